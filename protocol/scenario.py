"""Scenarios as TOML files: waypoints with times, the obstacle, the mode, the rates.

A scenario is what the controller and the plant agree to run, so it is part of the protocol:
both processes read the same file. It is checked whole before anything moves: every value
finite, times increasing, every waypoint reachable within the joint limits and outside the
obstacle, and the robot's ranges within what the wire carries. (The controller adds its own
check of the planned path, :func:`controller.planner.check_plan`.) Errors are
:class:`ConfigError` and name the field (``waypoints[2].x``, ``obstacle.height``, ...).
"""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, replace
from enum import Enum
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
from protocol.kinematics import Elbow, inverse
from protocol.messages import COMMAND, STATE

SCENARIO_DIR = Path(__file__).resolve().parent.parent / "scenarios"
WAYPOINT_TOLERANCE = 0.002
"""m: a waypoint counts as passed when the TCP comes this close."""
MAX_DURATION = 3600.0
"""s: the longest run a scenario may ask for (its waypoints' span plus the settling time)."""
DEFAULT_TOOL_RADIUS = 0.01
DEFAULT_MARGIN = 0.01

_TASK = {"name", "description", "mode", "elbow", "settle_time", "obstacle", "waypoints"}
"""What an operator sets; a scenario file adds the robot, the gains and the plant model."""
_TOP_LEVEL = _TASK | {"robot", "controller", "plant"}


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
    description: str = ""
    robot: RobotConfig = field(default_factory=RobotConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    plant: PlantConfig = field(default_factory=PlantConfig)
    tool_radius: float = 0.01

    def touched_obstacle(self) -> EllipticCylinder | None:
        """The obstacle grown by the tool radius only: what the tool really collides with."""
        if self.obstacle is None:
            return None
        return self.obstacle.grown(self.tool_radius - self.obstacle.inflation)

    def initial_joints(self) -> tuple[float, float, float]:
        first = self.waypoints[0]
        return inverse(self.robot, first.x, first.y, first.z, self.elbow)

    @property
    def duration(self) -> float:
        """Planned time plus the settling time after the last waypoint."""
        return self.waypoints[-1].t - self.waypoints[0].t + self.settle_time

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
        document = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(str(path), f"not valid TOML: {error}") from error
    return parse_scenario(document, default_name=path.stem)


def parse_scenario(document: Mapping[str, Any], default_name: str = "scenario") -> Scenario:
    """Build and fully check a scenario from its TOML tables."""
    unknown = set(document) - _TOP_LEVEL
    if unknown:
        raise ConfigError(sorted(unknown)[0], f"unknown field; known: {sorted(_TOP_LEVEL)}")
    robot = RobotConfig.from_mapping(dict(_table(document, "robot")))
    controller = ControllerConfig.from_mapping(dict(_table(document, "controller")))
    plant_table = _table(document, "plant")
    try:
        plant = PlantConfig(**plant_table)
    except TypeError as error:
        raise ConfigError("plant", str(error)) from error
    base = Scenario("", (), None, robot=robot, controller=controller, plant=plant)
    return _with_task(base, document, str(document.get("name", default_name)))


def parse_task(document: Mapping[str, Any], base: Scenario) -> Scenario:
    """A scenario from a task document (what an operator sets: name, mode, waypoints,
    obstacle, settling time, elbow) on ``base``'s robot, gains and plant model, checked as a
    scenario file is. The JSON an operator sends over the wire (:func:`encode_task`)."""
    unknown = set(document) - _TASK
    if unknown:
        raise ConfigError(sorted(unknown)[0], f"unknown field; known: {sorted(_TASK)}")
    return _with_task(base, document, str(document.get("name", "task")))


def task_document(scenario: Scenario) -> dict[str, Any]:
    """The task part of ``scenario`` as a document :func:`parse_task` reads back."""
    document: dict[str, Any] = {
        "name": scenario.name,
        "mode": scenario.mode.value,
        "elbow": "down" if scenario.elbow is Elbow.DOWN else "up",
        "settle_time": scenario.settle_time,
        "waypoints": [{"t": w.t, "x": w.x, "y": w.y, "z": w.z} for w in scenario.waypoints],
    }
    obstacle = scenario.obstacle
    if obstacle is not None:
        document["obstacle"] = {
            "x": obstacle.x,
            "y": obstacle.y,
            "long_diameter": obstacle.long_diameter,
            "short_diameter": obstacle.short_diameter,
            "height": obstacle.height,
            "yaw_deg": round(math.degrees(obstacle.yaw), 9),  # 30, not 29.999999999999996
            "tool_radius": scenario.tool_radius,
            "margin": round(obstacle.inflation - scenario.tool_radius, 12),
        }
    return document


def scenario_document(scenario: Scenario) -> dict[str, Any]:
    """The whole of ``scenario`` (task, robot, gains, plant model) as the tables of a scenario
    file, which :func:`parse_scenario` reads back: what a run's results carry."""
    angles = {"theta1_min", "theta1_max", "theta2_min", "theta2_max"}
    robot = {
        (f"{name}_deg" if name in angles else name): (
            math.degrees(value) if name in angles else value
        )
        for name, value in ((f.name, getattr(scenario.robot, f.name)) for f in fields(RobotConfig))
    }
    return task_document(scenario) | {
        "robot": robot,
        "controller": asdict(scenario.controller),
        "plant": asdict(scenario.plant),
    }


MAX_TASK_BYTES = 4095
"""The most one ISO-TP transfer on classic CAN carries."""


def encode_task(scenario: Scenario, ticket: int) -> bytes:
    """The task as compact UTF-8 JSON with the sender's ``ticket`` (0-255), for ScenarioUpload."""
    document = {"ticket": ticket} | task_document(scenario)
    payload = json.dumps(document, separators=(",", ":")).encode()
    if len(payload) > MAX_TASK_BYTES:
        raise ConfigError(
            "waypoints", f"the task takes {len(payload)} bytes, at most {MAX_TASK_BYTES}"
        )
    return payload


def read_task(payload: bytes) -> tuple[int, dict[str, Any]]:
    """``(ticket, task document)`` of a transfer, for :func:`parse_task`; :class:`ConfigError`
    (field ``document`` or ``ticket``) if it is not a JSON object with a valid ticket."""
    try:
        document = json.loads(payload.decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ConfigError("document", f"not UTF-8 JSON: {error}") from error
    if not isinstance(document, dict):
        raise ConfigError("document", "must be a JSON object")
    ticket = document.pop("ticket", 0)
    if isinstance(ticket, bool) or not isinstance(ticket, int) or not 0 <= ticket <= 255:
        raise ConfigError("ticket", f"must be an integer 0-255, got {ticket!r}")
    return ticket, document


def _with_task(base: Scenario, document: Mapping[str, Any], name: str) -> Scenario:
    mode_name = document.get("mode", "fuzzy")
    try:
        mode = Mode(mode_name)
    except ValueError as error:
        raise ConfigError(
            "mode", f"must be 'fuzzy' or 'conventional', got {mode_name!r}"
        ) from error
    elbow_name = document.get("elbow", "down")
    if elbow_name not in ("up", "down"):
        raise ConfigError("elbow", f"must be 'up' or 'down', got {elbow_name!r}")
    elbow = Elbow.DOWN if elbow_name == "down" else Elbow.UP
    settle_time = _number(document.get("settle_time", 1.0), "settle_time")
    if settle_time < 0.0:
        raise ConfigError("settle_time", "must not be negative")
    obstacle_table = _table(document, "obstacle")
    obstacle = _parse_obstacle(obstacle_table) if "obstacle" in document else None
    tool_radius = _number(
        obstacle_table.get("tool_radius", DEFAULT_TOOL_RADIUS), "obstacle.tool_radius"
    )
    scenario = replace(
        base,
        name=name,
        waypoints=_parse_waypoints(document.get("waypoints")),
        obstacle=obstacle,
        mode=mode,
        elbow=elbow,
        settle_time=settle_time,
        description=str(document.get("description", "")),
        tool_radius=tool_radius,
    )
    if scenario.duration > MAX_DURATION:
        raise ConfigError(
            "waypoints",
            f"the run would last {scenario.duration:g} s; at most {MAX_DURATION:g} s",
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


def _table(document: Mapping[str, Any], name: str) -> Mapping[str, Any]:
    value = document.get(name, {})
    if not isinstance(value, Mapping):
        raise ConfigError(name, "must be a table")
    return value


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(where, f"must be a finite number, got {value!r}")
    return float(value)


def _parse_waypoints(raw: Any) -> tuple[Waypoint, ...]:
    if not isinstance(raw, list) or len(raw) < 2:
        raise ConfigError("waypoints", "must be a list of at least 2 [[waypoints]] tables")
    waypoints: list[Waypoint] = []
    for index, entry in enumerate(raw):
        if not isinstance(entry, Mapping):
            raise ConfigError(f"waypoints[{index}]", "must be a table with t, x, y, z")
        unknown = set(entry) - {"t", "x", "y", "z"}
        if unknown:
            raise ConfigError(f"waypoints[{index}].{sorted(unknown)[0]}", "unknown field")
        values = []
        for key in ("t", "x", "y", "z"):
            if key not in entry:
                raise ConfigError(f"waypoints[{index}].{key}", "missing")
            values.append(_number(entry[key], f"waypoints[{index}].{key}"))
        if index and values[0] <= waypoints[-1].t:
            raise ConfigError(
                f"waypoints[{index}].t",
                f"times must increase ({values[0]:g} s after {waypoints[-1].t:g} s)",
            )
        waypoints.append(Waypoint(*values))
    return tuple(waypoints)


def _parse_obstacle(raw: Any) -> EllipticCylinder:
    if not isinstance(raw, Mapping):
        raise ConfigError("obstacle", "must be a table")
    known = {
        "x",
        "y",
        "long_diameter",
        "short_diameter",
        "height",
        "yaw_deg",
        "tool_radius",
        "margin",
    }
    unknown = set(raw) - known
    if unknown:
        raise ConfigError(
            f"obstacle.{sorted(unknown)[0]}", f"unknown field; known: {sorted(known)}"
        )
    values = {}
    for key in known:
        if key in raw:
            values[key] = _number(raw[key], f"obstacle.{key}")
        elif key in {"x", "y", "long_diameter", "short_diameter", "height"}:
            raise ConfigError(f"obstacle.{key}", "missing")
    for key in ("tool_radius", "margin"):
        if values.get(key, 0.0) < 0.0:
            raise ConfigError(f"obstacle.{key}", "must not be negative")
    return EllipticCylinder(
        x=values["x"],
        y=values["y"],
        long_diameter=values["long_diameter"],
        short_diameter=values["short_diameter"],
        height=values["height"],
        yaw=math.radians(values.get("yaw_deg", 0.0)),
        inflation=values.get("tool_radius", DEFAULT_TOOL_RADIUS)
        + values.get("margin", DEFAULT_MARGIN),
    )
