"""Module DM (paper section 3.2, ``controller.obstacle``): what it measures from the TCP
towards the next waypoint."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from shapes import obstacles, point_at, unit_interval

from controller.obstacle import measure
from protocol.geometry import EllipticCylinder

SENSING_RANGE = 0.2
OBSTACLE = EllipticCylinder(0.4, 0.0, 0.1, 0.06, 0.1, yaw=0.0, inflation=0.02)


def test_tool_above_the_obstacle_sees_nothing() -> None:
    top = OBSTACLE.height + OBSTACLE.inflation
    for z in (top, top + 0.05):
        assert not measure(OBSTACLE, (0.25, 0.0, z), (0.6, 0.0), SENSING_RANGE).present
    below = measure(OBSTACLE, (0.25, 0.0, top - 1e-6), (0.6, 0.0), SENSING_RANGE)
    assert below.present
    assert below.blocked
    assert not measure(None, (0.25, 0.0, 0.0), (0.6, 0.0), SENSING_RANGE).present


def test_obstacle_beyond_the_sensing_range_is_absent() -> None:
    a, _ = OBSTACLE.semi_axes
    for gap, present in (
        (SENSING_RANGE + 0.01, False),
        (SENSING_RANGE + 1e-9, False),
        (0.19, True),
    ):
        tcp = (OBSTACLE.x - a - gap, 0.0, 0.0)
        seen = measure(OBSTACLE, tcp, (1.0, 0.0), SENSING_RANGE)
        assert seen.present is present, gap
        if not present:
            assert seen.d_left == seen.d_right == SENSING_RANGE
            assert not seen.blocked
            assert seen.beta > 0.0


def _ray_hits(obstacle: EllipticCylinder, px: float, py: float, angle: float) -> bool:
    crossings = obstacle.line_crossings(px, py, px + math.cos(angle), py + math.sin(angle))
    return crossings is not None and crossings[1] >= 0.0


@pytest.mark.parametrize("yaw", [0.0, math.pi / 2.0])
@pytest.mark.parametrize("offset", [0.03, -0.03])
def test_goal_through_an_offset_obstacle(yaw: float, offset: float) -> None:
    """Path along y = 0, obstacle centre offset to the left (+y) or the right (-y)."""
    obstacle = EllipticCylinder(0.4, offset, 0.1, 0.06, 0.1, yaw=yaw, inflation=0.02)
    tcp, goal = (0.25, 0.0, 0.05), (0.6, 0.0)
    seen = measure(obstacle, tcp, goal, SENSING_RANGE)
    assert seen.present
    assert seen.blocked
    assert seen.beta < 0.0
    assert seen.clearance == obstacle.clearance(tcp[0], tcp[1]) > 0.0
    nearer, farther = (seen.d_left, seen.d_right) if offset > 0.0 else (seen.d_right, seen.d_left)
    assert nearer == seen.clearance < farther
    # The far side's distance is where the path enters the section.
    crossings = obstacle.line_crossings(tcp[0], tcp[1], goal[0], goal[1])
    assert crossings is not None
    entry = crossings[0]
    assert farther == pytest.approx(entry * (goal[0] - tcp[0]))
    # Turning by |beta| towards the side away from the obstacle just clears it.
    away = -1.0 if offset > 0.0 else 1.0
    assert _ray_hits(obstacle, tcp[0], tcp[1], away * (abs(seen.beta) - 1e-6))
    assert not _ray_hits(obstacle, tcp[0], tcp[1], away * (abs(seen.beta) + 1e-6))


def test_goal_past_the_obstacle() -> None:
    obstacle = EllipticCylinder(0.4, 0.12, 0.1, 0.06, 0.1, inflation=0.02)
    seen = measure(obstacle, (0.25, 0.0, 0.05), (0.6, 0.0), SENSING_RANGE)
    assert seen.present
    assert not seen.blocked
    assert seen.beta > 0.0
    assert seen.d_left == seen.clearance < seen.d_right == SENSING_RANGE
    # Turning left by beta just touches it.
    assert not _ray_hits(obstacle, 0.25, 0.0, seen.beta - 1e-6)
    assert _ray_hits(obstacle, 0.25, 0.0, seen.beta + 1e-6)


def test_goal_short_of_the_obstacle_is_not_blocked() -> None:
    seen = measure(OBSTACLE, (0.2, 0.0, 0.0), (0.25, 0.0), SENSING_RANGE)
    assert seen.present
    assert not seen.blocked
    assert seen.beta < 0.0  # ... though the direction to it points into the obstacle


def test_the_way_passes_the_obstacle_as_near_as_its_nearer_end_comes_to_the_tangent_point() -> None:
    """``passing``: 0 where the way to the goal is blocked; the ray's distance from the tangent
    point for a goal beyond the ray's nearest point; the goal's own distance from it for a
    goal short of that, larger, and meeting the ray's without a jump."""
    obstacle = EllipticCylinder(0.4, 0.0, 0.1, 0.1, 0.1, inflation=0.02)  # a circle, r 0.07
    tcp = (0.2, 0.0, 0.05)
    assert measure(obstacle, tcp, (0.6, 0.0), SENSING_RANGE).passing == 0.0
    tangent = math.sqrt(0.2**2 - 0.07**2)
    edge = math.asin(0.07 / 0.2)  # the tangent's angle off the line to the centre
    ray = edge + 0.1  # beta 0.1 to the left of the tangent
    foot = tangent * math.cos(0.1)

    def passing(distance: float) -> float:
        goal = (tcp[0] + distance * math.cos(ray), tcp[1] + distance * math.sin(ray))
        seen = measure(obstacle, tcp, goal, SENSING_RANGE)
        assert not seen.blocked and seen.beta == pytest.approx(0.1)
        return seen.passing

    beyond = tangent * math.sin(0.1)
    assert passing(foot + 0.05) == pytest.approx(beyond) == passing(foot + 0.2)
    short = 0.5 * foot
    assert passing(short) == pytest.approx(math.dist((short, 0.0), (foot, beyond)))
    assert passing(short) > passing(0.9 * foot) > passing(foot - 1e-6) == pytest.approx(beyond)


