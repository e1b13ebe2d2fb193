"""Plane geometry both sides of the wire agree on: the obstacle's elliptic section and angles.

The obstacle is a vertical cylinder of elliptic section standing on the floor (z = 0 up to
its height). It is *inflated* by the tool radius and a safety margin: the inflated section
is the ellipse with both semi-axes grown by that amount, which contains every point closer
than the inflation to the true section along the axes and is what clearance is measured to.
The controller's module DM measures it (``controller/obstacle.py``); the plant simulator uses
it as ground truth for collisions.

The formulas are written over :mod:`protocol.ops`, for one obstacle (floats) or one per run
of a batch (arrays), with :class:`Section` as the numbers they take. Squares are ``x * x`` and
lengths :func:`length` (``sqrt(x * x + y * y)``), not ``x ** 2`` and ``math.hypot``: numpy has
bit-identical twins of these, and not of libm's ``pow`` or Python's ``hypot``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

from protocol.errors import ConfigError
from protocol.ops import SCALAR, Mask, Ops, Real

Point = tuple[float, float]
AXIS_SNAP = 1e-12
NEWTON_ITERATIONS = 64
"""At most this many Newton steps in :func:`ellipse_distance` (a few are the rule)."""


def wrap_angle(angle: Real) -> Real:
    """``angle`` in [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def length(ops: Ops, x: Real, y: Real) -> Real:
    """``sqrt(x * x + y * y)``: ``math.hypot`` without the extra precision numpy cannot match."""
    return ops.sqrt(x * x + y * y)


def distance(ops: Ops, first: Sequence[Real], second: Sequence[Real]) -> Real:
    """Euclidean distance, as the square root of the squares summed in order (``math.dist``,
    like ``math.hypot``, has no bit-identical numpy twin)."""
    total = 0.0
    for a, b in zip(first, second, strict=True):
        total = total + (a - b) * (a - b)
    return ops.sqrt(total)


def cross(first: tuple[Real, Real], second: tuple[Real, Real]) -> Real:
    """The z component of the cross product of two plane vectors."""
    return first[0] * second[1] - first[1] * second[0]


@dataclass(frozen=True, slots=True)
class EllipticCylinder:
    """An obstacle: centre (x, y), diameters r1 >= r2 along/across its yaw, height h (m)."""

    x: float
    y: float
    long_diameter: float
    short_diameter: float
    height: float
    yaw: float = 0.0
    inflation: float = 0.0

    def __post_init__(self) -> None:
        """What the obstacle's schema cannot say (``protocol/validation.py`` checks the rest:
        finite, positive sizes, a non-negative inflation)."""
        if self.short_diameter > self.long_diameter:
            raise ConfigError("obstacle.short_diameter", "must not exceed long_diameter")

    @property
    def semi_axes(self) -> tuple[float, float]:
        """Semi-axes of the inflated section."""
        return (
            self.long_diameter / 2.0 + self.inflation,
            self.short_diameter / 2.0 + self.inflation,
        )

    def grown(self, extra: float) -> EllipticCylinder:
        """The same obstacle inflated by ``extra`` more."""
        return EllipticCylinder(
            self.x,
            self.y,
            self.long_diameter,
            self.short_diameter,
            self.height,
            self.yaw,
            self.inflation + extra,
        )

    def section(self) -> Section:
        """The inflated section as the numbers the geometry's formulas take."""
        a, b = self.semi_axes
        return Section(
            self.x,
            self.y,
            math.cos(self.yaw),
            math.sin(self.yaw),
            a,
            b,
            self.inflation,
            self.height + self.inflation,
        )

    def to_local(self, px: float, py: float) -> Point:
        return to_local(self.section(), px, py)

    def to_world(self, lx: float, ly: float) -> Point:
        return to_world(self.section(), lx, ly)

    def contains(self, px: float, py: float) -> bool:
        section = self.section()
        lx, ly = to_local(section, px, py)
        return bool(within(section.a, section.b, lx, ly))

    def holds(self, px: float, py: float, pz: float) -> bool:
        """The point is inside the solid: within the inflated section and below the inflated
        top (the plant's collision truth, and the soak checker's, on their obstacles)."""
        return pz < self.height + self.inflation and self.contains(px, py)

    def nearest_point(self, px: float, py: float) -> tuple[float, Point]:
        """Signed distance to the inflated section's boundary and the boundary point."""
        section = self.section()
        distance, x, y = nearest_to(SCALAR, section, px, py)
        return distance, (x, y)

    def clearance(self, px: float, py: float) -> float:
        return self.nearest_point(px, py)[0]

    def tangent_points(self, px: float, py: float) -> tuple[Point, Point] | None:
        """The (left, right) edges seen from (px, py) looking at the centre; None if inside."""
        section = self.section()
        outside, left_x, left_y, right_x, right_y = tangent_points(
            SCALAR, section, px, py, *to_local(section, px, py)
        )
        return ((left_x, left_y), (right_x, right_y)) if outside else None

    def line_crossings(
        self, px: float, py: float, qx: float, qy: float
    ) -> tuple[float, float] | None:
        """Parameters s (point = p + s (q - p)) where the line p->q crosses the section."""
        section = self.section()
        crosses, entry, exit_ = line_crossings(SCALAR, section, *to_local(section, px, py), qx, qy)
        return (entry, exit_) if crosses else None


class Section(NamedTuple):
    """An obstacle's inflated section as numbers: floats for one obstacle, or arrays with one
    element per run (the batch's runs each have their own). The formulas below take it."""

    x: Real
    y: Real
    cos: Real
    """cos yaw"""
    sin: Real
    """sin yaw"""
    a: Real
    """The long semi-axis, inflated: a >= b."""
    b: Real
    inflation: Real
    top: Real
    """Height plus inflation: the TCP at or above it passes over (-inf: no obstacle)."""


def to_local(section: Section, px: Real, py: Real) -> tuple[Real, Real]:
    """World to the section's own frame (centre at 0, long axis along x)."""
    dx, dy = px - section.x, py - section.y
    return (section.cos * dx + section.sin * dy, -section.sin * dx + section.cos * dy)


def to_world(section: Section, lx: Real, ly: Real) -> tuple[Real, Real]:
    return (
        section.x + section.cos * lx - section.sin * ly,
        section.y + section.sin * lx + section.cos * ly,
    )


def within(a: Real, b: Real, u: Real, v: Real) -> Mask:
    """Whether the local point (u, v) is strictly inside the ellipse of semi-axes a, b."""
    su, sv = u / a, v / b
    return su * su + sv * sv < 1.0


def nearest_point(ops: Ops, section: Section, lx: Real, ly: Real) -> tuple[Real, Real, Real]:
    """Signed distance from the local point (lx, ly) to the section's boundary (negative
    inside) and the boundary point nearest to it (world x, y)."""
    distance, cx, cy = ellipse_distance(ops, section.a, section.b, abs(lx), abs(ly))
    x, y = to_world(section, ops.copysign(cx, lx), ops.copysign(cy, ly))
    return distance, x, y


def nearest_to(ops: Ops, section: Section, px: Real, py: Real) -> tuple[Real, Real, Real]:
    """:func:`nearest_point` of the world point (px, py): its signed distance to the
    section's boundary and the boundary point nearest to it."""
    return nearest_point(ops, section, *to_local(section, px, py))


def tangent_points(
    ops: Ops, section: Section, px: Real, py: Real, lx: Real, ly: Real
) -> tuple[Mask, Real, Real, Real, Real]:
    """Whether (px, py) (local: lx, ly) is outside the section, and the left and right edges
    (x, y) seen from there looking at the centre (meaningless inside)."""
    a, b = section.a, section.b
    sx, sy = lx / a, ly / b
    norm = length(ops, sx, sy)
    outside = norm > 1.0
    centre_angle = ops.atan2(sy, sx)
    spread = ops.acos(1.0 / ops.where(outside, norm, 1.0))
    first_x, first_y = to_world(
        section, a * ops.cos(centre_angle + spread), b * ops.sin(centre_angle + spread)
    )
    second_x, second_y = to_world(
        section, a * ops.cos(centre_angle - spread), b * ops.sin(centre_angle - spread)
    )
    to_centre_x, to_centre_y = section.x - px, section.y - py
    first_left = to_centre_x * (first_y - py) - to_centre_y * (first_x - px) > 0.0
    return (
        outside,
        ops.where(first_left, first_x, second_x),
        ops.where(first_left, first_y, second_y),
        ops.where(first_left, second_x, first_x),
        ops.where(first_left, second_y, first_y),
    )


def line_crossings(
    ops: Ops, section: Section, plx: Real, ply: Real, qx: Real, qy: Real
) -> tuple[Mask, Real, Real]:
    """Whether the line from p (local: plx, ply) to q (world) crosses the section, and the
    parameters s of its entry and exit (point = p + s (q - p); meaningless where not)."""
    a, b = section.a, section.b
    qlx, qly = to_local(section, qx, qy)
    ox, oy = plx / a, ply / b
    dx, dy = (qlx - plx) / a, (qly - ply) / b
    quad_a = dx * dx + dy * dy
    half_b = ox * dx + oy * dy
    quad_c = ox * ox + oy * oy - 1.0
    discriminant = half_b * half_b - quad_a * quad_c
    crosses = (quad_a != 0.0) & ops.not_(discriminant < 0.0)
    root = ops.sqrt(ops.where(crosses, discriminant, 0.0))
    divisor = ops.where(crosses, quad_a, 1.0)
    return crosses, (-half_b - root) / divisor, (-half_b + root) / divisor


def ellipse_distance(ops: Ops, a: Real, b: Real, u: Real, v: Real) -> tuple[Real, Real, Real]:
    """Signed distance from (u, v), u, v >= 0, to the ellipse x^2/a^2 + y^2/b^2 = 1 (a >= b),
    and the nearest point of it (cx, cy).

    Eberly's method ("Distance from a point to an ellipse", 2013): the closest point is
    (a^2 u / (t + a^2), b^2 v / (t + b^2)) for the root t > -b^2 of a convex, decreasing
    function, which Newton's method approaches monotonically from below. On the axes it has
    closed forms.
    """
    inside = within(a, b, u, v)
    # A coordinate within rounding of an axis is taken as on it (an error of at most 1e-12 of
    # the axis), where the closed forms hold and Newton's denominators could vanish.
    v = ops.where(v <= AXIS_SNAP * b, 0.0, v)
    u = ops.where(u <= AXIS_SNAP * a, 0.0, u)
    gap = a * a - b * b
    # On the long axis: within the evolute's reach (off the axis), or at the axis's end.
    evolute = u < gap / a
    x0 = a * a * u / ops.where(evolute, gap, 1.0)
    sx = x0 / a
    y0 = b * ops.sqrt(ops.max(0.0, 1.0 - sx * sx))
    distance = ops.where(evolute, -length(ops, x0 - u, y0), u - a)
    cx = ops.where(evolute, x0, a)
    cy = ops.where(evolute, y0, 0.0)
    # On the short axis.
    on_short = (u == 0.0) & (v != 0.0)
    distance = ops.where(on_short, v - b, distance)
    cx = ops.where(on_short, 0.0, cx)
    cy = ops.where(on_short, b, cy)
    return ops.branch(
        (u != 0.0) & (v != 0.0),
        _ellipse_distance_off_axes,
        (distance, cx, cy),
        ops,
        a,
        b,
        u,
        v,
        inside,
    )


def _ellipse_distance_off_axes(
    ops: Ops, a: Real, b: Real, u: Real, v: Real, inside: Mask
) -> tuple[Real, Real, Real]:
    """:func:`ellipse_distance` off both axes: Newton on s = t + b^2 rather than on t (near
    the long axis the root t is within a hair of -b^2, and t + b^2 computed from t would keep
    only a few digits). Both starts are below the root (either term alone is 1 there)."""
    gap = a * a - b * b
    _, s, *_ = ops.converge(
        _newton_step,
        (ops.full(u, True), ops.max(b * v, a * u - gap), a * u, b * v, gap),
        NEWTON_ITERATIONS,
        ops,
    )
    cx, cy = a * a * u / (s + gap), b * b * v / s
    found = length(ops, cx - u, cy - v)
    return ops.where(inside, -found, found), cx, cy


def _newton_step(
    going: Mask, s: Real, a_u: Real, b_v: Real, gap: Real, ops: Ops
) -> tuple[Mask, Real, Real, Real, Real]:
    """One Newton step of :func:`_ellipse_distance_off_axes` where still ``going``."""
    shifted = s + gap
    ratio_u = a_u / shifted
    ratio_v = b_v / s
    square_u, square_v = ratio_u * ratio_u, ratio_v * ratio_v
    value = square_u + square_v - 1.0
    moving = going & ops.not_(value <= 0.0)
    step = value / (-2.0 * (square_u / shifted + square_v / s))
    s = ops.where(moving, s - step, s)
    return moving & ops.not_(abs(step) <= 1e-15 * s), s, a_u, b_v, gap
