"""The obstacle and module DM (detection and measurement) of the paper's Fig. 6.

The obstacle itself (:class:`protocol.geometry.EllipticCylinder`) is inflated by the tool
radius and a safety margin; DM measures against the inflated section.

What DM reports, seen from the tool centre point (TCP) looking towards the next waypoint p_j
(the paper's section 3.2):

- ``clearance``: signed distance from the TCP to the inflated section (negative inside);
- ``d_left`` / ``d_right``: distance to the part of the section left / right of the line from
  the TCP to p_j (the side the nearest point lies on gets ``clearance``; the other side gets
  the distance to where that line crosses the section, or the sensing range if it does not);
  ``sign(d_left - d_right)`` is +1 when the obstacle is nearer on the right, so turn left;
- ``beta``: the angle from the direction to p_j to the nearer (in angle) of the two edges, the
  tangent points of the inflated section seen from the TCP, signed: positive when the
  direction to p_j clears the obstacle by that angle, negative when that direction points
  into the obstacle and the TCP must turn by that angle to clear it (continuous as the
  direction sweeps across an edge). Table 2's "beta small, k_C big" then
  reads: the closer the obstacle is to (or the deeper it is in) the way, the more AO counts;
- ``blocked``: the straight segment from the TCP to p_j crosses the inflated section;
- ``ahead``: cosine of the angle between the direction to p_j and the direction to the
  nearest point (1: straight ahead, -1: behind, so already passed);
- ``toward``: the same cosine for the direction the TCP moves in (its ``heading``; -1 when
  none is given). An obstacle the TCP moves towards matters even when p_j lies elsewhere:
  PT follows a plan that may pass through the obstacle, and an arm that went round it on
  the far side of the plan is steered back through it;
- ``to_nearest``: the way from the TCP to the nearest point of the inflated section (for the
  control law's approach limit).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import cache
from typing import NamedTuple

from protocol.geometry import (
    EllipticCylinder,
    Point,
    Section,
    length,
    line_crossings,
    nearest_point,
    tangent_points,
    to_local,
    wrap_angle,
)
from protocol.ops import SCALAR, Mask, Ops, Real

ROOM_MAX = 0.05
"""m: the free room around a waypoint (:func:`free_room`) is at most this."""
REACH_MARGIN = 1e-6
"""m: beyond the sensing range plus the long semi-axis (plus this, for rounding) from an
obstacle's centre, the clearance exceeds the range: DM finds nothing, without measuring."""
NO_OBSTACLE = Section(100.0, 100.0, 1.0, 0.0, 0.01, 0.005, 0.0, -math.inf)
"""The section measured where there is no obstacle: one no TCP is ever below."""


class ObstacleMeasurement(NamedTuple):
    """What module DM hands to AO and to the coordinator on one tick (floats, or arrays of
    one element per run)."""

    present: Mask
    clearance: Real
    d_left: Real
    d_right: Real
    beta: Real
    blocked: Mask
    ahead: Real
    toward: Real = -1.0
    to_nearest: tuple[Real, Real] = (0.0, 0.0)
    passing: Real = math.inf
    """How near the straight way from the TCP to the goal passes the obstacle, measured to
    the tangent point nearer that way (0 where the way is blocked or the TCP inside)."""

    @property
    def min_distance(self) -> Real:
        """min(d_L, d_R), of one measurement (floats)."""
        return min(self.d_left, self.d_right)


@cache
def absent(sensing_range: float) -> ObstacleMeasurement:
    """The measurement when no obstacle is in reach (none, beyond range, or tool above it)."""
    return ObstacleMeasurement(
        present=False,
        clearance=math.inf,
        d_left=sensing_range,
        d_right=sensing_range,
        beta=math.pi,
        blocked=False,
        ahead=-1.0,
        toward=-1.0,
    )


def measure(
    obstacle: EllipticCylinder | None,
    tcp: tuple[float, float, float],
    goal: Point,
    sensing_range: float,
    heading: float | None = None,
) -> ObstacleMeasurement:
    """Module DM: measure ``obstacle`` from the TCP towards the next waypoint ``goal``
    (and along ``heading`` for ``toward``, if given)."""
    section = NO_OBSTACLE if obstacle is None else obstacle.section()
    angle = 0.0 if heading is None else heading
    found = sense(SCALAR, section, sensing_range, tcp, goal, (math.cos(angle), math.sin(angle)))
    return found if heading is not None or not found.present else found._replace(toward=-1.0)


def sense(
    ops: Ops,
    section: Section,
    sensing_range: float,
    tcp: tuple[Real, Real, Real],
    goal: tuple[Real, Real],
    heading: tuple[Real, Real],
) -> ObstacleMeasurement:
    """Module DM from the TCP towards ``goal`` (x, y), the TCP moving along ``heading`` (its
    cos and sin): what :func:`measure` finds, as floats or for many runs at once."""
    px, py, pz = tcp
    dx, dy = px - section.x, py - section.y
    reach = section.a + sensing_range + REACH_MARGIN
    return ops.branch(
        ops.not_(pz >= section.top) & (dx * dx + dy * dy < reach * reach),
        _sense_near,
        absent(sensing_range),
        ops,
        sensing_range,
        section,
        px,
        py,
        goal,
        heading,
    )


