"""Random scenarios from a seed, for studies over thousands of runs.

Scenario ``index`` of seed ``seed`` (of a family) depends on those numbers only (its own
random stream, ``numpy.random.default_rng([seed, index])`` for the mix and
``[seed, index, n]`` for the family numbered ``n``), so a study of 1,000 scenarios is the
first 1,000 of a study of 100,000 and any worker can rebuild any slice of it.

Every scenario passes the gate a hand-written one does (:func:`controller.task_rules.check_task`,
every rule of what a task may ask), except that a task with no way round its obstacle
(``NoWayRoundError``) is kept, as a user would offer it: the controller refuses it, and the
study counts the refusals. On top come the generator's own rules (a draw that breaks one is
drawn again from the same stream):

- **waypoints kept clear** (the study's condition for "every waypoint passed within 2 mm"):
  every waypoint below the obstacle's top is at least :data:`WAYPOINT_CLEARANCE` clear of
  the inflated obstacle, and consecutive waypoints are at least :data:`MIN_SPACING` apart;
- the obstacle is either in the way (its inflated top above the whole planned path) or
  below it (its inflated top under the whole planned path), never cut by the plan's height,
  which no planar avoidance could handle;
- an obstacle in the way leaves room to go round it: its inflated section grown by
  :data:`PASSAGE` is reachable all round.

The default study, :attr:`Family.MIX`, is the one the law was tuned on: its cases
(:class:`Case`) take turns by index, so every case is in any study of at least ``len(Case)``
scenarios; its scenarios never change (the study's history is measured on them). The other
families (:class:`Family`) each test one thing the mix leaves out, drawn from their own
streams with their own numbers (:class:`Recipe`), and run for the scenario file's default
settling time. An obstacle near a reach limit cannot have room all round, so families that
place one drop that rule: whether a way round is left, the controller's plan check says
(and :mod:`sim.passability`'s brute force checks a sample of its refusals).
:attr:`Family.HELD_OUT`, and seeds from :data:`HELD_OUT_SEEDS` on of every family, are set
aside for judging the law once it is tuned: they are generated only when asked for by name
(``held_out=True``).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from enum import Enum
from typing import NamedTuple

import numpy as np

from controller.planner import plan_of
from controller.task_rules import check_task
from protocol.config import RobotConfig
from protocol.errors import ConfigError, KinematicsError, NoWayRoundError, ScaraError
from protocol.geometry import EllipticCylinder, to_world
from protocol.kinematics import Elbow, inverse, reach_radii
from protocol.scenario import (
    DEFAULT_MARGIN,
    DEFAULT_TOOL_RADIUS,
    Mode,
    Scenario,
    Waypoint,
)
from sim.edges import Edge, at_edge
from sim.measures import STOP_REST_MARGIN, crawl_speed, stop_threshold_and_rests


class Case(Enum):
    """What a generated scenario is made to test."""

    OPEN = "open"
    """Waypoints and obstacle anywhere (sometimes a low obstacle)."""
    ACROSS = "across"
    """The obstacle across a segment."""
    BACK_ACROSS = "back_across"
    """Past the obstacle to a waypoint, then back across it to the next."""
    DOORSTEP = "doorstep"
    """The obstacle on the way in, just before a waypoint."""
    BOUNDARY = "boundary"
    """Waypoints near the reach's outer or inner edge, the obstacle across a segment."""
    STRETCHED = "stretched"
    """Two waypoints near the stretched-arm singularity (theta2 of about 5-11 deg)."""
    BELOW = "below"
    """An obstacle across a segment but below the path: the arm passes over it."""


class Kind(Enum):
    """What a scenario of the families beyond the mix is made to test (besides its cases)."""

    INNER = "inner"
    """An obstacle across a segment, its inflated edge near the radius where theta2 meets its
    limit (:data:`LIMIT_BAND`): the way round on the base's side is narrow or closed."""
    OUTER = "outer"
    """An obstacle across a segment, its inflated edge near the full reach."""
    FAST = "fast"
    """The obstacle across a segment planned at :data:`FAST_SPEEDS`."""
    MULTI = "multi"
    """Waypoints zig-zagging across the obstacle: several detours in one task."""


