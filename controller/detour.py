"""Which way round the obstacle the arm can take.

AO goes round the obstacle it steers by (the inflated obstacle grown by ``ao_pass_margin``)
on one side: from the TCP to the tangent point on that side, along the boundary, and from
the tangent point of the waypoint it heads for on to that waypoint. Whether the arm can
follow that way, the joint limits decide, not the distances d_L and d_R: near the inner
reach limit the side nearer the base runs through where theta2 would have to pass its stop.
:func:`passable` checks points along a side's way (:func:`protocol.kinematics.reaches`,
LIMIT_ROOM inside the limits), on floats for the controller and on arrays for the study;
AO takes the other side where its own is closed (``behaviours.avoid_obstacle``), also where
the straight way to the waypoint keeps clear of the obstacle but runs out of the limits
(:func:`straight_passable`: through the hole inside the inner reach, where the plan bends
round past the obstacle; there the way is judged round the inflated obstacle, without AO's
margin, which the plan passes within), and the plan check refuses a task with a segment
that neither side can take round (:func:`ways_round`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from protocol.config import RobotConfig
from protocol.geometry import EllipticCylinder, Section, line_crossings, to_local, to_world
from protocol.kinematics import Elbow, reaches
from protocol.ops import SCALAR, Mask, Ops, Real

ARC_POINTS = 24
"""Points checked along the boundary between the two tangent points."""
LEG_POINTS = (0.25, 0.5, 0.75)
"""Where on each straight leg (TCP to the boundary, the boundary to the waypoint) a point is
checked."""
STRAIGHT_POINTS = 16
"""Points a straight move is cut into to check it (:func:`straight_passable`)."""
LIMIT_ROOM = math.radians(0.5)
"""rad: how far inside every joint limit the way must stay (about 2.5 mm of radius at the
inner reach limit): the arm may pass up to the pass margin inside the boundary checked, and
more room refused tasks that a dense search (``sim/passability.py``) finds a way through."""


def _anomaly(ops: Ops, section: Section, px: Real, py: Real) -> tuple[Real, Real]:
    """The eccentric anomaly of (px, py) about ``section`` and half the angle its two tangent
    points span seen from there (0 inside)."""
    lx, ly = to_local(section, px, py)
    sx, sy = lx / section.a, ly / section.b
    norm = ops.sqrt(sx * sx + sy * sy)
    outside = norm > 1.0
    return ops.atan2(sy, sx), ops.where(outside, ops.acos(1.0 / ops.where(outside, norm, 1.0)), 0.0)


def passable(
    ops: Ops,
    robot: RobotConfig,
    section: Section,
    start: tuple[Real, Real],
    goal: tuple[Real, Real],
    side: Real,
    elbow: Real,
) -> Mask:
    """Whether the way from ``start`` round ``section`` on ``side`` (+1 the left, seen from
    ``start`` looking at the goal: clockwise round it; -1 the right) to ``goal`` stays within
    the joint limits of an arm whose elbow is on ``elbow``'s side."""
    start_angle, start_spread = _anomaly(ops, section, start[0], start[1])
    goal_angle, goal_spread = _anomaly(ops, section, goal[0], goal[1])
    # Left: the start's left tangent, clockwise (falling anomaly) to the goal's tangent it
    # meets first; right: the mirror image.
    leave = start_angle - side * start_spread
    arrive = goal_angle + side * goal_spread
    span = (side * (leave - arrive)) % math.tau
    ok: Mask = True
    for k in range(ARC_POINTS):
        angle = leave - side * span * (k / (ARC_POINTS - 1))
        x, y = to_world(section, section.a * ops.cos(angle), section.b * ops.sin(angle))
        ok = ok & reaches(ops, robot, x, y, elbow, LIMIT_ROOM)
    for end, angle in ((start, leave), (goal, arrive)):
        edge = to_world(section, section.a * ops.cos(angle), section.b * ops.sin(angle))
        ok = ok & _reaches_along(ops, robot, end, edge, LEG_POINTS, elbow)
    return ok


def straight_passable(
    ops: Ops,
    robot: RobotConfig,
    start: tuple[Real, Real],
    goal: tuple[Real, Real],
    elbow: Real,
) -> Mask:
    """Whether the straight move from ``start`` to ``goal`` stays within the joint limits
    (LIMIT_ROOM inside them) at STRAIGHT_POINTS - 1 points between the two."""
    shares = [k / STRAIGHT_POINTS for k in range(1, STRAIGHT_POINTS)]
    return _reaches_along(ops, robot, start, goal, shares, elbow)


def _reaches_along(
    ops: Ops,
    robot: RobotConfig,
    start: tuple[Real, Real],
    end: tuple[Real, Real],
    shares: Sequence[float],
    elbow: Real,
) -> Mask:
    """Whether the points at ``shares`` of the way from ``start`` to ``end`` are reached
    LIMIT_ROOM inside the joint limits."""
    ok: Mask = True
    for share in shares:
        x = start[0] + share * (end[0] - start[0])
        y = start[1] + share * (end[1] - start[1])
        ok = ok & reaches(ops, robot, x, y, elbow, LIMIT_ROOM)
    return ok


def ways_round(
    robot: RobotConfig,
    aim: EllipticCylinder,
    start: tuple[float, float, float],
    goal: tuple[float, float, float],
    elbow: Elbow,
) -> tuple[bool, bool] | None:
    """Whether the left and the right way round ``aim`` (the obstacle AO steers by) are
    passable for a straight move from ``start`` to ``goal``; None where that move does not
    need one (it passes the obstacle, or over it)."""
    section = aim.section()
    if max(start[2], goal[2]) >= section.top:
        return None
    crossings = line_crossings(
        SCALAR, section, *to_local(section, start[0], start[1]), goal[0], goal[1]
    )
    crosses, entry, exit_ = crossings
    if not (crosses and entry <= 1.0 and exit_ >= 0.0):
        return None
    return (
        bool(passable(SCALAR, robot, section, start[:2], goal[:2], 1, elbow.value)),
        bool(passable(SCALAR, robot, section, start[:2], goal[:2], -1, elbow.value)),
    )
