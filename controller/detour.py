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
that neither side can take round (:func:`ways_round`). A leg that cuts through the hole inside
the inner reach counts as the arm takes it: sliding round the hole with theta2 at its stop
(:func:`_leg_passable`); AO asks first for a way clear of the hole (``slide=False``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from protocol.config import RobotConfig
from protocol.geometry import (
    EllipticCylinder,
    Section,
    line_crossings,
    to_local,
    to_world,
    within,
    wrap_angle,
)
from protocol.kinematics import Elbow, reaches
from protocol.ops import SCALAR, Mask, Ops, Real

ARC_POINTS = 24
"""Points checked along the boundary between the two tangent points."""
LEG_POINTS = (0.25, 0.5, 0.75)
"""Where on each straight leg (TCP to the boundary, the boundary to the waypoint) a point is
checked."""
SLIDE_POINTS = 24
"""Points checked along the arc a leg through the hole inside the inner reach slides round."""
STRAIGHT_POINTS = 16
"""Points a straight move is cut into to check it (:func:`straight_passable`)."""
LIMIT_ROOM = math.radians(0.5)
"""rad: how far inside every joint limit the way must stay (about 2.5 mm of radius at the
inner reach limit), as rule 6 says; the brute force of ``sim/passability.py`` searches with
the same room."""
SLIDE_NUDGE = 1e-9
"""Share of its radius the slide's arc is moved outwards, so that rounding leaves it reached."""


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
    slide: bool = True,
) -> Mask:
    """Whether the way from ``start`` round ``section`` on ``side`` (+1 the left, seen from
    ``start`` looking at the goal: clockwise round it; -1 the right) to ``goal`` stays within
    the joint limits of an arm whose elbow is on ``elbow``'s side (its legs:
    :func:`_leg_passable`; without ``slide``, only a way clear of the hole inside the inner
    reach)."""
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
        ok = ok & _leg_passable(ops, robot, section, end, edge, elbow, slide)
    return ok


def _leg_passable(
    ops: Ops,
    robot: RobotConfig,
    section: Section,
    start: tuple[Real, Real],
    end: tuple[Real, Real],
    elbow: Real,
    slide: bool,
) -> Mask:
    """Whether the arm can follow the straight leg from ``start`` to ``end`` beside
    ``section``: its LEG_POINTS reached LIMIT_ROOM inside the joint limits, except where the
    leg cuts through the hole inside the inner reach. There the arm slides round the hole
    instead, theta2 held at its stop: along the circle where theta2 is LIMIT_ROOM inside it,
    from where the leg enters the circle to where it leaves it, and that arc must keep
    outside ``section`` and inside theta1's limits. Judged by the leg's points alone, such
    ways were closed: the plan check refused ``wide`` tasks a brute-force search
    (``sim/passability.py``) finds a way for, and where both sides were judged closed AO
    kept to one closed for good. Without ``slide``: the LEG_POINTS alone."""
    if not slide:
        return _reaches_along(ops, robot, start, end, LEG_POINTS, elbow)
    stop = ops.where(elbow > 0.0, robot.theta2_max, -robot.theta2_min) - LIMIT_ROOM
    a1, a2 = robot.a1, robot.a2
    inner = ops.sqrt(a1 * a1 + a2 * a2 + 2.0 * a1 * a2 * ops.cos(stop))
    # |start + share (end - start)| = inner: the shares where the leg enters and leaves it.
    dx, dy = end[0] - start[0], end[1] - start[1]
    quadratic = dx * dx + dy * dy
    half_linear = start[0] * dx + start[1] * dy
    constant = start[0] * start[0] + start[1] * start[1] - inner * inner
    discriminant = half_linear * half_linear - quadratic * constant
    meets = (quadratic > 0.0) & (discriminant > 0.0)
    root = ops.sqrt(ops.where(meets, discriminant, 0.0))
    divisor = ops.where(meets, quadratic, 1.0)
    enters = ops.clip((-half_linear - root) / divisor, 0.0, 1.0)
    leaves = ops.clip((-half_linear + root) / divisor, 0.0, 1.0)
    cuts = meets & (enters < leaves)
    ok: Mask = True
    for share in LEG_POINTS:
        x, y = start[0] + share * dx, start[1] + share * dy
        in_hole = cuts & (enters < share) & (share < leaves)
        ok = ok & (reaches(ops, robot, x, y, elbow, LIMIT_ROOM) | in_hole)
    if not ops.any(cuts):
        return ok
    first = ops.atan2(start[1] + enters * dy, start[0] + enters * dx)
    last = ops.atan2(start[1] + leaves * dy, start[0] + leaves * dx)
    turn = wrap_angle(last - first)
    radius = inner * (1.0 + SLIDE_NUDGE)
    slides: Mask = True
    for k in range(SLIDE_POINTS):
        angle = first + turn * (k / (SLIDE_POINTS - 1))
        x, y = radius * ops.cos(angle), radius * ops.sin(angle)
        clear = ops.not_(within(section.a, section.b, *to_local(section, x, y)))
        slides = slides & clear & reaches(ops, robot, x, y, elbow, LIMIT_ROOM)
    return ok & (ops.not_(cuts) | slides)


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