class Family(Enum):
    """A selection of scenarios (``scara-compare --family``)."""

    MIX = "mix"
    """The seven cases the law was tuned on, in turn (the default; never changes)."""
    INNER = "inner"
    """:attr:`Kind.INNER` only."""
    OUTER = "outer"
    """:attr:`Kind.OUTER` only."""
    FAST = "fast"
    """:attr:`Kind.FAST` only, its other segments at up to the fast speed too."""
    MULTI = "multi"
    """:attr:`Kind.MULTI` only."""
    USER = "user"
    """Tasks as users of the paper's GUI wrote them: 3-6 waypoints, 0.08-0.35 m/s, the
    obstacle across a segment, at a doorstep or between two segments that double back."""
    WIDE = "wide"
    """:attr:`Kind.INNER` with obstacles 25-50 cm long: often neither side of one is open, and
    the plan check refuses the task (for measuring its refusals against the brute force)."""
    HELD_OUT = "held_out"
    """Every kind of the families above in turn, with numbers of its own: for judging the
    tuned law, never for tuning it."""
    EDGE_OBSTACLE = "edge_obstacle"
    """:attr:`USER`'s tasks with a waypoint at rule 4's edge (:mod:`sim.edges`)."""
    EDGE_LIMIT = "edge_limit"
    """... with a waypoint's joint at rule 3's edge."""
    EDGE_SPEED = "edge_speed"
    """... retimed so that the plan peaks at rule 7's edge."""
    EDGE_REACH = "edge_reach"
    """... with a waypoint at rule 2's outer edge."""


WAYPOINT_CLEARANCE = 0.02
"""m: least clearance between a waypoint and the inflated obstacle it is below the top of."""
DOORSTEP_CLEARANCE = (0.02, 0.03)
"""m: the clearance of the waypoint an obstacle stands at the doorstep of."""
MIN_SPACING = 0.05
"""m: least distance between consecutive waypoints."""
PASSAGE = 0.03
"""m: room kept reachable all round an obstacle in the way (AO passes 15 mm off it)."""
HEIGHT_GAP = 0.01
"""m: least vertical gap between the obstacle's inflated top and the planned path."""
SETTLE_TIME = 3.0
"""s after the last waypoint's time: the run's allowance for the time detours cost."""
SPEED_RANGE = (0.08, 0.22)
"""m/s: the planned mean speed of a segment is drawn from this range ..."""
MIN_SEGMENT_TIME = 1.0
"""... and a segment lasts at least this long (s)."""
ANGLE_RANGE = math.radians(90.0)
"""Waypoints lie within this angle either side of the x axis (theta1 stays within limits)."""
Z_RANGE = (0.20, 0.37)
"""m: heights of the waypoints (the tool reaches 0.187-0.387 m)."""
TALL_HEIGHT = (0.40, 0.45)
"""m: heights of an obstacle in the way (above every reachable tool height)."""
DIAMETER_RANGE = (0.03, 0.14)
"""m: the obstacle's long diameter; the short one is a fraction of it ..."""
ASPECT_RANGE = (0.3, 1.0)
"""... drawn from this range."""
STRETCHED_RADIUS = (0.9955, 0.9985)
"""Fraction of the full reach of the stretched case's waypoints (theta2 about 5-11 deg)."""
MAX_ATTEMPTS = 500
"""Draws per scenario before giving up (a valid one comes within a few)."""
PATH_SAMPLES = 2000
"""Planned points checked against the height and speed rules."""
BISECTIONS = 40
"""Halvings of the distance an obstacle is moved to its place (0.5 m / 2^40: far below a
micrometre)."""
LIMIT_BAND = 0.03
"""m: how far from a reach limit's radius (``protocol.kinematics.reach_radii``), either side,
an obstacle near that limit has its inflated edge. Inside the limit is where users saw the
arm fail: with the edge only outside it (0 to 30 mm), 200 such tasks never did."""
FAST_SPEEDS = (0.35, 0.40)
"""m/s: the planned mean speed of the fast kind's segment across the obstacle."""
USER_SPEEDS = (0.08, 0.35)
"""m/s: the segment speeds users wrote."""
WIDE_DIAMETERS = (0.25, 0.50)
"""m: the wide family's obstacles' long diameters."""
HELD_OUT_DIAMETERS = (0.02, 0.16)
"""m: the held-out family's obstacles' long diameters (the others': DIAMETER_RANGE)."""
HELD_OUT_SPEEDS = (0.06, 0.26)
"""m/s: the held-out family's segments near a limit or zig-zagging (the others': SPEED_RANGE)."""
HELD_OUT_SEEDS = 1_000_000
"""Seeds from this one on, of every family, are held out like :attr:`Family.HELD_OUT`."""

