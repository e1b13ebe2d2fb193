"""Scenarios as TOML files: waypoints with times, the obstacle, the mode, the rates.

A scenario is what the controller and the plant agree to run, so it is part of the protocol:
both processes read the same file. It is checked whole before anything moves: against its
JSON Schema (``scenario-file``, or ``task`` for a task an operator sends: every value finite,
the number of waypoints capped, ...), then for what a schema cannot say: times increasing,
every waypoint reachable within the joint limits and outside the obstacle, the run not too
long, and the robot's ranges within what the wire carries. (The controller adds its own check
of the planned path, :func:`controller.planner.check_plan`.) Errors are :class:`ConfigError`
and name the field (``waypoints[2].x``, ``obstacle.height``, ...).
"""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from enum import Enum
from itertools import pairwise
from pathlib import Path
from typing import Any

from protocol.config import ControllerConfig, PlantConfig, RobotConfig
from protocol.errors import (
    ConfigError,
    KinematicsError,
    UnreachableWaypointError,
    WaypointInObstacleError,
)
from protocol.geometry import EllipticCylinder
from protocol.isotp_link import MAX_PAYLOAD
from protocol.kinematics import Elbow, inverse
from protocol.messages import COMMAND, STATE
from protocol.validation import check, read_json

SCENARIO_DIR = Path(__file__).resolve().parent.parent / "scenarios"
WAYPOINT_TOLERANCE = 0.002
"""m: a waypoint counts as passed when the TCP comes this close."""
MAX_DURATION = 3600.0
"""s: the longest a run may last: its timeout, and so its plan (the waypoints' span plus the
settling time), are at most this. It bounds a run's log (500 Hz: 1.8 million rows)."""
NO_PROGRESS_TIME = 5.0
"""s: a task's ``no_progress_time`` unless it sets one."""
TIMEOUT_FACTOR = 2.0
"""A scenario's default timeout is this many times its plan's span, plus the settling time
and TIMEOUT_ALLOWANCE (at most MAX_DURATION): beyond what a detour costs on a feasible task,
a short plan's round a large obstacle included. A run that makes no progress ends long before
(its ``no_progress_time``): the timeout is the last resort."""
TIMEOUT_ALLOWANCE = 10.0
DEFAULT_TOOL_RADIUS = 0.01
DEFAULT_MARGIN = 0.01


class Mode(Enum):
    """How PT and AO are blended: the fuzzy coordinator or the conventional hard switch."""

    FUZZY = "fuzzy"
    CONVENTIONAL = "conventional"


@dataclass(frozen=True, slots=True)
class Waypoint:
    t: float
    x: float
    y: float
    z: float