def _sense_near(
    ops: Ops,
    sensing_range: float,
    section: Section,
    px: Real,
    py: Real,
    goal: tuple[Real, Real],
    heading: tuple[Real, Real],
) -> ObstacleMeasurement:
    """:func:`sense` below the obstacle's top and near enough to measure."""
    lx, ly = to_local(section, px, py)
    clearance, nearest_x, nearest_y = nearest_point(ops, section, lx, ly)
    return ops.branch(
        ops.not_(clearance >= sensing_range),
        _sense_present,
        absent(sensing_range),
        ops,
        sensing_range,
        section,
        px,
        py,
        lx,
        ly,
        clearance,
        (nearest_x - px, nearest_y - py),
        goal,
        heading,
    )


def _sense_present(
    ops: Ops,
    sensing_range: float,
    section: Section,
    px: Real,
    py: Real,
    lx: Real,
    ly: Real,
    clearance: Real,
    to_nearest: tuple[Real, Real],
    goal: tuple[Real, Real],
    heading: tuple[Real, Real],
) -> ObstacleMeasurement:
    """:func:`sense` within the sensing range."""
    gx, gy = goal[0] - px, goal[1] - py
    goal_distance = length(ops, gx, gy)
    on_goal = goal_distance < 1e-9
    if ops.any(on_goal):  # on the goal: look at the obstacle instead
        gx = ops.where(on_goal, section.x - px, gx)
        gy = ops.where(on_goal, section.y - py, gy)
        goal_distance = ops.where(on_goal, ops.max(length(ops, gx, gy), 1e-9), goal_distance)
    near = ops.clip(clearance, 0.0, sensing_range)
    crosses, entry, exit_ = line_crossings(ops, section, lx, ly, px + gx, py + gy)
    other = ops.min(ops.min(abs(entry), abs(exit_)) * goal_distance, sensing_range)
    other = ops.where(crosses, ops.max(other, near), sensing_range)
    blocked = crosses & (entry <= 1.0) & (exit_ >= 0.0)
    to_x, to_y = to_nearest
    side = gx * to_y - gy * to_x
    nearest_distance = length(ops, to_x, to_y)
    span = nearest_distance * goal_distance
    spanned, apart = span > 0.0, nearest_distance > 0.0
    ahead = ops.where(spanned, (gx * to_x + gy * to_y) / ops.where(spanned, span, 1.0), 1.0)
    heading_cos, heading_sin = heading
    toward = ops.where(
        apart,
        (heading_cos * to_x + heading_sin * to_y) / ops.where(apart, nearest_distance, 1.0),
        -1.0,
    )
    left_side = side >= 0.0
    outside, left_x, left_y, right_x, right_y = tangent_points(ops, section, px, py, lx, ly)
    goal_angle = ops.atan2(gy, gx)
    left = wrap_angle(ops.atan2(left_y - py, left_x - px) - goal_angle)
    right = wrap_angle(ops.atan2(right_y - py, right_x - px) - goal_angle)
    beta = ops.min(abs(left), abs(right))
    beta = ops.where((left > 0.0) & (right < 0.0), -beta, beta)
    nearer_left = abs(left) <= abs(right)
    tangent = length(
        ops,
        ops.where(nearer_left, left_x, right_x) - px,
        ops.where(nearer_left, left_y, right_y) - py,
    )
    passing = ops.where(
        outside & ops.not_(blocked), _way_passing(ops, tangent, goal_distance, beta), 0.0
    )
    return ObstacleMeasurement(
        ops.full(clearance, True),
        clearance,
        ops.where(left_side, near, other),
        ops.where(left_side, other, near),
        ops.where(outside, beta, -math.pi / 2.0),
        blocked,
        ahead,
        toward,
        to_nearest,
        passing,
    )


def _way_passing(ops: Ops, tangent: Real, goal_distance: Real, beta: Real) -> Real:
    """How near the way from the TCP to the goal (``goal_distance`` long, ``beta`` off the
    tangent ``tangent`` long) comes to the tangent point: the ray's distance from it, or the
    goal's where the way ends before the ray's nearest point. Measured on the ray alone, it
    fell fast as a near goal's direction turned, and k_C pulsed."""
    angle = ops.clip(beta, 0.0, math.pi / 2.0)
    cos = ops.cos(angle)
    to_end = tangent * tangent + goal_distance * goal_distance - 2.0 * tangent * goal_distance * cos
    return ops.where(
        goal_distance < tangent * cos, ops.sqrt(ops.max(to_end, 0.0)), tangent * ops.sin(angle)
    )


def free_room(obstacle: EllipticCylinder | None, point: Sequence[float]) -> float:
    """The radius around a waypoint that the obstacle leaves free (at most ROOM_MAX): its
    clearance from the inflated obstacle, where it is below the obstacle's top."""
    if obstacle is None or point[2] >= obstacle.height + obstacle.inflation:
        return ROOM_MAX
    return min(max(obstacle.clearance(point[0], point[1]), 0.0), ROOM_MAX)