Point = tuple[float, float, float]


class Draw(NamedTuple):
    """Waypoints and an obstacle, before their times."""

    points: list[Point]
    obstacle: EllipticCylinder
    detour: int | None = None
    """The segment the obstacle was drawn across, if it was drawn across one."""


@dataclass(frozen=True, slots=True)
class Recipe:
    """A kind of scenario and the numbers it is drawn with (by default the mix's)."""

    case: Case | Kind
    """What it draws (:data:`_DRAWS`) and names its scenarios by."""
    waypoints: tuple[int, int] = (2, 6)
    """The least and most waypoints, where the kind does not fix their number."""
    speeds: tuple[float, float] = SPEED_RANGE
    """m/s: the range of each segment's planned mean speed ..."""
    fast_speeds: tuple[float, float] | None = None
    """... but this one's for the segment the obstacle was drawn across, if given."""
    settle_time: float | None = SETTLE_TIME
    """s; None: the scenario file's default."""
    diameters: tuple[float, float] = DIAMETER_RANGE
    """m: the range of the obstacle's long diameter."""
    near_limit: bool = False
    """An obstacle in the way has room all round it (:data:`PASSAGE`), unless it is placed
    near a reach limit (where the plan check decides whether a way round is left)."""


_INNER = Recipe(Kind.INNER, settle_time=None, near_limit=True)
_OUTER = replace(_INNER, case=Kind.OUTER)
_FAST = Recipe(
    Kind.FAST, speeds=(SPEED_RANGE[0], FAST_SPEEDS[1]), fast_speeds=FAST_SPEEDS, settle_time=None
)
_MULTI = Recipe(Kind.MULTI, settle_time=None)
_USER = tuple(
    Recipe(case, waypoints=(3, 6), speeds=USER_SPEEDS, settle_time=None, near_limit=True)
    for case in (Case.ACROSS, Case.DOORSTEP, Case.BACK_ACROSS)
)
FAMILIES: dict[Family, tuple[Recipe, ...]] = {
    Family.MIX: tuple(Recipe(case) for case in Case),
    Family.INNER: (_INNER,),
    Family.OUTER: (_OUTER,),
    Family.FAST: (_FAST,),
    Family.MULTI: (_MULTI,),
    Family.USER: _USER,
    Family.WIDE: (replace(_INNER, diameters=WIDE_DIAMETERS),),
    **dict.fromkeys(
        (Family.EDGE_OBSTACLE, Family.EDGE_LIMIT, Family.EDGE_SPEED, Family.EDGE_REACH), _USER
    ),
    Family.HELD_OUT: tuple(
        replace(recipe, diameters=HELD_OUT_DIAMETERS)
        for recipe in (
            replace(_INNER, speeds=HELD_OUT_SPEEDS),
            replace(_OUTER, speeds=HELD_OUT_SPEEDS),
            replace(_FAST, speeds=(HELD_OUT_SPEEDS[0], FAST_SPEEDS[1])),
            replace(_MULTI, speeds=HELD_OUT_SPEEDS),
            *_USER,
        )
    ),
}
"""Each family's recipes, taking turns by index."""
_STREAMS = {
    Family.INNER: 1,
    Family.OUTER: 2,
    Family.FAST: 3,
    Family.MULTI: 4,
    Family.USER: 5,
    Family.HELD_OUT: 6,
    Family.WIDE: 7,
    Family.EDGE_OBSTACLE: 8,
    Family.EDGE_LIMIT: 9,
    Family.EDGE_SPEED: 10,
    Family.EDGE_REACH: 11,
}
"""Each family's own random streams beyond the mix's (a new family takes a new number)."""


def is_held_out(family: Family, seed: int) -> bool:
    """Whether these scenarios are set aside for judging the tuned law."""
    return family is Family.HELD_OUT or seed >= HELD_OUT_SEEDS


def generate_scenarios(
    count: int,
    seed: int,
    mode: Mode = Mode.FUZZY,
    family: Family = Family.MIX,
    *,
    held_out: bool = False,
) -> list[Scenario]:
    """The first ``count`` scenarios of ``family``'s study with ``seed``, in ``mode``."""
    return [
        generate_scenario_at(seed, index, mode, family, held_out=held_out) for index in range(count)
    ]


