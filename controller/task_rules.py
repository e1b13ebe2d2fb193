"""What a task may ask: the rules a task meets before any process takes it, numbered.

Every task comes through one gate: :func:`accept` for a task document (the bridge's commands,
a task over ISO-TP to the service), :func:`check_task` for a scenario (a file: ``scara-sim``,
``scara-run``, the controller and the plant). A task that breaks a rule is refused with the
:class:`~protocol.errors.ConfigError` of that rule (its reason on the wire:
:func:`protocol.messages.reason_of`), naming the field and the rule's number, e.g.
``waypoints[2]: 4.1 mm from the inflated obstacle; a waypoint must be 8 mm or more from it
(rule 4)``. :data:`RULES` says them for users; ``docs/usage.md`` ("What a task may ask")
is that list, and each rule is tested at its edge (``tests/controller/test_task_rules.py``,
the study's edge families).

Each limit here is where the law was measured to finish every task (``docs/study.md``): just
inside, a task is done in both modes; just outside, it is refused, never left to circle or to
wait for its timeout.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from controller.detour import LIMIT_ROOM
from controller.planner import PATH_CHECK_STEP, check_plan, plan_of
from protocol.config import ControllerConfig
from protocol.errors import (
    ConfigError,
    NoWayRoundError,
    PathOutsideWorkspaceError,
    PlanTooFastError,
    UnreachableWaypointError,
    WaypointInObstacleError,
    WaypointNearLimitError,
    WaypointNearObstacleError,
)
from protocol.kinematics import inverse
from protocol.scenario import Scenario, check_scenario, load_scenario, parse_task

WAYPOINT_CLEARANCE = 0.008
"""m: the least distance of a waypoint below the obstacle's top from the inflated obstacle."""
JOINT_MARGIN = math.radians(1.0)
"""rad: the least distance of a waypoint's revolute joints from their stops."""


@dataclass(frozen=True, slots=True)
class Rule:
    """One rule: its number, what it says to users, and the errors that break it."""

    number: int
    says: str
    errors: tuple[type[ConfigError], ...]


RULES = (
    Rule(
        1,
        "The task is a document its schema takes (protocol/schemas/task.schema.json): 2 to 32 "
        "waypoints, their times increasing; the run (the waypoints' span plus settle_time) "
        "lasts at most 3600 s; a timeout, if set, at least the run and at most 3600 s; a "
        "no_progress_time, if set, at most 3600 s. The obstacle: any size and place its "
        "schema takes; what it stands in the way of, rules 4, 6 and 8 decide.",
        (ConfigError,),
    ),
    Rule(
        2,
        "Every waypoint can be reached: its distance from the base axis between the inner "
        "and outer reach radii, its height within the quill's stroke, and its joints, on the "
        "task's elbow, inside their limits.",
        (UnreachableWaypointError,),
    ),
    Rule(
        3,
        "Every waypoint's revolute joints (theta1, theta2, on the task's elbow) are "
        f"{math.degrees(JOINT_MARGIN):g} degree or more inside their stops.",
        (WaypointNearLimitError,),
    ),
    Rule(
        4,
        "Every waypoint below the obstacle's top (its height plus the inflation) is "
        f"{1000 * WAYPOINT_CLEARANCE:g} mm or more outside the inflated obstacle (the obstacle "
        "grown by the tool radius and the margin).",
        (WaypointInObstacleError, WaypointNearObstacleError),
    ),
    Rule(
        5,
        "The planned path (the cubic through the waypoints) stays within reach and the joint "
        "limits everywhere.",
        (PathOutsideWorkspaceError,),
    ),
    Rule(
        6,
        "A segment the obstacle stands across leaves a way round it inside the joint limits: "
        "on one side or the other, the way AO takes (from the waypoint to the tangent point, "
        "round the obstacle grown by AO's pass margin, "
        f"{ControllerConfig().ao_pass_margin * 1000:g} mm by default and less where the next "
        "waypoint is nearer the obstacle than that, and on to the next waypoint) stays "
        f"{math.degrees(LIMIT_ROOM):g} degree inside the joints' limits, or, where a straight "
        "part of it cuts through the hole inside the inner reach, the arm can slide round the "
        f"hole instead, theta2 {math.degrees(LIMIT_ROOM):g} degree inside its stop, outside "
        f"that grown obstacle and {math.degrees(LIMIT_ROOM):g} degree inside theta1's limits.",
        (NoWayRoundError,),
    ),
    Rule(
        7,
        f"The planned path is nowhere faster than {ControllerConfig().speed_max:g} m/s in the "
        "plane (the controller's speed_max, the most PT commands).",
        (PlanTooFastError,),
    ),
    Rule(
        8,
        "The obstacle does not stand where the arm stands when it is set (the service's: "
        "the arm would start inside it).",
        (),
    ),
)
"""Every rule, in order; a task breaking one is refused by the first that applies."""


