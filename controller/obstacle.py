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
from dataclasses import dataclass

from protocol.geometry import EllipticCylinder, Point, cross, length, wrap_angle


@dataclass(frozen=True, slots=True)
class ObstacleMeasurement:
    """What module DM hands to AO and to the coordinator on one tick."""

    present: bool
    clearance: float
    d_left: float
    d_right: float
    beta: float
    blocked: bool
    ahead: float
    toward: float = -1.0
    to_nearest: tuple[float, float] = (0.0, 0.0)

    @property
    def min_distance(self) -> float:
        return min(self.d_left, self.d_right)


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
    px, py, pz = tcp
    if obstacle is None or pz >= obstacle.height + obstacle.inflation:
        return absent(sensing_range)
    clearance, nearest = obstacle.nearest_point(px, py)
    if clearance >= sensing_range:
        return absent(sensing_range)
    gx, gy = goal[0] - px, goal[1] - py
    goal_distance = length(gx, gy)
    if goal_distance < 1e-9:  # on the goal: look at the obstacle instead
        gx, gy = obstacle.x - px, obstacle.y - py
        goal_distance = max(length(gx, gy), 1e-9)
    near = min(max(clearance, 0.0), sensing_range)
    crossings = obstacle.line_crossings(px, py, px + gx, py + gy)
    if crossings is None:
        other = sensing_range
        blocked = False
    else:
        entry, exit_ = crossings
        other = min(min(abs(entry), abs(exit_)) * goal_distance, sensing_range)
        other = max(other, near)
        blocked = entry <= 1.0 and exit_ >= 0.0
    to_nearest = (nearest[0] - px, nearest[1] - py)
    side = cross((gx, gy), to_nearest)
    nearest_distance = length(*to_nearest)
    span = nearest_distance * goal_distance
    ahead = (gx * to_nearest[0] + gy * to_nearest[1]) / span if span > 0.0 else 1.0
    toward = -1.0
    if heading is not None and nearest_distance > 0.0:
        toward = (
            math.cos(heading) * to_nearest[0] + math.sin(heading) * to_nearest[1]
        ) / nearest_distance
    d_left, d_right = (near, other) if side >= 0.0 else (other, near)
    edges = obstacle.tangent_points(px, py)
    if edges is None:
        beta = -math.pi / 2.0
    else:
        goal_angle = math.atan2(gy, gx)
        left, right = (wrap_angle(math.atan2(e[1] - py, e[0] - px) - goal_angle) for e in edges)
        beta = min(abs(left), abs(right))
        if left > 0.0 > right:
            beta = -beta
    return ObstacleMeasurement(
        True, clearance, d_left, d_right, beta, blocked, ahead, toward, to_nearest
    )