def generate_scenario_at(
    seed: int,
    index: int,
    mode: Mode = Mode.FUZZY,
    family: Family = Family.MIX,
    *,
    held_out: bool = False,
) -> Scenario:
    """Scenario ``index`` of ``family``'s study with ``seed``: the same numbers, the same
    scenario. A held-out one (:func:`is_held_out`) only with ``held_out``."""
    if seed < 0 or index < 0:
        raise ConfigError("seed" if seed < 0 else "index", "must not be negative")
    if is_held_out(family, seed) and not held_out:
        raise ConfigError(
            "family" if family is Family.HELD_OUT else "seed",
            f"family {family.value}, seed {seed} is held out for judging the tuned law "
            f"(family {Family.HELD_OUT.value}, or a seed from {HELD_OUT_SEEDS}); ask with "
            "held_out=True",
        )
    recipes = FAMILIES[family]
    recipe = recipes[index % len(recipes)]
    if family is Family.MIX:
        rng = np.random.default_rng([seed, index])
        name = f"gen-{seed}-{index}-{recipe.case.value}"
    else:
        rng = np.random.default_rng([seed, index, _STREAMS[family]])
        name = f"{family.value}-{seed}-{index}-{recipe.case.value}"
    if family.value.startswith("edge_"):
        edge = Edge(family.value)
        for _ in range(MAX_ATTEMPTS):
            moved = at_edge(generate_scenario(rng, recipe, name), edge, rng)
            if moved is not None:
                return moved.with_mode(mode)
        raise ScaraError(f"no task at {edge.value} in {MAX_ATTEMPTS} draws ({name})")
    return generate_scenario(rng, recipe, name).with_mode(mode)


def generate_scenario(
    rng: np.random.Generator, recipe: Case | Recipe, name: str, robot: RobotConfig | None = None
) -> Scenario:
    """A valid scenario of ``recipe`` (a case: the mix's) from ``rng`` (invalid draws are
    drawn again)."""
    robot = robot or RobotConfig()
    if isinstance(recipe, Case):
        recipe = Recipe(recipe)
    for _ in range(MAX_ATTEMPTS):
        draw = _DRAWS[recipe.case](rng, robot, recipe)
        scenario = _timed_scenario(name, draw, rng, robot, recipe)
        if scenario is not None:
            return scenario
    raise ScaraError(f"no valid {recipe.case.value} scenario in {MAX_ATTEMPTS} draws ({name})")


def case_of(scenario: Scenario) -> Case:
    """The case of a generated scenario of the mix, from its name."""
    return Case(scenario.name.rsplit("-", 1)[-1])


def waypoints_clear(scenario: Scenario, room: float = WAYPOINT_CLEARANCE) -> bool:
    """Every waypoint reachable and, if below the obstacle's inflated top, at least ``room``
    clear of the inflated obstacle: the scenarios whose waypoints must all be passed."""
    obstacle = scenario.obstacle
    for point in scenario.waypoints:
        try:
            inverse(scenario.robot, point.x, point.y, point.z, scenario.elbow)
        except KinematicsError:
            return False
        if (
            obstacle is not None
            and point.z < obstacle.height + obstacle.inflation
            and obstacle.clearance(point.x, point.y) < room - 1e-9
        ):
            return False
    return True


# --- building blocks --------------------------------------------------------------------------


def _polar(rng: np.random.Generator, radius: tuple[float, float]) -> Point:
    r = rng.uniform(*radius)
    angle = rng.uniform(-ANGLE_RANGE, ANGLE_RANGE)
    return (r * math.cos(angle), r * math.sin(angle), rng.uniform(*Z_RANGE))


def _reach(robot: RobotConfig, inner: float, outer: float) -> tuple[float, float]:
    """The reachable radii less ``inner`` at the inside and ``outer`` at the outside."""
    low, high = reach_radii(robot)
    return (low + inner, high - outer)


def _random_points(rng: np.random.Generator, robot: RobotConfig, count: int) -> list[Point]:
    return [_polar(rng, _reach(robot, 0.05, 0.03)) for _ in range(count)]


def _count(rng: np.random.Generator, recipe: Recipe) -> int:
    least, most = recipe.waypoints
    return int(rng.integers(least, most + 1))