@dataclass(frozen=True, slots=True)
class Scenario:
    name: str
    waypoints: tuple[Waypoint, ...]
    obstacle: EllipticCylinder | None
    mode: Mode = Mode.FUZZY
    elbow: Elbow = Elbow.DOWN
    settle_time: float = 1.0
    timeout: float | None = None
    """s from the first waypoint after which a run that is not done ends in a fault; None: the
    default (:attr:`time_limit`)."""
    no_progress_time: float = NO_PROGRESS_TIME
    """s of plan without progress that end a run (:mod:`controller.run_end`)."""
    description: str = ""
    robot: RobotConfig = field(default_factory=RobotConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    plant: PlantConfig = field(default_factory=PlantConfig)
    tool_radius: float = 0.01

    def initial_joints(self) -> tuple[float, float, float]:
        first = self.waypoints[0]
        return inverse(self.robot, first.x, first.y, first.z, self.elbow)

    @property
    def duration(self) -> float:
        """Planned time plus the settling time after the last waypoint."""
        return self.waypoints[-1].t - self.waypoints[0].t + self.settle_time

    @property
    def time_limit(self) -> float:
        """The timeout in force: the scenario's own, else TIMEOUT_FACTOR times the plan's
        span plus the settling time and TIMEOUT_ALLOWANCE, at most MAX_DURATION."""
        if self.timeout is not None:
            return self.timeout
        span = self.waypoints[-1].t - self.waypoints[0].t
        return min(TIMEOUT_FACTOR * span + self.settle_time + TIMEOUT_ALLOWANCE, MAX_DURATION)

    def with_mode(self, mode: Mode) -> Scenario:
        return replace(self, mode=mode)

    def with_rate(self, rate_hz: float) -> Scenario:
        """The same scenario with another control rate (the plant steps at the same rate)."""
        return replace(self, controller=replace(self.controller, rate_hz=rate_hz))


def load_scenario(source: str | Path) -> Scenario:
    """A scenario from a TOML file, or by name from the packaged ``scenarios/`` folder."""
    path = Path(source)
    if not path.exists() and not path.suffix:
        path = SCENARIO_DIR / f"{source}.toml"
    if not path.exists():
        known = ", ".join(sorted(p.stem for p in SCENARIO_DIR.glob("*.toml")))
        raise ConfigError("scenario", f"no file {str(source)!r} (packaged scenarios: {known})")
    try:
        text = path.read_bytes().decode()
    except OSError as error:  # a directory, no permission
        raise ConfigError(str(path), f"cannot be read: {error.strerror}") from None
    except UnicodeDecodeError as error:
        raise ConfigError(str(path), f"not UTF-8 text: {error}") from None
    try:
        document = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(str(path), f"not valid TOML: {error}") from error
    except RecursionError:  # tomllib parses nested arrays and tables recursively
        raise ConfigError(str(path), "not valid TOML: nested too deeply") from None
    return parse_scenario(document, default_name=path.stem)


def parse_scenario(document: Mapping[str, Any], default_name: str = "scenario") -> Scenario:
    """Build and fully check a scenario from its TOML tables."""
    check(document, "scenario-file.schema.json")
    base = Scenario(
        "",
        (),
        None,
        robot=RobotConfig.from_table(document.get("robot", {})),
        controller=ControllerConfig.from_table(document.get("controller", {})),
        plant=PlantConfig(**document.get("plant", {})),
    )
    return _with_task(base, document, document.get("name", default_name))


def parse_task(document: Mapping[str, Any], base: Scenario) -> Scenario:
    """A scenario from a task document (what an operator sets: name, mode, waypoints,
    obstacle, settling time, timeout, elbow) on ``base``'s robot, gains and plant model,
    checked as a scenario file is. The JSON an operator sends over the wire
    (:func:`encode_task`)."""
    check(document, "task.schema.json")
    task = _with_task(base, document, document.get("name", "task"))
    size = len(_task_payload(task, TICKET_MAX))
    if size > MAX_TASK_BYTES:
        # What the controller sends back when asked (every field, non-ASCII escaped) must fit
        # one transfer too: a long name in other scripts takes up to six bytes a character.
        nameless = len(_task_payload(replace(task, name=""), TICKET_MAX))
        raise ConfigError(
            "name" if nameless <= MAX_TASK_BYTES else "waypoints",
            f"the task takes {size} bytes written out, at most {MAX_TASK_BYTES} "
            "(one ISO-TP transfer)",
        )
    return task


def task_document(scenario: Scenario) -> dict[str, Any]:
    """The task part of ``scenario`` as a document :func:`parse_task` reads back (the
    timeout only where the scenario sets one: the default follows the waypoints)."""
    document: dict[str, Any] = {
        "name": scenario.name,
        "mode": scenario.mode.value,
        "elbow": "down" if scenario.elbow is Elbow.DOWN else "up",
        "settle_time": scenario.settle_time,
        "waypoints": [{"t": w.t, "x": w.x, "y": w.y, "z": w.z} for w in scenario.waypoints],
    }
    if scenario.timeout is not None:
        document["timeout"] = scenario.timeout
    if scenario.no_progress_time != NO_PROGRESS_TIME:
        document["no_progress_time"] = scenario.no_progress_time
    if scenario.obstacle is not None:
        document["obstacle"] = obstacle_document(scenario.obstacle, scenario.tool_radius)
    return document


def obstacle_document(obstacle: EllipticCylinder, tool_radius: float) -> dict[str, Any]:
    """``obstacle`` (inflated by ``tool_radius`` and a margin) as the table a task or a
    scenario file writes, which :func:`obstacle_of` reads back."""
    return {
        "x": obstacle.x,
        "y": obstacle.y,
        "long_diameter": obstacle.long_diameter,
        "short_diameter": obstacle.short_diameter,
        "height": obstacle.height,
        "yaw_deg": round(math.degrees(obstacle.yaw), 9),  # 30, not 29.999999999999996
        "tool_radius": tool_radius,
        "margin": round(obstacle.inflation - tool_radius, 12),
    }


def scenario_document(scenario: Scenario) -> dict[str, Any]:
    """The whole of ``scenario`` (task, robot, gains, plant model) as the tables of a scenario
    file, which :func:`parse_scenario` reads back: what a run's results carry."""
    return task_document(scenario) | {
        "robot": scenario.robot.table(),
        "controller": asdict(scenario.controller),
        "plant": asdict(scenario.plant),
    }


MAX_TASK_BYTES = MAX_PAYLOAD
"""The most one ISO-TP transfer on classic CAN carries (its CRC apart)."""


TICKET_MAX = 255
"""The largest ticket (one byte): the longest a task's payload gets."""


def encode_task(scenario: Scenario, ticket: int) -> bytes:
    """The task as compact UTF-8 JSON with the sender's ``ticket`` (0-255), for ScenarioUpload."""
    payload = _task_payload(scenario, ticket)
    if len(payload) > MAX_TASK_BYTES:
        raise ConfigError(
            "waypoints", f"the task takes {len(payload)} bytes, at most {MAX_TASK_BYTES}"
        )
    return payload


def _task_payload(scenario: Scenario, ticket: int) -> bytes:
    document = {"ticket": ticket} | task_document(scenario)
    return json.dumps(document, separators=(",", ":")).encode()


def read_task(payload: bytes) -> tuple[int, dict[str, Any]]:
    """``(ticket, task document)`` of a transfer, for :func:`parse_task`; :class:`ConfigError`
    (field ``document`` or ``ticket``) if it is not a JSON object with a valid ticket."""
    document = read_json(payload, "document")
    if not isinstance(document, dict):
        raise ConfigError("document", "must be a JSON object")
    ticket = document.pop("ticket", 0)
    if isinstance(ticket, bool) or not isinstance(ticket, int) or not 0 <= ticket <= 255:
        raise ConfigError("ticket", f"must be an integer 0-255, got {ticket!r}")
    return ticket, document


def _with_task(base: Scenario, document: Mapping[str, Any], name: str) -> Scenario:
    """``base`` with the task of ``document``, which fits the task's schema."""
    obstacle, tool_radius = obstacle_of(document.get("obstacle"))
    scenario = replace(
        base,
        name=name,
        waypoints=_waypoints(document["waypoints"]),
        obstacle=obstacle,
        mode=Mode(document.get("mode", Mode.FUZZY.value)),
        elbow=Elbow.UP if document.get("elbow", "down") == "up" else Elbow.DOWN,
        settle_time=float(document.get("settle_time", 1.0)),
        timeout=None if "timeout" not in document else float(document["timeout"]),
        no_progress_time=float(document.get("no_progress_time", NO_PROGRESS_TIME)),
        description=document.get("description", ""),
        tool_radius=tool_radius,
    )
    if scenario.duration > MAX_DURATION:
        raise ConfigError(
            "waypoints",
            f"the run would last {scenario.duration:g} s; at most {MAX_DURATION:g} s",
        )
    if scenario.no_progress_time > MAX_DURATION:
        raise ConfigError(
            "no_progress_time", f"{scenario.no_progress_time:g} s; at most {MAX_DURATION:g} s"
        )
    timeout = scenario.timeout
    if timeout is not None and not scenario.duration <= timeout <= MAX_DURATION:
        raise ConfigError(
            "timeout",
            f"{timeout:g} s must be at least the plan's {scenario.duration:g} s (the "
            f"waypoints' span plus the settling time) and at most {MAX_DURATION:g} s",
        )
    check_scenario(scenario)
    return scenario


def check_scenario(scenario: Scenario) -> None:
    """The robot must fit the wire; every waypoint must be reachable and free."""
    check_robot_fits_wire(scenario.robot)
    obstacle = scenario.obstacle
    for index, point in enumerate(scenario.waypoints):
        try:
            inverse(scenario.robot, point.x, point.y, point.z, scenario.elbow)
        except KinematicsError as error:
            raise UnreachableWaypointError(f"waypoints[{index}]", str(error)) from error
        if (
            obstacle is not None
            and point.z < obstacle.height + obstacle.inflation
            and obstacle.contains(point.x, point.y)
        ):
            raise WaypointInObstacleError(
                f"waypoints[{index}]",
                f"({point.x:g}, {point.y:g}, {point.z:g}) is inside the inflated obstacle",
            )


def check_robot_fits_wire(robot: RobotConfig) -> None:
    """Joint limits and speed limits must lie within what the DBC's signals can carry."""
    lows, highs, speeds = robot.joint_min, robot.joint_max, robot.speed_limits
    names = ("theta1", "theta2", "d3")
    rates = ("Theta1Rate", "Theta2Rate", "D3Rate")
    for joint, (state, name, rate_name) in enumerate(zip(STATE, names, rates, strict=True)):
        position, velocity = state.spec["Position"], state.spec["Velocity"]
        for field_name, value in ((f"{name}_min", lows[joint]), (f"{name}_max", highs[joint])):
            if not position.minimum <= value <= position.maximum:
                raise ConfigError(
                    f"robot.{field_name}",
                    f"{value:g} is outside what {state.name}.Position carries "
                    f"[{position.minimum:g}, {position.maximum:g}]",
                )
        rate = COMMAND.spec[rate_name]
        limit = min(velocity.maximum, -velocity.minimum, rate.maximum, -rate.minimum)
        if speeds[joint] > limit:
            raise ConfigError(
                f"robot.speed_limit_{name}",
                f"{speeds[joint]:g} is above what {state.name}.Velocity and "
                f"{COMMAND.name}.{rate.name} carry ({limit:g})",
            )


def _waypoints(entries: list[Mapping[str, float]]) -> tuple[Waypoint, ...]:
    """The waypoints, their times increasing."""
    waypoints = tuple(Waypoint(*(float(entry[key]) for key in "txyz")) for entry in entries)
    for index, (before, after) in enumerate(pairwise(waypoints), start=1):
        if after.t <= before.t:
            raise ConfigError(
                f"waypoints[{index}].t",
                f"times must increase ({after.t:g} s after {before.t:g} s)",
            )
    return waypoints


def obstacle_of(
    table: Mapping[str, float] | None,
) -> tuple[EllipticCylinder | None, float]:
    """The obstacle of a table that fits the obstacle's schema (None: no obstacle), inflated
    by the tool radius and the margin, and the tool radius."""
    if table is None:
        return None, DEFAULT_TOOL_RADIUS
    tool_radius = float(table.get("tool_radius", DEFAULT_TOOL_RADIUS))
    obstacle = EllipticCylinder(
        x=float(table["x"]),
        y=float(table["y"]),
        long_diameter=float(table["long_diameter"]),
        short_diameter=float(table["short_diameter"]),
        height=float(table["height"]),
        yaw=math.radians(table.get("yaw_deg", 0.0)),
        inflation=tool_radius + float(table.get("margin", DEFAULT_MARGIN)),
    )
    return obstacle, tool_radius
