"""The tasks the gate refuses (:mod:`controller.task_rules`): counted by rule, and a sample of
them checked by brute force, each by a search of its own that does not use the gate's
formulas: a way round the obstacle by :mod:`sim.passability`, a waypoint's clearance against
the densely sampled edge of the inflated obstacle, a joint's margin from the arm's forward
kinematics, the plan's speed sampled fifty times as finely, the reach from the arm's
lengths."""

from __future__ import annotations

import math
import random
import re
from collections import Counter
from collections.abc import Callable, Sequence
from enum import Enum

import numpy as np

from controller.planner import plan_of
from controller.task_rules import JOINT_MARGIN, WAYPOINT_CLEARANCE, rule_of
from protocol.errors import (
    ConfigError,
    NoWayRoundError,
    PlanTooFastError,
    UnreachableWaypointError,
    WaypointInObstacleError,
    WaypointNearLimitError,
    WaypointNearObstacleError,
)
from protocol.kinematics import forward
from protocol.scenario import Scenario
from sim.passability import RESOLUTION, Verdict, way_round

DEFAULT_CHECKED = 20
"""Refused tasks checked by brute force by default (a way-round search takes about 0.1 s, up
to about 3 s where it is unsure and asked again on finer grids)."""
_SEGMENT = re.compile(r"waypoints\[(\d+)\.\.")
_WAYPOINT = re.compile(r"waypoints\[(\d+)\]$")
EDGE_SAMPLES = 200_000
"""Points on the inflated obstacle's edge the clearance is searched over."""
BISECTIONS = 80
"""Halvings of theta2's interval in the search for the joints that reach a point."""
REFINEMENTS = 3
"""Times an unsure way-round search is asked again on a grid twice as fine (to RESOLUTION / 8:
a gap the grid's error hides, about 4 mm wide at RESOLUTION, is told from 0.5 mm)."""
SPEED_STEP = 1e-4
"""s between the plan's points the speed is searched over (the gate's: 5 ms)."""


class Check(Enum):
    """The brute force's word on one refusal."""

    RIGHT = "right"
    """It agrees: the task breaks the rule."""
    WRONG = "wrong"
    """It does not: the gate refused a task it should have taken."""
    UNSURE = "unsure"
    """It cannot tell (a way round only where the gaps are as narrow as its grid)."""


def refused_segment(error: ConfigError) -> int:
    """The segment a refusal names (``waypoints[i..i+1]``)."""
    found = _SEGMENT.match(error.field)
    if found is None:
        raise ValueError(f"a refusal that names no segment: {error}")
    return int(found.group(1))


def refused_waypoint(error: ConfigError) -> int:
    """The waypoint a refusal names (``waypoints[i]``)."""
    found = _WAYPOINT.match(error.field)
    if found is None:
        raise ValueError(f"a refusal that names no waypoint: {error}")
    return int(found.group(1))


def _way_round(task: Scenario, error: ConfigError) -> Check:
    """The search on its grid, asked again on grids twice as fine while it is unsure."""
    segment, resolution = refused_segment(error), RESOLUTION
    verdict = way_round(task, segment, resolution)
    for _ in range(REFINEMENTS):
        if verdict is not Verdict.UNSURE:
            break
        resolution /= 2.0
        verdict = way_round(task, segment, resolution)
    return {Verdict.NO_WAY: Check.RIGHT, Verdict.WAY: Check.WRONG}.get(verdict, Check.UNSURE)


def _near_obstacle(task: Scenario, error: ConfigError) -> Check:
    """The least distance from the waypoint to EDGE_SAMPLES points of the inflated edge."""
    point = task.waypoints[refused_waypoint(error)]
    obstacle = task.obstacle
    assert obstacle is not None
    a, b = obstacle.semi_axes
    angles = np.linspace(0.0, 2.0 * math.pi, EDGE_SAMPLES, endpoint=False)
    local_x, local_y = a * np.cos(angles), b * np.sin(angles)
    cos, sin = math.cos(obstacle.yaw), math.sin(obstacle.yaw)
    edge_x = obstacle.x + cos * local_x - sin * local_y
    edge_y = obstacle.y + sin * local_x + cos * local_y
    nearest = float(np.min(np.hypot(edge_x - point.x, edge_y - point.y)))
    dx, dy = point.x - obstacle.x, point.y - obstacle.y
    u, v = cos * dx + sin * dy, -sin * dx + cos * dy
    inside = (u / a) ** 2 + (v / b) ** 2 < 1.0
    return Check.RIGHT if inside or nearest < WAYPOINT_CLEARANCE else Check.WRONG


def _near_limit(task: Scenario, error: ConfigError) -> Check:
    """The joints that reach the waypoint, found by bisection on the forward kinematics
    (theta2 on the task's elbow turns the arm to the point's radius, theta1 onto its
    bearing): refused rightly if either is within JOINT_MARGIN of a stop, or beyond it."""
    point = task.waypoints[refused_waypoint(error)]
    robot = task.robot
    radius = math.hypot(point.x, point.y)
    low, high = 0.0, math.pi  # |theta2|: the arm folds, its reach shrinks
    for _ in range(BISECTIONS):
        middle = (low + high) / 2.0
        x, y, _ = forward(robot, 0.0, middle, 0.0)
        low, high = (middle, high) if math.hypot(x, y) > radius else (low, middle)
    theta2 = task.elbow.value * (low + high) / 2.0
    x, y, _ = forward(robot, 0.0, theta2, 0.0)
    theta1 = math.atan2(point.y, point.x) - math.atan2(y, x)
    theta1 = math.atan2(math.sin(theta1), math.cos(theta1))
    inside = (
        robot.theta1_min + JOINT_MARGIN <= theta1 <= robot.theta1_max - JOINT_MARGIN
        and robot.theta2_min + JOINT_MARGIN <= theta2 <= robot.theta2_max - JOINT_MARGIN
    )
    return Check.WRONG if inside else Check.RIGHT


def _too_fast(task: Scenario, error: ConfigError) -> Check:
    trajectory = plan_of(task)
    start, end = task.waypoints[0].t, task.waypoints[-1].t
    times = np.arange(start, end, SPEED_STEP)
    velocities = trajectory.sample(times)[1]
    fastest = float(np.max(np.hypot(velocities[:, 0], velocities[:, 1])))
    return Check.RIGHT if fastest > task.controller.speed_max else Check.WRONG


def _unreachable(task: Scenario, error: ConfigError) -> Check:
    """Out of the annulus the arm's lengths span, or of the quill's stroke (a waypoint
    beyond a joint limit but within those is not this search's to judge)."""
    point = task.waypoints[refused_waypoint(error)]
    robot = task.robot
    radius = math.hypot(point.x, point.y)
    height = robot.d0 - point.z  # d3
    outside = not (abs(robot.a1 - robot.a2) <= radius <= robot.a1 + robot.a2)
    outside = outside or not (robot.d3_min <= height <= robot.d3_max)
    return Check.RIGHT if outside else Check.UNSURE


_CHECKS: dict[type[ConfigError], Callable[[Scenario, ConfigError], Check]] = {
    NoWayRoundError: _way_round,
    WaypointNearObstacleError: _near_obstacle,
    WaypointInObstacleError: _near_obstacle,
    WaypointNearLimitError: _near_limit,
    PlanTooFastError: _too_fast,
    UnreachableWaypointError: _unreachable,
}


def brute_force(task: Scenario, error: ConfigError) -> Check:
    """The brute force's word on the gate's refusal of ``task`` with ``error``."""
    check = _CHECKS.get(type(error))
    return Check.UNSURE if check is None else check(task, error)


def check_refused(
    refused: Sequence[tuple[Scenario, ConfigError]], count: int, seed: int = 0
) -> list[tuple[Scenario, ConfigError, Check]]:
    """The brute force's word on ``count`` of the ``refused`` tasks, drawn at random."""
    sample = random.Random(seed).sample(list(refused), min(count, len(refused)))
    return [(task, error, brute_force(task, error)) for task, error in sample]


def refusal_report(
    offered: int, refused: Sequence[tuple[Scenario, ConfigError]], checked: int
) -> str:
    """How many tasks were refused, by which rule, and what the brute force found on a sample
    of them; a refusal it finds wrong is named."""
    by_rule = Counter(rule_of(error).number for _, error in refused)
    rules = ", ".join(f"rule {rule}: {by_rule[rule]}" for rule in sorted(by_rule))
    lines = [
        f"tasks offered: {offered}, accepted: {offered - len(refused)}, refused: "
        f"{len(refused)}" + (f" ({rules})" if rules else "")
    ]
    if refused and checked > 0:
        checks = check_refused(refused, checked)
        counts = Counter(check for _, _, check in checks)
        lines.append(
            f"refusals checked by brute force: {len(checks)}: "
            + ", ".join(f"{counts[check]} {check.value}" for check in Check)
        )
        lines += [
            f"  refused though the rule holds: {task.name} ({error})"
            for task, error, check in checks
            if check is Check.WRONG
        ]
    return "\n".join(lines)