def _around(
    rng: np.random.Generator, robot: RobotConfig, recipe: Recipe, crossing: list[Point]
) -> list[Point]:
    """``crossing`` with random waypoints before and after it, as many as the recipe allows."""
    least, most = recipe.waypoints
    extra = int(rng.integers(max(0, least - len(crossing)), most - len(crossing) + 1))
    before = int(rng.integers(0, extra + 1))
    return (
        _random_points(rng, robot, before) + crossing + _random_points(rng, robot, extra - before)
    )


def _obstacle(
    rng: np.random.Generator, x: float, y: float, recipe: Recipe, height: float | None = None
) -> EllipticCylinder:
    """An elliptic cylinder of random size and yaw at (x, y); tall unless ``height`` is given."""
    long_diameter = rng.uniform(*recipe.diameters)
    return EllipticCylinder(
        x=x,
        y=y,
        long_diameter=long_diameter,
        short_diameter=long_diameter * rng.uniform(*ASPECT_RANGE),
        height=rng.uniform(*TALL_HEIGHT) if height is None else height,
        yaw=rng.uniform(0.0, math.pi),
        inflation=DEFAULT_TOOL_RADIUS + DEFAULT_MARGIN,
    )


def _moved(obstacle: EllipticCylinder, x: float, y: float) -> EllipticCylinder:
    return EllipticCylinder(
        x,
        y,
        obstacle.long_diameter,
        obstacle.short_diameter,
        obstacle.height,
        obstacle.yaw,
        obstacle.inflation,
    )


def _placed(
    obstacle: EllipticCylinder,
    x: float,
    y: float,
    direction: float,
    measure: Callable[[EllipticCylinder], float],
    wanted: float,
    far: float = 0.5,
) -> EllipticCylinder:
    """``obstacle`` moved from (x, y) along ``direction`` to where ``measure`` of it (which
    grows with the distance, up to ``far``) is ``wanted``."""
    near = 0.0
    for _ in range(BISECTIONS):
        middle = 0.5 * (near + far)
        trial = _moved(obstacle, x + middle * math.cos(direction), y + middle * math.sin(direction))
        if measure(trial) < wanted:
            near = middle
        else:
            far = middle
    return _moved(obstacle, x + far * math.cos(direction), y + far * math.sin(direction))


def _farthest(obstacle: EllipticCylinder) -> float:
    """How far from the base axis the inflated section reaches (its boundary sampled every
    half degree of its parameter: within a micrometre)."""
    a, b = obstacle.semi_axes
    angles = np.linspace(0.0, 2.0 * math.pi, 720, endpoint=False)
    x, y = to_world(obstacle.section(), a * np.cos(angles), b * np.sin(angles))
    return float(np.hypot(x, y).max())


def _across(rng: np.random.Generator, start: Point, end: Point, recipe: Recipe) -> EllipticCylinder:
    """An obstacle across the chord from ``start`` to ``end``: its centre between 35 % and
    65 % of the way, off the chord by at most half its short semi-axis."""
    share = rng.uniform(0.35, 0.65)
    probe = _obstacle(rng, 0.0, 0.0, recipe)
    dx, dy = end[0] - start[0], end[1] - start[1]
    length = max(math.hypot(dx, dy), 1e-9)
    offset = rng.uniform(-0.5, 0.5) * probe.semi_axes[1]
    x = start[0] + share * dx - offset * dy / length
    y = start[1] + share * dy + offset * dx / length
    return _moved(probe, x, y)


def _across_a_segment(rng: np.random.Generator, points: list[Point], recipe: Recipe) -> Draw:
    segment = int(rng.integers(0, len(points) - 1))
    return Draw(points, _across(rng, points[segment], points[segment + 1], recipe), segment)


def _through(rng: np.random.Generator, obstacle: EllipticCylinder, heading: float) -> list[Point]:
    """Two waypoints either side of ``obstacle`` on a chord along ``heading`` that passes its
    centre by at most half its short semi-axis: a segment the obstacle is across."""
    a, b = obstacle.semi_axes
    offset = rng.uniform(-0.5, 0.5) * b
    x = obstacle.x - offset * math.sin(heading)
    y = obstacle.y + offset * math.cos(heading)
    z = rng.uniform(*Z_RANGE)
    ends = []
    for side in (-1.0, 1.0):
        distance = side * (a + WAYPOINT_CLEARANCE + rng.uniform(0.01, 0.12))
        ends.append(
            (
                x + distance * math.cos(heading),
                y + distance * math.sin(heading),
                z + rng.uniform(-0.02, 0.02),
            )
        )
    return ends


