"""Plane geometry both sides of the wire agree on: the obstacle's elliptic section and angles.

The obstacle is a vertical cylinder of elliptic section standing on the floor (z = 0 up to
its height). It is *inflated* by the tool radius and a safety margin: the inflated section
is the ellipse with both semi-axes grown by that amount, which contains every point closer
than the inflation to the true section along the axes and is what clearance is measured to.
The controller's module DM measures it (``controller/obstacle.py``); the plant simulator uses
it as ground truth for collisions.

Squares are ``x * x`` and lengths :func:`length` (``sqrt(x * x + y * y)``), not ``x ** 2`` and
``math.hypot``: numpy has bit-identical twins of these (and not of libm's ``pow`` or Python's
``hypot``), so the batch simulator (``sim/batch.py``) reproduces this geometry, and the law
that uses it, exactly.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from protocol.errors import ConfigError

Point = tuple[float, float]
AXIS_SNAP = 1e-12


def wrap_angle(angle: float) -> float:
    """``angle`` in [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def length(x: float, y: float) -> float:
    """``sqrt(x * x + y * y)``: ``math.hypot`` without the extra precision numpy cannot match."""
    return math.sqrt(x * x + y * y)


def distance(first: Sequence[float], second: Sequence[float]) -> float:
    """Euclidean distance, as the square root of the squares summed in order (``math.dist``,
    like ``math.hypot``, has no bit-identical numpy twin)."""
    total = 0.0
    for a, b in zip(first, second, strict=True):
        total += (a - b) * (a - b)
    return math.sqrt(total)


def cross(first: Point, second: Point) -> float:
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
        for name in ("x", "y", "long_diameter", "short_diameter", "height", "yaw", "inflation"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(f"obstacle.{name}", f"must be a finite number, got {value!r}")
        for name in ("long_diameter", "short_diameter", "height"):
            if getattr(self, name) <= 0.0:
                raise ConfigError(f"obstacle.{name}", "must be positive")
        if self.short_diameter > self.long_diameter:
            raise ConfigError("obstacle.short_diameter", "must not exceed long_diameter")
        if self.inflation < 0.0:
            raise ConfigError("obstacle.inflation", "must not be negative")

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

    def to_local(self, px: float, py: float) -> Point:
        dx, dy = px - self.x, py - self.y
        cos_yaw, sin_yaw = math.cos(self.yaw), math.sin(self.yaw)
        return (cos_yaw * dx + sin_yaw * dy, -sin_yaw * dx + cos_yaw * dy)

    def to_world(self, lx: float, ly: float) -> Point:
        cos_yaw, sin_yaw = math.cos(self.yaw), math.sin(self.yaw)
        return (self.x + cos_yaw * lx - sin_yaw * ly, self.y + sin_yaw * lx + cos_yaw * ly)

    def contains(self, px: float, py: float) -> bool:
        a, b = self.semi_axes
        lx, ly = self.to_local(px, py)
        su, sv = lx / a, ly / b
        return su * su + sv * sv < 1.0

    def nearest_point(self, px: float, py: float) -> tuple[float, Point]:
        """Signed distance to the inflated section's boundary and the boundary point."""
        a, b = self.semi_axes
        lx, ly = self.to_local(px, py)
        distance, (cx, cy) = _ellipse_distance(a, b, abs(lx), abs(ly))
        return distance, self.to_world(math.copysign(cx, lx), math.copysign(cy, ly))

    def clearance(self, px: float, py: float) -> float:
        return self.nearest_point(px, py)[0]

    def tangent_points(self, px: float, py: float) -> tuple[Point, Point] | None:
        """The (left, right) edges seen from (px, py) looking at the centre; None if inside."""
        a, b = self.semi_axes
        lx, ly = self.to_local(px, py)
        sx, sy = lx / a, ly / b
        norm = length(sx, sy)
        if norm <= 1.0:
            return None
        centre_angle = math.atan2(sy, sx)
        spread = math.acos(1.0 / norm)
        first = self.to_world(
            a * math.cos(centre_angle + spread), b * math.sin(centre_angle + spread)
        )
        second = self.to_world(
            a * math.cos(centre_angle - spread), b * math.sin(centre_angle - spread)
        )
        to_centre = (self.x - px, self.y - py)
        if cross(to_centre, (first[0] - px, first[1] - py)) > 0.0:
            return first, second
        return second, first

    def line_crossings(
        self, px: float, py: float, qx: float, qy: float
    ) -> tuple[float, float] | None:
        """Parameters s (point = p + s (q - p)) where the line p->q crosses the section."""
        a, b = self.semi_axes
        plx, ply = self.to_local(px, py)
        qlx, qly = self.to_local(qx, qy)
        ox, oy = plx / a, ply / b
        dx, dy = (qlx - plx) / a, (qly - ply) / b
        quad_a = dx * dx + dy * dy
        if quad_a == 0.0:
            return None
        half_b = ox * dx + oy * dy
        quad_c = ox * ox + oy * oy - 1.0
        discriminant = half_b * half_b - quad_a * quad_c
        if discriminant < 0.0:
            return None
        root = math.sqrt(discriminant)
        return ((-half_b - root) / quad_a, (-half_b + root) / quad_a)


def _ellipse_distance(a: float, b: float, u: float, v: float) -> tuple[float, Point]:
    """Signed distance from (u, v), u, v >= 0, to the ellipse x^2/a^2 + y^2/b^2 = 1.

    Eberly's method ("Distance from a point to an ellipse", 2013): the closest point is
    (a^2 u / (t + a^2), b^2 v / (t + b^2)) for the root t > -min(a, b)^2 of a convex,
    decreasing function, which Newton's method approaches monotonically from below.
    """
    if a < b:
        distance, (cy, cx) = _ellipse_distance(b, a, v, u)
        return distance, (cx, cy)
    su, sv = u / a, v / b
    inside = su * su + sv * sv < 1.0
    # A coordinate within rounding of an axis is taken as on it (an error of at most 1e-12 of
    # the axis), where the closed forms below hold and Newton's denominators could vanish.
    if v <= AXIS_SNAP * b:
        v = 0.0
    if u <= AXIS_SNAP * a:
        u = 0.0
    if v == 0.0:
        if u < (a * a - b * b) / a:
            x0 = a * a * u / (a * a - b * b)
            sx = x0 / a
            y0 = b * math.sqrt(max(0.0, 1.0 - sx * sx))
            return -length(x0 - u, y0), (x0, y0)
        return u - a, (a, 0.0)
    if u == 0.0:
        return v - b, (0.0, b)
    # Newton on s = t + b^2 rather than on t: near the long axis the root t is within a hair
    # of -b^2, and t + b^2 computed from t would keep only a few digits.
    gap = a * a - b * b
    # Both starts are below the root (either term alone is 1 there).
    s = max(b * v, a * u - gap)
    for _ in range(64):
        ratio_u = a * u / (s + gap)
        ratio_v = b * v / s
        value = ratio_u * ratio_u + ratio_v * ratio_v - 1.0
        if value <= 0.0:
            break
        slope = -2.0 * (ratio_u * ratio_u / (s + gap) + ratio_v * ratio_v / s)
        step = value / slope
        s -= step
        if abs(step) <= 1e-15 * s:
            break
    cx, cy = a * a * u / (s + gap), b * b * v / s
    found = length(cx - u, cy - v)
    return (-found if inside else found), (cx, cy)