@settings(max_examples=200, deadline=None)
@given(
    obstacle=obstacles(),
    scaled_radius=st.floats(min_value=0.0, max_value=4.0),
    angle=st.floats(min_value=-math.pi, max_value=math.pi),
    goal=st.tuples(unit_interval, unit_interval),
    sensing_range=st.floats(min_value=0.02, max_value=0.5),
)
def test_measure_properties(
    obstacle: EllipticCylinder,
    scaled_radius: float,
    angle: float,
    goal: tuple[float, float],
    sensing_range: float,
) -> None:
    px, py = point_at(obstacle, scaled_radius, angle)
    gx, gy = obstacle.x + goal[0], obstacle.y + goal[1]
    assume(math.hypot(gx - px, gy - py) > 1e-6)
    seen = measure(obstacle, (px, py, 0.5 * obstacle.height), (gx, gy), sensing_range)
    clearance = obstacle.clearance(px, py)
    assert seen.present == (clearance < sensing_range)
    assert 0.0 <= seen.min_distance <= sensing_range
    assert seen.d_left <= sensing_range
    assert seen.d_right <= sensing_range
    if not seen.present:
        assert seen.min_distance == sensing_range
        return
    assert seen.clearance == clearance
    assert seen.min_distance == max(clearance, 0.0)
    assert -1.0 - 1e-12 <= seen.ahead <= 1.0 + 1e-12
    # blocked: the segment TCP -> goal meets the section (direct walk along it).
    s = np.linspace(0.0, 1.0, 2001)
    inside = [obstacle.contains(px + t * (gx - px), py + t * (gy - py)) for t in s]
    if any(inside):
        assert seen.blocked
    if clearance < 0.0:
        assert seen.beta < 0.0
        return
    # beta: the smallest turn that makes the ray towards the goal touch (beta > 0) or clear
    # (beta < 0) the section.
    assume(1e-4 < abs(seen.beta) < math.pi - 1e-4)
    assume(clearance > 1e-3 * obstacle.semi_axes[1])
    heading = math.atan2(gy - py, gx - px)
    epsilon = 1e-6
    ahead = _ray_hits(obstacle, px, py, heading)
    assert (seen.beta < 0.0) == ahead
    magnitude = abs(seen.beta)
    inner = [_ray_hits(obstacle, px, py, heading + k * (magnitude - epsilon)) for k in (1, -1)]
    outer = [_ray_hits(obstacle, px, py, heading + k * (magnitude + epsilon)) for k in (1, -1)]
    if ahead:
        assert all(inner)
        assert not all(outer)
    else:
        assert not any(inner)
        assert any(outer)


# --------------------------------------------------------------------------- validation