# --- the cases ---------------------------------------------------------------------------------


def _draw_open(rng: np.random.Generator, robot: RobotConfig, recipe: Recipe) -> Draw:
    points = _random_points(rng, robot, _count(rng, recipe))
    x, y, _ = _polar(rng, _reach(robot, 0.08, 0.06))
    low = rng.random() < 0.3
    return Draw(points, _obstacle(rng, x, y, recipe, rng.uniform(0.03, 0.12) if low else None))


def _draw_across(rng: np.random.Generator, robot: RobotConfig, recipe: Recipe) -> Draw:
    return _across_a_segment(rng, _random_points(rng, robot, _count(rng, recipe)), recipe)


def _draw_back_across(rng: np.random.Generator, robot: RobotConfig, recipe: Recipe) -> Draw:
    x, y, _ = _polar(rng, _reach(robot, 0.15, 0.15))
    obstacle = _obstacle(rng, x, y, recipe)
    reach = obstacle.semi_axes[0] + WAYPOINT_CLEARANCE
    direction = rng.uniform(-math.pi, math.pi)
    legs = []
    for turn, distance in (
        (0.0, reach + rng.uniform(0.02, 0.10)),
        (math.pi + rng.uniform(-0.4, 0.4), reach + rng.uniform(0.0, 0.05)),
        (rng.uniform(-0.6, 0.6), reach + rng.uniform(0.02, 0.10)),
    ):
        angle = direction + turn
        legs.append((x + distance * math.cos(angle), y + distance * math.sin(angle)))
    z = rng.uniform(*Z_RANGE)
    crossing = [(px, py, z + rng.uniform(-0.02, 0.02)) for px, py in legs]
    return Draw(_around(rng, robot, recipe, crossing), obstacle)


def _draw_doorstep(rng: np.random.Generator, robot: RobotConfig, recipe: Recipe) -> Draw:
    points = _random_points(rng, robot, _count(rng, recipe))
    index = int(rng.integers(1, len(points)))
    target, previous = points[index], points[index - 1]
    back = math.atan2(previous[1] - target[1], previous[0] - target[0])
    direction = back + rng.uniform(-0.5, 0.5)
    obstacle = _obstacle(rng, target[0], target[1], recipe)
    wanted = rng.uniform(*DOORSTEP_CLEARANCE)
    x, y = target[0], target[1]
    return Draw(points, _placed(obstacle, x, y, direction, lambda o: o.clearance(x, y), wanted))


def _draw_boundary(rng: np.random.Generator, robot: RobotConfig, recipe: Recipe) -> Draw:
    low, high = reach_radii(robot)
    points = []
    for _ in range(_count(rng, recipe)):
        band = (high - 0.06, high - 0.008) if rng.random() < 0.6 else (low + 0.005, low + 0.05)
        points.append(_polar(rng, band) if rng.random() < 0.7 else _random_points(rng, robot, 1)[0])
    return _across_a_segment(rng, points, recipe)


def _draw_stretched(rng: np.random.Generator, robot: RobotConfig, recipe: Recipe) -> Draw:
    high = reach_radii(robot)[1]
    count = int(rng.integers(3, 7))
    first = int(rng.integers(0, count - 1))
    points = _random_points(rng, robot, count)
    anchor = rng.uniform(-ANGLE_RANGE + 0.3, ANGLE_RANGE - 0.3)
    for offset, index in enumerate((first, first + 1)):
        radius = high * rng.uniform(*STRETCHED_RADIUS)
        angle = anchor + (offset - 0.5) * rng.uniform(0.15, 0.4)
        points[index] = (radius * math.cos(angle), radius * math.sin(angle), points[index][2])
    # The obstacle across a segment that leaves or reaches the stretched pair.
    if first + 2 < count and (first == 0 or rng.random() < 0.5):
        segment = first + 1
    elif first > 0:
        segment = first - 1
    else:
        segment = first
    return Draw(points, _across(rng, points[segment], points[segment + 1], recipe), segment)


def _draw_below(rng: np.random.Generator, robot: RobotConfig, recipe: Recipe) -> Draw:
    points, obstacle, segment = _draw_across(rng, robot, recipe)
    top = min(p[2] for p in points) - obstacle.inflation - HEIGHT_GAP
    return Draw(
        points,
        EllipticCylinder(
            obstacle.x,
            obstacle.y,
            obstacle.long_diameter,
            obstacle.short_diameter,
            rng.uniform(0.3, 0.9) * top,
            obstacle.yaw,
            obstacle.inflation,
        ),
        segment,
    )