def rule_of(error: ConfigError) -> Rule:
    """The rule ``error`` breaks (the most specific one whose errors it is)."""
    return next(
        (rule for rule in RULES[1:] if isinstance(error, rule.errors)),
        RULES[0],
    )


def numbered(error: ConfigError) -> ConfigError:
    """``error`` with its rule's number at the end of its message, of the same class."""
    return type(error)(error.field, f"{error.message} (rule {rule_of(error).number})")


def check_task(task: Scenario) -> Scenario:
    """``task`` (a scenario built in code: a generator's), once it meets rules 2 to 7; the
    error of the first rule it breaks, numbered, otherwise."""
    try:
        check_scenario(task)
    except ConfigError as error:
        raise numbered(error) from error
    return _beyond_the_document(task)


def accept(document: Mapping[str, Any], base: Scenario) -> Scenario:
    """The task of ``document`` on ``base``'s robot, gains and plant, once it meets every
    rule; the error of the first rule it breaks, numbered, otherwise."""
    try:
        task = parse_task(document, base)
    except ConfigError as error:
        raise numbered(error) from error
    return _beyond_the_document(task)


def load_task(source: str | Path) -> Scenario:
    """A scenario from a file or name, through the gate (what the controller runs, and so
    what anything that simulates it must accept)."""
    try:
        scenario = load_scenario(source)
    except ConfigError as error:
        raise numbered(error) from error
    return _beyond_the_document(scenario)


def _beyond_the_document(task: Scenario) -> Scenario:
    """Rules 3 to 7, for a task whose document was read (rule 1, 2 and a waypoint inside the
    obstacle are :func:`protocol.scenario.check_scenario`'s, as it is read)."""
    try:
        _check_waypoints(task)
        check_plan(task)
        _check_speed(task)
    except ConfigError as error:
        raise numbered(error) from error
    return task


def _check_waypoints(task: Scenario) -> None:
    """Rule 3, and rule 4 for a waypoint outside the inflated obstacle."""
    robot, obstacle = task.robot, task.obstacle
    stops = (
        (robot.theta1_min, robot.theta1_max, "theta1"),
        (robot.theta2_min, robot.theta2_max, "theta2"),
    )
    for index, point in enumerate(task.waypoints):
        field = f"waypoints[{index}]"
        joints = inverse(robot, point.x, point.y, point.z, task.elbow)
        for angle, (low, high, name) in zip(joints, stops, strict=False):
            left = min(angle - low, high - angle)
            if left < JOINT_MARGIN:
                raise WaypointNearLimitError(
                    field,
                    f"{name} {math.degrees(angle):.2f} deg is {math.degrees(left):.2f} deg from "
                    f"its stop; a waypoint's joints must be {math.degrees(JOINT_MARGIN):g} deg "
                    "or more inside their stops",
                )
        if obstacle is not None and point.z < obstacle.height + obstacle.inflation:
            clearance = obstacle.clearance(point.x, point.y)
            if clearance < WAYPOINT_CLEARANCE:
                raise WaypointNearObstacleError(
                    field,
                    f"{1000 * clearance:.1f} mm from the inflated obstacle; a waypoint must be "
                    f"{1000 * WAYPOINT_CLEARANCE:g} mm or more from it",
                )


def peak_speed(task: Scenario) -> tuple[float, float]:
    """The plan's fastest planar speed, every PATH_CHECK_STEP, and when (rule 7's measure)."""
    trajectory = plan_of(task)
    start, end = task.waypoints[0].t, task.waypoints[-1].t
    steps = max(1, math.ceil((end - start) / PATH_CHECK_STEP))
    times = start + (end - start) * np.arange(steps + 1) / steps
    velocities = trajectory.sample(times)[1]
    speeds = np.hypot(velocities[:, 0], velocities[:, 1])
    fastest = int(np.argmax(speeds))
    return float(speeds[fastest]), float(times[fastest])


def _check_speed(task: Scenario) -> None:
    """Rule 7: the plan's planar speed at most the controller's ``speed_max``."""
    speed, when = peak_speed(task)
    cap = task.controller.speed_max
    if speed > cap:
        segment = plan_of(task).segment_index(when)
        raise PlanTooFastError(
            f"waypoints[{segment - 1}..{segment}]",
            f"the planned path moves at {speed:.3f} m/s at t = {when:.3f} s; it may move at "
            f"{cap:g} m/s at most",
        )
