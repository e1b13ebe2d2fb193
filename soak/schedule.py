"""What a soak does and when, as a pure function of its seed: the disturbances, the wire
faults of each node's every start, and the tasks the operator runs.

Rerunning a seed replays the same schedule (the system's own timing is not the seed's: the
same disturbance may meet the arm elsewhere on its way). Times are seconds from the moment
the stack first answers ready.
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from enum import Enum

from controller.service import with_approach
from controller.task_rules import load_task
from protocol.errors import ConfigError
from protocol.faults import FaultSpec
from protocol.scenario import Mode, Scenario
from sim.generator import Family, generate_scenario_at

PROCESSES = ("can_router", "keys_router", "plant", "controller", "bridge", "recorder")
"""The processes of the robot as a service, by the names the soak gives them."""
NODES = ("plant", "controller")
"""The processes that send the loop's frames: their wire faults are injected."""
HOME_SCENARIO = "reference"
"""The scenario the plant starts from (and returns to on a reset): its first waypoint is the
arm's home, where a run may begin."""
TASK_FAMILIES = (Family.MIX, Family.USER, Family.MULTI, Family.FAST)
"""Where the tasks come from, in turn (the families whose obstacles stand clear of the reach
limits: a soak tests the service, the study tests the law near its limits)."""
LONGEST_TASK = 9.0
"""s a task may be planned for, settling included: a soak tests the service, the study long
tasks; a disturbance comes every few seconds, so that a longer one seldom ends done."""
HOME_ROOM = 0.02
"""m the inflated obstacle of a task keeps clear of the home: the safety filter's room to
move off from there."""
PAUSE = (0.010, 0.500)
"""s a process is stopped for (SIGSTOP, then SIGCONT)."""
DROP, CORRUPT, DUPLICATE, REORDER = 0.10, 0.02, 0.01, 0.01
"""The largest share of a node's frames its wire drops, corrupts, duplicates, reorders."""
FLOOD = (0.5, 3.0)
"""s a flood of foreign CAN IDs lasts."""
FLOOD_RATE = 1000.0
"""Foreign frames per second in a flood: about what the loop itself puts on the bus."""
BURST = (2, 6)
"""Commands in an e-stop, stop or read-only burst."""
MEAN_GAP = 6.0
"""s between disturbances, on average (from half to one and a half times it)."""
FIRST = 3.0
"""s before the first disturbance: the first task under way."""
QUIET_END = 10.0
"""s at the end with no disturbance: the last one recovered from before the soak ends."""


class Kind(Enum):
    """A kind of disturbance."""

    PAUSE = "pause"
    """SIGSTOP of a process for :data:`PAUSE` s."""
    KILL = "kill"
    """SIGKILL of a process, and its restart."""
    FLOOD = "flood"
    """Foreign CAN IDs (standard ones the DBC does not define, and extended ones)."""
    RUN_TWICE = "run_twice"
    """Run, and run again at once (the second while running)."""
    OBSTACLE_IN_RUN = "obstacle_in_run"
    """Set an obstacle while the arm runs."""
    RESET = "reset"
    """A reset at whatever moment (during a run, during a fault)."""
    ESTOP_BURST = "estop_burst"
    """E-stops in a burst, then a reset."""
    STOP_BURST = "stop_burst"
    """Stops in a burst."""
    READ_ONLY = "read_only"
    """Commands from the read-only user, which must reach nothing."""


WEIGHTS = {
    Kind.PAUSE: 6,
    Kind.KILL: 3,
    Kind.FLOOD: 1,
    Kind.RUN_TWICE: 1,
    Kind.OBSTACLE_IN_RUN: 1,
    Kind.RESET: 1,
    Kind.ESTOP_BURST: 1,
    Kind.STOP_BURST: 1,
    Kind.READ_ONLY: 1,
}
"""How often each kind comes, relatively."""