def _draw_near_limit(rng: np.random.Generator, robot: RobotConfig, recipe: Recipe) -> Draw:
    """An obstacle whose inflated edge is within LIMIT_BAND of the inner or the outer reach
    limit's radius, and a segment across it running round the base (within 0.5 rad)."""
    low, high = reach_radii(robot)
    angle = rng.uniform(-ANGLE_RANGE, ANGLE_RANGE)
    probe = _obstacle(rng, 0.0, 0.0, recipe)
    gap = rng.uniform(-LIMIT_BAND, LIMIT_BAND)
    if recipe.case is Kind.INNER:
        obstacle = _placed(probe, 0.0, 0.0, angle, lambda o: o.clearance(0.0, 0.0), low + gap)
    else:
        obstacle = _placed(probe, 0.0, 0.0, angle, _farthest, high - gap, far=2.0 * high)
    heading = angle + math.pi / 2.0 + rng.uniform(-0.5, 0.5)
    return Draw(_around(rng, robot, recipe, _through(rng, obstacle, heading)), obstacle)


def _draw_multi(rng: np.random.Generator, robot: RobotConfig, recipe: Recipe) -> Draw:
    """Three to five waypoints on alternate sides of the obstacle (up to the recipe's most)."""
    x, y, _ = _polar(rng, _reach(robot, 0.15, 0.15))
    obstacle = _obstacle(rng, x, y, recipe)
    reach = obstacle.semi_axes[0] + WAYPOINT_CLEARANCE
    direction = rng.uniform(-math.pi, math.pi)
    z = rng.uniform(*Z_RANGE)
    crossing = []
    for side in range(int(rng.integers(3, min(5, recipe.waypoints[1]) + 1))):
        angle = direction + side * math.pi + rng.uniform(-0.3, 0.3)
        distance = reach + rng.uniform(0.02, 0.10)
        crossing.append(
            (
                x + distance * math.cos(angle),
                y + distance * math.sin(angle),
                z + rng.uniform(-0.02, 0.02),
            )
        )
    return Draw(_around(rng, robot, recipe, crossing), obstacle)


_DRAWS: dict[Case | Kind, Callable[[np.random.Generator, RobotConfig, Recipe], Draw]] = {
    Case.OPEN: _draw_open,
    Case.ACROSS: _draw_across,
    Case.BACK_ACROSS: _draw_back_across,
    Case.DOORSTEP: _draw_doorstep,
    Case.BOUNDARY: _draw_boundary,
    Case.STRETCHED: _draw_stretched,
    Case.BELOW: _draw_below,
    Kind.INNER: _draw_near_limit,
    Kind.OUTER: _draw_near_limit,
    Kind.FAST: _draw_across,
    Kind.MULTI: _draw_multi,
}


# --- checks --------------------------------------------------------------------------------------


def _timed_scenario(
    name: str, draw: Draw, rng: np.random.Generator, robot: RobotConfig, recipe: Recipe
) -> Scenario | None:
    """The scenario through the drawn points with timed segments, or None if a rule refuses
    it."""
    pairs = list(itertools.pairwise(draw.points))
    if any(math.dist(first, second) < MIN_SPACING for first, second in pairs):
        return None
    times = [0.0]
    for segment, (first, second) in enumerate(pairs):
        speeds = recipe.speeds
        if recipe.fast_speeds is not None and segment == draw.detour:
            speeds = recipe.fast_speeds
        duration = max(MIN_SEGMENT_TIME, math.dist(first, second) / rng.uniform(*speeds))
        times.append(round(times[-1] + duration, 3))
    obstacle = _as_written(draw.obstacle)
    scenario = Scenario(
        name=name,
        waypoints=tuple(
            Waypoint(t, round(x, 4), round(y, 4), round(z, 4))
            for t, (x, y, z) in zip(times, draw.points, strict=True)
        ),
        obstacle=obstacle,
        robot=robot,
        tool_radius=DEFAULT_TOOL_RADIUS,
    )
    if recipe.settle_time is not None:
        scenario = replace(scenario, settle_time=recipe.settle_time)
    try:
        check_task(scenario)
    except NoWayRoundError:
        pass  # offered as a user would: the controller refuses it, and the study counts that
    except ConfigError:
        return None
    return scenario if _fits_the_rules(scenario, obstacle, recipe) else None


