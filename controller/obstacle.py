"""The obstacle and module DM (detection and measurement) of the paper's Fig. 6.

The obstacle is a vertical cylinder of elliptic section standing on the floor (z = 0 up to
its height). It is *inflated* by the tool radius and a safety margin: the inflated section
is the ellipse with both semi-axes grown by that amount, which contains every point closer
than the inflation to the true section along the axes and is what clearance is measured to.

What DM reports, seen from the tool centre point (TCP) looking towards the next waypoint p_j
(the paper's section 3.2 and DESIGN.md section 3):

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
  nearest point (1: straight ahead, -1: behind, so already passed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from protocol.errors import ConfigError

Point = tuple[float, float]
AXIS_SNAP = 1e-12


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
        return (lx / a) ** 2 + (ly / b) ** 2 < 1.0

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
        norm = math.hypot(sx, sy)
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
        if _cross(to_centre, (first[0] - px, first[1] - py)) > 0.0:
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
    )


def measure(
    obstacle: EllipticCylinder | None,
    tcp: tuple[float, float, float],
    goal: Point,
    sensing_range: float,
) -> ObstacleMeasurement:
    """Module DM: measure ``obstacle`` from the TCP towards the next waypoint ``goal``."""
    px, py, pz = tcp
    if obstacle is None or pz >= obstacle.height + obstacle.inflation:
        return absent(sensing_range)
    clearance, nearest = obstacle.nearest_point(px, py)
    if clearance >= sensing_range:
        return absent(sensing_range)
    gx, gy = goal[0] - px, goal[1] - py
    goal_distance = math.hypot(gx, gy)
    if goal_distance < 1e-9:  # on the goal: look at the obstacle instead
        gx, gy = obstacle.x - px, obstacle.y - py
        goal_distance = max(math.hypot(gx, gy), 1e-9)
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
    side = _cross((gx, gy), to_nearest)
    span = math.hypot(*to_nearest) * goal_distance
    ahead = (gx * to_nearest[0] + gy * to_nearest[1]) / span if span > 0.0 else 1.0
    d_left, d_right = (near, other) if side >= 0.0 else (other, near)
    edges = obstacle.tangent_points(px, py)
    if edges is None:
        beta = -math.pi / 2.0
    else:
        goal_angle = math.atan2(gy, gx)
        left, right = (_wrap(math.atan2(e[1] - py, e[0] - px) - goal_angle) for e in edges)
        beta = min(abs(left), abs(right))
        if left > 0.0 > right:
            beta = -beta
    return ObstacleMeasurement(True, clearance, d_left, d_right, beta, blocked, ahead)


def _ellipse_distance(a: float, b: float, u: float, v: float) -> tuple[float, Point]:
    """Signed distance from (u, v), u, v >= 0, to the ellipse x^2/a^2 + y^2/b^2 = 1.

    Eberly's method ("Distance from a point to an ellipse", 2013): the closest point is
    (a^2 u / (t + a^2), b^2 v / (t + b^2)) for the root t > -min(a, b)^2 of a convex,
    decreasing function, which Newton's method approaches monotonically from below.
    """
    if a < b:
        distance, (cy, cx) = _ellipse_distance(b, a, v, u)
        return distance, (cx, cy)
    inside = (u / a) ** 2 + (v / b) ** 2 < 1.0
    # A coordinate within rounding of an axis is taken as on it (an error of at most 1e-12 of
    # the axis), where the closed forms below hold and Newton's denominators could vanish.
    if v <= AXIS_SNAP * b:
        v = 0.0
    if u <= AXIS_SNAP * a:
        u = 0.0
    if v == 0.0:
        if u < (a * a - b * b) / a:
            x0 = a * a * u / (a * a - b * b)
            y0 = b * math.sqrt(max(0.0, 1.0 - (x0 / a) ** 2))
            return -math.hypot(x0 - u, y0), (x0, y0)
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
    distance = math.hypot(cx - u, cy - v)
    return (-distance if inside else distance), (cx, cy)


def _cross(first: Point, second: Point) -> float:
    return first[0] * second[1] - first[1] * second[0]


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi
