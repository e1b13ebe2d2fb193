"""The edge families: a task as users write it, moved to the edge of one rule of what a task
may ask (:mod:`controller.task_rules`), just inside or just outside it, half and half.

Just inside, the task must be taken and done in both modes; just outside, refused by that
rule (the study counts the refusals by rule and checks a sample of them by brute force,
:mod:`sim.study.refusals`). A move that leaves the inside twin refused (by this rule or any
other) is drawn again: each task of a family sits at its own rule's edge and no other.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from enum import Enum

import numpy as np

from controller.task_rules import JOINT_MARGIN, WAYPOINT_CLEARANCE, check_task, peak_speed
from protocol.errors import ConfigError
from protocol.kinematics import forward, inverse, reach_radii
from protocol.scenario import Scenario, Waypoint

OBSTACLE_BAND = 0.0003
"""m: an edge task's waypoint is this near rule 4's 8 mm, either side."""
LIMIT_BAND = math.radians(0.05)
"""rad: an edge task's joint is this near rule 3's margin, either side."""
SPEED_BAND = 0.005
"""An edge task's plan peaks this share of rule 7's cap away from it, either side."""
REACH_BAND = 0.0005
"""m: an edge task's waypoint is this near the outer reach (rule 2), either side."""
BISECTIONS = 60


class Edge(Enum):
    """Which rule's edge a family's tasks sit at."""

    OBSTACLE = "edge_obstacle"
    """Rule 4: a waypoint 8 mm from the inflated obstacle."""
    LIMIT = "edge_limit"
    """Rule 3: a waypoint's theta1 or theta2 1 degree from its stop."""
    SPEED = "edge_speed"
    """Rule 7: the plan's peak speed at 0.6 m/s."""
    REACH = "edge_reach"
    """Rule 2: a waypoint at the outer reach."""


Move = Callable[[Scenario, np.random.Generator, float], Scenario | None]
"""A task moved to its rule's edge, ``side`` (+1 inside, -1 outside) times the band from it."""


def at_edge(task: Scenario, edge: Edge, rng: np.random.Generator) -> Scenario | None:
    """``task`` moved to ``edge``'s rule, just inside or just outside (at random, named so),
    or None where its inside twin would be refused (draw another)."""
    move = _MOVES[edge]
    side = 1.0 if rng.random() < 0.5 else -1.0
    share = rng.uniform(0.05, 1.0)
    seed = int(rng.integers(2**32))  # the twins move the same waypoint the same way
    inside = move(task, np.random.default_rng(seed), share)
    if inside is None or not _taken(inside):
        return None
    chosen = inside if side > 0 else move(task, np.random.default_rng(seed), -share)
    if chosen is None:
        return None
    where = "inside" if side > 0 else "outside"
    return dataclasses.replace(chosen, name=f"{task.name}-{where}")


def _taken(task: Scenario) -> bool:
    try:
        check_task(task)
    except ConfigError:
        return False
    return True


def _with_point(task: Scenario, index: int, x: float, y: float) -> Scenario:
    waypoints = list(task.waypoints)
    waypoints[index] = Waypoint(waypoints[index].t, round(x, 6), round(y, 6), waypoints[index].z)
    return dataclasses.replace(task, waypoints=tuple(waypoints))


def _near_obstacle(task: Scenario, rng: np.random.Generator, share: float) -> Scenario | None:
    """A waypoint below the top moved along the ray from the obstacle's centre to
    ``WAYPOINT_CLEARANCE + share * OBSTACLE_BAND`` from the inflated obstacle."""
    obstacle = task.obstacle
    if obstacle is None:
        return None
    below = [i for i, w in enumerate(task.waypoints) if w.z < obstacle.height + obstacle.inflation]
    if not below:
        return None
    index = below[int(rng.integers(len(below)))]
    point = task.waypoints[index]
    angle = math.atan2(point.y - obstacle.y, point.x - obstacle.x)
    wanted = WAYPOINT_CLEARANCE + share * OBSTACLE_BAND
    low, high = 0.0, 1.0
    for _ in range(BISECTIONS):
        middle = (low + high) / 2.0
        x, y = obstacle.x + middle * math.cos(angle), obstacle.y + middle * math.sin(angle)
        low, high = (middle, high) if obstacle.clearance(x, y) < wanted else (low, middle)
    # the written point (to a micrometre) on the band's own side
    x, y = obstacle.x + high * math.cos(angle), obstacle.y + high * math.sin(angle)
    return _with_point(task, index, x, y)


def _near_limit(task: Scenario, rng: np.random.Generator, share: float) -> Scenario | None:
    """A waypoint whose theta1 or theta2 is moved to ``JOINT_MARGIN + share * LIMIT_BAND``
    from its nearer stop, the other joint and the height kept."""
    index = int(rng.integers(len(task.waypoints)))
    point = task.waypoints[index]
    robot = task.robot
    theta1, theta2, d3 = inverse(robot, point.x, point.y, point.z, task.elbow)
    left = JOINT_MARGIN + share * LIMIT_BAND
    if rng.random() < 0.5:
        theta2 = math.copysign(robot.theta2_max - left, theta2 or 1.0)
    else:
        theta1 = robot.theta1_max - left if theta1 >= 0.0 else robot.theta1_min + left
    x, y, _ = forward(robot, theta1, theta2, d3)
    return _with_point(task, index, x, y)


def _at_reach(task: Scenario, rng: np.random.Generator, share: float) -> Scenario | None:
    """A waypoint moved along its ray from the base axis to ``share * REACH_BAND`` inside
    the outer reach (outside for a negative share)."""
    index = int(rng.integers(len(task.waypoints)))
    point = task.waypoints[index]
    radius = reach_radii(task.robot)[1] - share * REACH_BAND
    angle = math.atan2(point.y, point.x)
    return _with_point(task, index, radius * math.cos(angle), radius * math.sin(angle))


def _at_speed(task: Scenario, rng: np.random.Generator, share: float) -> Scenario | None:
    """The task's times stretched or shrunk about its first waypoint so that its plan peaks
    at ``(1 - share * SPEED_BAND)`` times the cap (by the gate's own measure)."""
    peak = peak_speed(task)[0]
    if peak <= 0.0:
        return None
    wanted = task.controller.speed_max * (1.0 - share * SPEED_BAND)
    scale = peak / wanted
    start = task.waypoints[0].t
    waypoints = tuple(
        dataclasses.replace(w, t=round(start + (w.t - start) * scale, 6)) for w in task.waypoints
    )
    moved = dataclasses.replace(task, waypoints=waypoints)
    for _ in range(3):  # the times were rounded: settle on the band's side
        peak = peak_speed(moved)[0]
        if (peak <= task.controller.speed_max) == (share > 0):
            return moved
        scale *= peak / wanted
        waypoints = tuple(
            dataclasses.replace(w, t=round(start + (w.t - start) * scale, 6))
            for w in task.waypoints
        )
        moved = dataclasses.replace(task, waypoints=waypoints)
    return None


_MOVES: dict[Edge, Move] = {
    Edge.OBSTACLE: _near_obstacle,
    Edge.LIMIT: _near_limit,
    Edge.SPEED: _at_speed,
    Edge.REACH: _at_reach,
}