def _as_written(obstacle: EllipticCylinder) -> EllipticCylinder:
    """``obstacle`` to a tenth of a millimetre and a thousandth of a degree, as a scenario
    file would give it (so that the file of a generated scenario reads back the same)."""
    return EllipticCylinder(
        round(obstacle.x, 4),
        round(obstacle.y, 4),
        round(obstacle.long_diameter, 4),
        round(obstacle.short_diameter, 4),
        round(obstacle.height, 4),
        math.radians(round(math.degrees(obstacle.yaw), 3)),
        obstacle.inflation,
    )


def _fits_the_rules(scenario: Scenario, obstacle: EllipticCylinder, recipe: Recipe) -> bool:
    """The generator's own rules (module docstring) on top of the scenario checks."""
    if not (_tests_its_kind(scenario, obstacle, recipe) and _moves_sensibly(scenario)):
        return False
    plan = plan_of(scenario)
    start, end = scenario.waypoints[0].t, scenario.waypoints[-1].t
    heights = plan.sample(np.linspace(start, end, PATH_SAMPLES))[0][:, 2]
    top = obstacle.height + obstacle.inflation
    if heights.min() > top + HEIGHT_GAP:
        return True  # the path passes over it
    if heights.max() > top - HEIGHT_GAP or not waypoints_clear(scenario):
        return False
    if recipe.near_limit:
        return True
    a, b = obstacle.semi_axes
    for angle in np.linspace(0.0, 2.0 * math.pi, 36, endpoint=False):
        x, y = obstacle.to_world((a + PASSAGE) * math.cos(angle), (b + PASSAGE) * math.sin(angle))
        try:
            inverse(scenario.robot, x, y, float(heights[0]), Elbow.DOWN)
        except KinematicsError:
            return False
    return True


def _tests_its_kind(scenario: Scenario, obstacle: EllipticCylinder, recipe: Recipe) -> bool:
    """What the recipe is made to test holds of the scenario as written (rounding to a tenth
    of a millimetre and to whole milliseconds may have moved it)."""
    low, high = reach_radii(scenario.robot)
    if recipe.case is Kind.INNER and abs(obstacle.clearance(0.0, 0.0) - low) > LIMIT_BAND:
        return False
    if recipe.case is Kind.OUTER and abs(high - _farthest(obstacle)) > LIMIT_BAND:
        return False
    pairs = list(itertools.pairwise(scenario.waypoints))
    if recipe.fast_speeds is not None:
        speeds = [math.dist(_xyz(a), _xyz(b)) / (b.t - a.t) for a, b in pairs]
        if max(speeds) < recipe.fast_speeds[0]:
            return False
    crossed = 0
    for a, b in pairs:
        crossings = obstacle.line_crossings(a.x, a.y, b.x, b.y)
        crossed += crossings is not None and crossings[0] < 1.0 and crossings[1] > 0.0
    return crossed >= _LEAST_CROSSED.get(recipe.case, 0)


_LEAST_CROSSED: dict[Case | Kind, int] = {Kind.INNER: 1, Kind.OUTER: 1, Kind.MULTI: 2}
"""How many segments' chords the obstacle of a kind lies across, at least."""


def _xyz(point: Waypoint) -> Point:
    return (point.x, point.y, point.z)


def _moves_sensibly(scenario: Scenario) -> bool:
    """The plan never crawls (below :func:`~sim.measures.crawl_speed`) except within
    STOP_REST_MARGIN of a waypoint it stops at: a crawl is where the stop measure cannot
    tell a lagging arm from a stopped one (the wire's velocity quantum is 1e-3 rad/s)."""
    plan = plan_of(scenario)
    threshold, rest_indices = stop_threshold_and_rests(plan)
    rests = np.array([plan.times[index] for index in rest_indices])
    crawl = crawl_speed(threshold)
    times = np.linspace(scenario.waypoints[0].t, scenario.waypoints[-1].t, PATH_SAMPLES)
    velocities = plan.sample(times)[1].tolist()
    speeds = np.array([math.hypot(vx, vy) for vx, vy, _ in velocities])
    near_rest = np.any(np.abs(times[:, None] - rests[None, :]) <= STOP_REST_MARGIN, axis=1)
    crawling = (speeds < crawl) & ~near_rest
    return not crawling.any()