@dataclass(frozen=True, slots=True)
class Disturbance:
    at: float
    """s from the start of the soak."""
    kind: Kind
    target: str = ""
    """The process of a pause or kill."""
    duration: float = 0.0
    """s of a pause or a flood."""
    count: int = 1
    """Commands of a burst."""

    def describe(self) -> str:
        what = self.kind.value + (f" {self.target}" if self.target else "")
        if self.duration:
            what += f" {self.duration * 1000:.0f} ms"
        if self.count > 1:
            what += f" x{self.count}"
        return what


@dataclass(frozen=True, slots=True)
class Schedule:
    seed: int
    minutes: float
    disturbances: tuple[Disturbance, ...]


def make_schedule(seed: int, minutes: float) -> Schedule:
    """The disturbances of a soak of ``minutes`` with ``seed``."""
    draw = random.Random(f"soak-{seed}-disturbances")
    end = minutes * 60.0 - QUIET_END
    kinds = list(WEIGHTS)
    weights = [WEIGHTS[kind] for kind in kinds]
    found: list[Disturbance] = []
    at = FIRST
    while at < end:
        kind = draw.choices(kinds, weights)[0]
        found.append(_disturbance(draw, at, kind))
        at += draw.uniform(0.5, 1.5) * MEAN_GAP
    return Schedule(seed, minutes, tuple(found))


def _disturbance(draw: random.Random, at: float, kind: Kind) -> Disturbance:
    if kind is Kind.PAUSE:
        return Disturbance(at, kind, draw.choice(PROCESSES), round(draw.uniform(*PAUSE), 3))
    if kind is Kind.KILL:
        return Disturbance(at, kind, draw.choice(PROCESSES))
    if kind is Kind.FLOOD:
        return Disturbance(at, kind, duration=round(draw.uniform(*FLOOD), 3))
    if kind in (Kind.ESTOP_BURST, Kind.STOP_BURST, Kind.READ_ONLY):
        return Disturbance(at, kind, count=draw.randint(*BURST))
    return Disturbance(at, kind)


def wire_faults(seed: int, node: str, start: int) -> FaultSpec:
    """The wire faults of ``node``'s ``start``-th start (0 the first): a fresh share of each,
    up to :data:`DROP`, :data:`CORRUPT`, :data:`DUPLICATE` and :data:`REORDER`."""
    draw = random.Random(f"soak-{seed}-wire-{node}-{start}")
    return FaultSpec(
        drop=round(draw.uniform(0.0, DROP), 4),
        corrupt=round(draw.uniform(0.0, CORRUPT), 4),
        seed=draw.randrange(2**31),
        duplicate=round(draw.uniform(0.0, DUPLICATE), 4),
        reorder=round(draw.uniform(0.0, REORDER), 4),
    )


def home() -> Scenario:
    """The scenario whose first waypoint is the arm's home (:data:`HOME_SCENARIO`)."""
    return load_task(HOME_SCENARIO)


def task(seed: int, number: int, start: Scenario) -> Scenario:
    """The ``number``-th task of the soak (0 the first): the next generated scenario, of
    :data:`TASK_FAMILIES` in turn, in a mode drawn from the seed, that is feasible from the
    home of ``start`` (its plan, led there by the controller's approach segment, passes the
    controller's checks), no longer than :data:`LONGEST_TASK`, and whose inflated obstacle
    leaves that home clear (a reset or a restarted plant puts the arm there)."""
    draw = random.Random(f"soak-{seed}-task-{number}")
    family = TASK_FAMILIES[number % len(TASK_FAMILIES)]
    mode = draw.choice(list(Mode))
    home_point = start.waypoints[0]
    for attempt in range(1000):
        index = number * 1000 + attempt
        scenario = generate_scenario_at(seed, index, mode, family)
        if scenario.duration > LONGEST_TASK:
            continue
        obstacle = scenario.obstacle
        if obstacle is not None and obstacle.grown(HOME_ROOM).holds(
            home_point.x, home_point.y, home_point.z
        ):
            continue
        try:
            with_approach(scenario, (home_point.x, home_point.y, home_point.z))
        except ConfigError:
            continue
        return scenario
    raise ConfigError("seed", f"no feasible task {number} for seed {seed}")
