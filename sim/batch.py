"""The in-process simulation of many scenarios at once: one numpy array step advances them all.

Each array step is one tick of :func:`sim.simulation.simulate` for every scenario of the batch:
the wire (:mod:`protocol.messages`), the control law (:class:`controller.control_law.ControlLaw`)
and the plant model (:class:`plant_sim.model.PlantModel`), written with the same operations in
the same order as the scalar code. The wire rounds, so a value one ulp off could round the
other way and the runs part; hence only ufuncs that agree with :mod:`math` bit for bit
(``+ - * /``, ``sqrt``, ``sin``, ``cos``, ``%``, ``rint``) or, for ``atan2``, ``acos`` and
``exp``, to one ulp: numpy's own AVX-512 code for those, on a CPU that has it, is one ulp off
libm's in a few per cent of values, too rarely next to a rounding edge of the wire to part a
run (``tests/sim/test_batch.py`` checks both, and the measures of sampled runs to 1e-9).
``math.tanh`` itself where it is needed (numpy's differs in the last bit), and ties of
``min``/``max`` broken as Python does (:func:`_min`).
A branch becomes a mask: both sides are computed and one is kept, or the rare side is computed
on the few scenarios that take it.

Scenarios in one batch share the robot, the gains and the plant model; they differ in mode,
waypoints (padded), obstacle (a scenario without one gets a placeholder no tick measures) and
duration (a finished scenario leaves the arrays soon after it ends, and is no longer counted
in its measures meanwhile).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from controller.behaviours import AHEAD_SPEED_FRACTION, PLANNED_REST_SPEED, TURN_LEFT, TURN_RIGHT
from controller.control_law import (
    BEHIND,
    CLEAR_WAY,
    GOAL_KEPT,
    HEIGHT_LEAD,
    HEIGHT_LEAD_NEAR,
    HEIGHT_LEAD_NEAR_AHEAD,
    LOOP_AGAINST,
    LOOP_RADIUS,
    PASSED,
    RATE_CHANGE,
    ControlLaw,
    Windows,
)
from controller.coordination import AHEAD_FULL, AHEAD_NONE
from controller.fuzzy import OUTPUT_NAMES, OUTPUT_TERMS, FuzzyInference, RuleBase
from controller.obstacle import absent
from controller.planner import Trajectory
from protocol.geometry import AXIS_SNAP, EllipticCylinder
from protocol.kinematics import DAMPING_S2_REF, reach_radii
from protocol.messages import COMMAND, STATE
from protocol.scenario import Mode, Scenario
from sim.measures import Measures, MeasureStream

Array = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]
Index = npt.NDArray[np.intp]

BLOCK_TICKS = 64
"""Ticks of log kept before they are folded into the measures (memory: 15 columns of this)."""
REACH_MARGIN = 1e-6
"""m: DM measures within the sensing range plus the long semi-axis (plus this, for rounding)
of an obstacle's centre; farther, the clearance exceeds the range and DM finds nothing."""
COMPACT_SHARE = 0.03
"""Finished scenarios are dropped from the arrays once they are this share of them."""
NEWTON_ITERATIONS = 64
"""As in :func:`protocol.geometry._ellipse_distance`."""


# --- elementwise twins of the scalar code's building blocks ------------------------------


def _min(a: Array | float, b: Array | float) -> Array:
    """Python's ``min(a, b)``: ``a`` on a tie (which only shows with signed zeros)."""
    return np.minimum(b, a)


def _max(a: Array | float, b: Array | float) -> Array:
    """Python's ``max(a, b)``: ``a`` on a tie."""
    return np.maximum(b, a)


def _smoothstep(x: Array) -> Array:
    """:func:`controller.coordination.smoothstep` (clamped by two ufuncs, not two compares and
    two wheres: the same bits, NaN and signed zeros included, as the result shows)."""
    x = np.minimum(np.maximum(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


def _wrap(angle: Array) -> Array:
    """:func:`protocol.geometry.wrap_angle`."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def _tanh(x: Array) -> Array:
    """``math.tanh`` of each element (numpy's tanh differs from libm's in the last bit)."""
    return np.fromiter(map(math.tanh, x.tolist()), np.float64, len(x))


_Measurement = tuple[Mask, Array, Array, Array, Array, Array, Array, Array, Array]
"""DM's present, clearance, d_L, d_R, beta, ahead, toward, and the way from the TCP to the
nearest point of the section (x, y)."""


def _norm3(difference: Array) -> Array:
    """The length of (3, n) differences as the scalar code takes it (not ``math.dist``)."""
    x, y, z = difference
    return np.asarray(np.sqrt(x * x + y * y + z * z))


def _depth(room: Array, to_waypoint: Array) -> Array:
    """ControlLaw._depth: how deep a TCP ``to_waypoint`` from a waypoint is in its free room
    ``room``, 0..1."""
    half = room / 2.0
    inside = 1.0 - _smoothstep((to_waypoint - half) / half)
    return np.asarray(np.where(room <= 0.0, 0.0, inside))


def _clear_way(depth: Array, to_waypoint: Array, present: Mask, clearance: Array) -> Array:
    """``depth`` raised, where an obstacle is present, to how far it is beyond a waypoint
    ``to_waypoint`` from the TCP (ControlLaw._at_waypoint's clear way)."""
    clear_way = _smoothstep((clearance - to_waypoint) / CLEAR_WAY)
    return np.asarray(np.where(present, _max(depth, clear_way), depth))


def _capped_along(
    vx: Array, vy: Array, rows: Index, nx: Array, ny: Array, allowed: Array
) -> tuple[Array, Array]:
    """control_law.capped_along on the scenarios ``rows`` (new arrays; the others as given)."""
    near_x, near_y = vx[rows], vy[rows]
    excess = near_x * nx + near_y * ny - allowed
    cut = excess > 0.0
    vx, vy = vx.copy(), vy.copy()
    vx[rows] = np.where(cut, near_x - excess * nx, near_x)
    vy[rows] = np.where(cut, near_y - excess * ny, near_y)
    return vx, vy


def _keep(holder: object, rows: Index, by_row: Sequence[str], by_column: Sequence[str]) -> None:
    """Keep only the scenarios ``rows`` in the named arrays (scenarios along the first axis,
    or along the second for the (axis, scenario) arrays ``by_column``)."""
    for name in by_row:
        setattr(holder, name, getattr(holder, name)[rows])
    for name in by_column:
        setattr(holder, name, getattr(holder, name)[:, rows])


def _norm2(x: Array, y: Array) -> Array:
    """The length of (x, y) as the scalar code takes it: ``sqrt(x * x + y * y)``."""
    return np.sqrt(x * x + y * y)


class _Wire:
    """:func:`protocol.messages.on_the_wire_state` and ``on_the_wire_command`` on (3, n)."""

    def __init__(self, specs: Sequence[object]) -> None:
        self.scale = np.array([[spec.scale] for spec in specs])  # type: ignore[attr-defined]
        self.offset = np.array([[spec.offset] for spec in specs])  # type: ignore[attr-defined]

    def __call__(self, values: Array) -> Array:
        # The codec's range check cannot fire here: the plant keeps positions within the
        # joint limits and speeds within the speed limits, and the law its commands within
        # the speed limits, all of which check_robot_fits_wire keeps within the wire's ranges.
        return np.asarray(np.rint((values - self.offset) / self.scale) * self.scale + self.offset)


WIRE_POSITION = _Wire([codec.spec["Position"] for codec in STATE])
WIRE_VELOCITY = _Wire([codec.spec["Velocity"] for codec in STATE])
WIRE_COMMAND = _Wire([COMMAND.spec[name] for name in ("Theta1Rate", "Theta2Rate", "D3Rate")])


# --- the obstacle's section, per scenario ----------------------------------------------------


class _Sections:
    """One :class:`EllipticCylinder` per scenario, as arrays (see ``protocol/geometry.py``)."""

    def __init__(self, obstacles: Sequence[EllipticCylinder | None]) -> None:
        placeholder = EllipticCylinder(100.0, 100.0, 0.02, 0.01, 1.0)
        shapes = [obstacle or placeholder for obstacle in obstacles]
        self.x = np.array([o.x for o in shapes])
        self.y = np.array([o.y for o in shapes])
        self.cos = np.array([math.cos(o.yaw) for o in shapes])
        self.sin = np.array([math.sin(o.yaw) for o in shapes])
        self.a = np.array([o.semi_axes[0] for o in shapes])
        self.b = np.array([o.semi_axes[1] for o in shapes])
        self.inflation = np.array([o.inflation for o in shapes])
        self.top = np.array([-math.inf if o is None else o.height + o.inflation for o in obstacles])

    def take(self, index: Index) -> _Sections:
        """The sections of the scenarios ``index`` only."""
        part = object.__new__(_Sections)
        for name in ("x", "y", "cos", "sin", "a", "b", "inflation", "top"):
            setattr(part, name, getattr(self, name)[index])
        return part

    def to_local(self, px: Array, py: Array) -> tuple[Array, Array]:
        dx, dy = px - self.x, py - self.y
        return (self.cos * dx + self.sin * dy, -self.sin * dx + self.cos * dy)

    def to_world(self, lx: Array, ly: Array) -> tuple[Array, Array]:
        return (
            self.x + self.cos * lx - self.sin * ly,
            self.y + self.sin * lx + self.cos * ly,
        )

    def nearest_point(self, lx: Array, ly: Array) -> tuple[Array, Array, Array]:
        """Signed distance and boundary point (world) from local coordinates."""
        distance, cx, cy = _ellipse_distance(self.a, self.b, np.abs(lx), np.abs(ly))
        wx, wy = self.to_world(np.copysign(cx, lx), np.copysign(cy, ly))
        return distance, wx, wy

    def tangent_points(
        self, px: Array, py: Array, lx: Array, ly: Array
    ) -> tuple[Mask, Array, Array, Array, Array]:
        """Outside (else the scalar code's None), then the left and right edges (x, y)."""
        sx, sy = lx / self.a, ly / self.b
        norm = np.sqrt(sx * sx + sy * sy)
        outside = norm > 1.0
        centre_angle = np.arctan2(sy, sx)
        spread = np.arccos(1.0 / norm)
        first_x, first_y = self.to_world(
            self.a * np.cos(centre_angle + spread), self.b * np.sin(centre_angle + spread)
        )
        second_x, second_y = self.to_world(
            self.a * np.cos(centre_angle - spread), self.b * np.sin(centre_angle - spread)
        )
        to_centre_x, to_centre_y = self.x - px, self.y - py
        first_left = to_centre_x * (first_y - py) - to_centre_y * (first_x - px) > 0.0
        return (
            outside,
            np.where(first_left, first_x, second_x),
            np.where(first_left, first_y, second_y),
            np.where(first_left, second_x, first_x),
            np.where(first_left, second_y, first_y),
        )

    def line_crossings(
        self, plx: Array, ply: Array, qx: Array, qy: Array
    ) -> tuple[Mask, Array, Array]:
        """Whether the line p->q crosses (else None), and its entry and exit parameters."""
        qlx, qly = self.to_local(qx, qy)
        ox, oy = plx / self.a, ply / self.b
        dx, dy = (qlx - plx) / self.a, (qly - ply) / self.b
        quad_a = dx * dx + dy * dy
        half_b = ox * dx + oy * dy
        quad_c = ox * ox + oy * oy - 1.0
        discriminant = half_b * half_b - quad_a * quad_c
        crosses = (quad_a != 0.0) & ~(discriminant < 0.0)
        root = np.sqrt(discriminant)
        return crosses, (-half_b - root) / quad_a, (-half_b + root) / quad_a


def _measure(
    obstacle: _Sections,
    sensing_range: float,
    px: Array,
    py: Array,
    goal_x: Array,
    goal_y: Array,
    heading_cos: Array,
    heading_sin: Array,
) -> _Measurement:
    """controller.obstacle.measure below the obstacle's top: present (within the sensing
    range), clearance, d_L, d_R, beta, ahead, toward, and the way to the nearest point
    (meaningful where present)."""
    lx, ly = obstacle.to_local(px, py)
    clearance, nearest_x, nearest_y = obstacle.nearest_point(lx, ly)
    present = ~(clearance >= sensing_range)
    gx, gy = goal_x - px, goal_y - py
    goal_distance = _norm2(gx, gy)
    on_goal = goal_distance < 1e-9
    if on_goal.any():
        gx = np.where(on_goal, obstacle.x - px, gx)
        gy = np.where(on_goal, obstacle.y - py, gy)
        goal_distance = np.where(on_goal, _max(_norm2(gx, gy), 1e-9), goal_distance)
    near = _min(_max(clearance, 0.0), sensing_range)
    crosses, entry, exit_ = obstacle.line_crossings(lx, ly, px + gx, py + gy)
    other = _max(_min(_min(np.abs(entry), np.abs(exit_)) * goal_distance, sensing_range), near)
    other = np.where(crosses, other, sensing_range)
    to_nearest_x, to_nearest_y = nearest_x - px, nearest_y - py
    side = gx * to_nearest_y - gy * to_nearest_x
    nearest_distance = _norm2(to_nearest_x, to_nearest_y)
    span = nearest_distance * goal_distance
    spanned = span > 0.0
    ahead = np.where(
        spanned, (gx * to_nearest_x + gy * to_nearest_y) / np.where(spanned, span, 1.0), 1.0
    )
    apart = nearest_distance > 0.0
    toward = np.where(
        apart,
        (heading_cos * to_nearest_x + heading_sin * to_nearest_y)
        / np.where(apart, nearest_distance, 1.0),
        -1.0,
    )
    left_side = side >= 0.0
    d_left = np.where(left_side, near, other)
    d_right = np.where(left_side, other, near)
    outside, left_x, left_y, right_x, right_y = obstacle.tangent_points(px, py, lx, ly)
    goal_angle = np.arctan2(gy, gx)
    left = _wrap(np.arctan2(left_y - py, left_x - px) - goal_angle)
    right = _wrap(np.arctan2(right_y - py, right_x - px) - goal_angle)
    beta = _min(np.abs(left), np.abs(right))
    beta = np.where((left > 0.0) & (right < 0.0), -beta, beta)
    beta = np.where(outside, beta, -math.pi / 2.0)
    return present, clearance, d_left, d_right, beta, ahead, toward, to_nearest_x, to_nearest_y


def _ellipse_distance(a: Array, b: Array, u: Array, v: Array) -> tuple[Array, Array, Array]:
    """:func:`protocol.geometry._ellipse_distance` (``a >= b`` always: long >= short)."""
    su, sv = u / a, v / b
    inside = su * su + sv * sv < 1.0
    v = np.where(v <= AXIS_SNAP * b, 0.0, v)
    u = np.where(u <= AXIS_SNAP * a, 0.0, u)
    aa, bb = a * a, b * b
    gap = aa - bb
    # On the long axis: inside the evolute's reach, or at its end.
    x0 = aa * u / gap
    sx = x0 / a
    y0 = b * np.sqrt(_max(0.0, 1.0 - sx * sx))
    dx0 = x0 - u
    evolute = u < gap / a
    distance = np.where(evolute, -np.sqrt(dx0 * dx0 + y0 * y0), u - a)
    cx = np.where(evolute, x0, a)
    cy = np.where(evolute, y0, 0.0)
    # On the short axis.
    on_short = (u == 0.0) & (v != 0.0)
    distance = np.where(on_short, v - b, distance)
    cx = np.where(on_short, 0.0, cx)
    cy = np.where(on_short, b, cy)
    general = np.flatnonzero((u != 0.0) & (v != 0.0))
    if len(general):
        s = _newton(a[general], b[general], u[general], v[general], gap[general])
        ga, gb, gu, gv, ggap = a[general], b[general], u[general], v[general], gap[general]
        gx = ga * ga * gu / (s + ggap)
        gy = gb * gb * gv / s
        ddx, ddy = gx - gu, gy - gv
        found = np.sqrt(ddx * ddx + ddy * ddy)
        distance[general] = np.where(inside[general], -found, found)
        cx[general] = gx
        cy[general] = gy
    return distance, cx, cy


def _newton(a: Array, b: Array, u: Array, v: Array, gap: Array) -> Array:
    """Eberly's Newton iteration on s, each element stopping where the scalar loop breaks
    (those still going are gathered into shorter arrays once they are few)."""
    s = _max(b * v, a * u - gap)
    a_u, b_v = a * u, b * v
    result = s.copy()
    active = np.arange(len(s))
    going = np.ones(len(s), dtype=bool)
    for _ in range(NEWTON_ITERATIONS):
        shifted = s + gap
        ratio_u = a_u / shifted
        ratio_v = b_v / s
        square_u, square_v = ratio_u * ratio_u, ratio_v * ratio_v
        value = square_u + square_v - 1.0
        moving = going & ~(value <= 0.0)
        step = value / (-2.0 * (square_u / shifted + square_v / s))
        s = np.where(moving, s - step, s)
        going = moving & ~(np.abs(step) <= 1e-15 * s)
        count = np.count_nonzero(going)
        if count == 0:
            break
        if count <= len(going) // 2:
            result[active] = s
            active = active[going]
            a_u, b_v, gap, s = a_u[going], b_v[going], gap[going], s[going]
            going = np.ones(count, dtype=bool)
    result[active] = s
    return result


# --- the plan, per scenario -------------------------------------------------------------


class _Plans:
    """Each scenario's :class:`Trajectory`, with the segment it is in as state.

    ``stage`` i < n - 1 is segment i (from waypoint i to i + 1); n - 1 is the rest after the
    last waypoint, where the coefficients hold the last point with zero velocity. Times only
    move forward, so the segment changes when the time reaches the next boundary.
    """

    def __init__(
        self,
        trajectories: Sequence[Trajectory],
        rooms: Sequence[Sequence[float]],
        windows: Sequence[Sequence[Windows]],
        leaving: Sequence[Sequence[tuple[float, float]]],
    ) -> None:
        count = len(trajectories)
        self.size = np.array([len(tr.times) for tr in trajectories])
        width = int(self.size.max())
        self.times = np.full((count, width), math.inf)
        self.points = np.zeros((count, width, 3))
        # Per stage: k0..k3 of the three axes, the start of tau and the boundary time.
        self.stage_k = np.zeros((count, width, 4, 3))
        self.stage_start = np.zeros((count, width))
        self.stage_end = np.full((count, width), math.inf)
        # Per stage: the goal DM looks at, its slide to the following one, when, how long.
        self.goal = np.zeros((count, width, 2))
        self.goal_slide = np.zeros((count, width, 2))
        self.goal_end = np.zeros((count, width))
        self.goal_handover = np.ones((count, width))
        # Per stage: the waypoint p_j it heads for and p_j-1 (index, point, time, free room),
        # whether p_j and p_j-1 are inner waypoints, and the gate's approach and release.
        self.stage_index = np.zeros((count, width), dtype=np.intp)
        self.stage_point = np.zeros((count, width, 2, 3))
        self.stage_time = np.zeros((count, width, 2))
        self.stage_room = np.zeros((count, width, 2))
        self.stage_leaving = np.zeros((count, width, 2, 2))
        self.stage_inner = np.zeros((count, width, 2), dtype=bool)
        self.stage_gate = np.ones((count, width, 2))
        for row, trajectory in enumerate(trajectories):
            times, points = trajectory.times, trajectory.points
            n = len(times)
            self.times[row, :n] = times
            self.points[row, :n] = points
            for stage in range(n):
                if stage < n - 1:
                    for axis in range(3):
                        self.stage_k[row, stage, :, axis] = trajectory.segment(
                            stage, axis
                        ).coefficients
                    self.stage_start[row, stage] = times[stage]
                    last = stage == n - 2
                    boundary = times[stage + 1]
                    self.stage_end[row, stage] = (
                        math.nextafter(boundary, math.inf) if last else boundary
                    )
                else:
                    self.stage_k[row, stage, 0] = points[-1]
                    self.stage_start[row, stage] = times[-1]
                index = min(stage + 1, n - 1)
                self.stage_index[row, stage] = index
                self.stage_point[row, stage] = (points[index], points[index - 1])
                self.stage_time[row, stage] = (times[index], times[index - 1])
                self.stage_room[row, stage] = (rooms[row][index], rooms[row][index - 1])
                self.stage_leaving[row, stage] = (leaving[row][index], leaving[row][index - 1])
                self.stage_inner[row, stage] = (index < n - 1, index >= 2)
                window = windows[row][index - 1]
                self.stage_gate[row, stage] = (window.approach, window.release)
                goal = points[index]
                self.goal[row, stage] = goal[:2]
                if index + 1 < n:
                    following = points[index + 1]
                    end = times[index]
                    self.goal_slide[row, stage] = (
                        following[0] - goal[0],
                        following[1] - goal[1],
                    )
                    self.goal_end[row, stage] = end
                    self.goal_handover[row, stage] = window.handover
        self.stage = np.zeros(count, dtype=np.intp)
        shape = (3, count)
        self.k0, self.k1, self.k2, self.k3 = (np.zeros(shape) for _ in range(4))
        self.k2x2, self.k3x3, self.k3x6 = (np.zeros(shape) for _ in range(3))
        self.start, self.end = np.zeros(count), np.zeros(count)
        self.goal_now, self.slide_now = np.zeros((2, count)), np.zeros((2, count))
        self.goal_end_now, self.handover_now = np.zeros(count), np.zeros(count)
        self.index = np.zeros(count, dtype=np.intp)
        self.point, self.point_before = np.zeros((3, count)), np.zeros((3, count))
        self.time, self.time_before = np.zeros(count), np.zeros(count)
        self.room, self.room_before = np.zeros(count), np.zeros(count)
        self.leaving, self.leaving_before = np.zeros((2, count)), np.zeros((2, count))
        self.inner, self.inner_before = np.zeros(count, dtype=bool), np.zeros(count, dtype=bool)
        self.approach, self.release = np.zeros(count), np.zeros(count)
        self._load(np.arange(count))

    BY_ROW = (
        "size",
        "times",
        "points",
        "stage_k",
        "stage_start",
        "stage_end",
        "goal",
        "goal_slide",
        "goal_end",
        "goal_handover",
        "stage_index",
        "stage_point",
        "stage_time",
        "stage_room",
        "stage_leaving",
        "stage_inner",
        "stage_gate",
        "stage",
        "start",
        "end",
        "goal_end_now",
        "handover_now",
        "index",
        "time",
        "time_before",
        "room",
        "room_before",
        "inner",
        "inner_before",
        "approach",
        "release",
    )
    BY_COLUMN = (
        "k0",
        "k1",
        "k2",
        "k3",
        "k2x2",
        "k3x3",
        "k3x6",
        "goal_now",
        "slide_now",
        "point",
        "point_before",
        "leaving",
        "leaving_before",
    )

    def keep(self, rows: Index) -> None:
        """Only the scenarios ``rows`` from now on."""
        _keep(self, rows, self.BY_ROW, self.BY_COLUMN)

    def _load(self, rows: Index) -> None:
        """Take the coefficients and goal of the stage ``rows`` are now in."""
        stage = self.stage[rows]
        k = self.stage_k[rows, stage]  # (n, 4, 3)
        self.k0[:, rows], self.k1[:, rows] = k[:, 0].T, k[:, 1].T
        self.k2[:, rows], self.k3[:, rows] = k[:, 2].T, k[:, 3].T
        self.k2x2[:, rows] = 2.0 * k[:, 2].T
        self.k3x3[:, rows] = 3.0 * k[:, 3].T
        self.k3x6[:, rows] = 6.0 * k[:, 3].T
        self.start[rows] = self.stage_start[rows, stage]
        self.end[rows] = self.stage_end[rows, stage]
        self.goal_now[:, rows] = self.goal[rows, stage].T
        self.slide_now[:, rows] = self.goal_slide[rows, stage].T
        self.goal_end_now[rows] = self.goal_end[rows, stage]
        self.handover_now[rows] = self.goal_handover[rows, stage]
        self.index[rows] = self.stage_index[rows, stage]
        self.point[:, rows] = self.stage_point[rows, stage, 0].T
        self.point_before[:, rows] = self.stage_point[rows, stage, 1].T
        self.time[rows], self.time_before[rows] = self.stage_time[rows, stage].T
        self.room[rows], self.room_before[rows] = self.stage_room[rows, stage].T
        self.leaving[:, rows] = self.stage_leaving[rows, stage, 0].T
        self.leaving_before[:, rows] = self.stage_leaving[rows, stage, 1].T
        self.inner[rows], self.inner_before[rows] = self.stage_inner[rows, stage].T
        self.approach[rows], self.release[rows] = self.stage_gate[rows, stage].T

    def advance(self, t: Array) -> None:
        """Move each scenario to the stage its time ``t`` falls in."""
        while True:
            rows = np.flatnonzero(t >= self.end)
            if not len(rows):
                return
            self.stage[rows] += 1
            self._load(rows)

    def evaluate(self, t: Array) -> tuple[Array, Array, Array]:
        """Position (3, n), velocity (3, n), acceleration (3, n): Trajectory.evaluate."""
        tau = t - self.start
        position = ((self.k3 * tau + self.k2) * tau + self.k1) * tau + self.k0
        velocity = (self.k3x3 * tau + self.k2x2) * tau + self.k1
        acceleration = self.k3x6 * tau + self.k2x2
        return position, velocity, acceleration

    def goal_at(self, t: Array, behind: Array) -> tuple[Array, Array]:
        """ControlLaw._goal: p_j, sliding to p_j+1 over the segment's last GOAL_HANDOVER as
        far as the arm keeps to the way to p_j."""
        low, high = GOAL_KEPT
        share = _smoothstep((t - self.goal_end_now + self.handover_now) / self.handover_now) * (
            1.0 - _smoothstep((behind - low) / (high - low))
        )
        return (
            self.goal_now[0] + share * self.slide_now[0],
            self.goal_now[1] + share * self.slide_now[1],
        )


# --- fuzzy inference, vectorised -------------------------------------------------------


class _Fuzzy:
    """:class:`FuzzyInference` on arrays of inputs (same rule base, same arithmetic).

    The terms of both inputs are evaluated as one (terms, n) array and both outputs' centroids
    as one (2, n) array, which halves the number of numpy calls.
    """

    def __init__(self, rule_base: RuleBase) -> None:
        self.scalar = FuzzyInference(rule_base)
        distance, beta = rule_base.inputs["min_distance"], rule_base.inputs["beta"]
        terms = [(0, term) for term in distance.terms.values()]
        terms += [(1, term) for term in beta.terms.values()]
        self._reads = np.array([which for which, _ in terms])
        self._a, self._b, self._c, self._d = (
            np.array([[getattr(term, corner)] for _, term in terms]) for corner in "abcd"
        )
        self._ranges = (distance.universe, beta.universe)
        distance_row = {name: i for i, name in enumerate(distance.terms)}
        beta_row = {name: len(distance.terms) + i for i, name in enumerate(beta.terms)}
        self._rule_distance = np.array(
            [distance_row[rule.min_distance] for rule in rule_base.rules]
        )
        self._rule_beta = np.array([beta_row[rule.beta] for rule in rule_base.rules])
        self._firing = [
            [
                [i for i, rule in enumerate(rule_base.rules) if getattr(rule, output) == term]
                for output in OUTPUT_NAMES
            ]
            for term in OUTPUT_TERMS
        ]
        self._peaks = [
            np.array([[rule_base.outputs[output].peaks[k]] for output in OUTPUT_NAMES])
            for k in range(3)
        ]

    def weights(self, min_distance: Array, beta: Array) -> tuple[Array, Array]:
        inputs = []
        for x, (low, high) in zip((min_distance, beta), self._ranges, strict=True):
            inputs.append(np.where(x < low, low, np.where(x > high, high, x)))
        x = np.stack(inputs)[self._reads]
        a, b, c, d = self._a, self._b, self._c, self._d
        with np.errstate(divide="ignore", invalid="ignore"):  # a shoulder's side, not taken
            rising, falling = (x - a) / (b - a), (d - x) / (d - c)
        membership = np.where(x < b, rising, np.where(x <= c, 1.0, falling))
        membership = np.where((x < a) | (x > d), 0.0, membership)
        strength = _min(membership[self._rule_distance], membership[self._rule_beta])
        fired = [
            np.stack([strength[rules].max(axis=0, initial=0.0) for rules in per_output])
            for per_output in self._firing
        ]
        k_t, k_c = _centroid(self._peaks, fired)
        return k_t, k_c


def _centroid(peaks: Sequence[Array], fired: Sequence[Array]) -> Array:
    """:func:`controller.fuzzy.centroid_of_partition`, the same sums in the same order."""
    small, medium, big = peaks
    low_width = medium - small
    high_width = big - medium
    whole = [_rising_whole(w) for w in fired]
    piece_area, piece_moment = whole[0]
    area = 0.0 + low_width * piece_area
    moment = 0.0 + low_width * ((small - low_width) * piece_area + low_width * piece_moment)
    piece_area, piece_moment = whole[2]
    area = area + high_width * piece_area
    moment = moment + high_width * (big * piece_area + high_width * (piece_area - piece_moment))
    for start, width, falling, rising in ((small, low_width, 0, 1), (medium, high_width, 1, 2)):
        piece_area, piece_moment = _falling_then_rising(
            fired[falling], fired[rising], whole[falling], whole[rising]
        )
        area = area + width * piece_area
        moment = moment + width * (start * piece_area + width * piece_moment)
    return np.asarray(moment / area)


def _rising(level: Array, upto: Array | float) -> tuple[Array, Array]:
    """:func:`controller.fuzzy._rising`."""
    full = upto <= level
    return (
        np.where(full, upto * upto * 0.5, level * (upto - level * 0.5)),
        np.where(
            full,
            upto * upto * upto / 3.0,
            level * level * level / 3.0 + level * (upto * upto - level * level) * 0.5,
        ),
    )


def _rising_whole(level: Array) -> tuple[Array, Array]:
    """``_rising(level, 1.0)``: with ``level <= 1`` (a membership) both of its branches give
    the same bits at ``level == 1``, so the general one serves throughout."""
    return (
        level * (1.0 - level * 0.5),
        level * level * level / 3.0 + level * (1.0 * 1.0 - level * level) * 0.5,
    )


def _falling_then_rising(
    falling: Array,
    rising: Array,
    falling_whole: tuple[Array, Array],
    rising_whole: tuple[Array, Array],
) -> tuple[Array, Array]:
    """:func:`controller.fuzzy._falling_then_rising`, given ``_rising(x, 1.0)`` of both."""
    crossing = np.where(
        (falling <= rising) & (falling <= 0.5),
        falling,
        np.where((rising < falling) & (rising <= 0.5), 1.0 - rising, 0.5),
    )
    full_area, full_moment = falling_whole
    part_area, part_moment = _rising(falling, 1.0 - crossing)
    falling_area = full_area - part_area
    falling_moment = falling_area - (full_moment - part_moment)
    full_area, full_moment = rising_whole
    part_area, part_moment = _rising(rising, crossing)
    return (
        falling_area + full_area - part_area,
        falling_moment + full_moment - part_moment,
    )


# --- the batch ---------------------------------------------------------------------------


class _Batch:
    """The state of every scenario of a batch, advanced one tick per :meth:`step`."""

    def __init__(
        self, scenarios: Sequence[Scenario], modes: Sequence[Mode], rule_base: RuleBase | None
    ) -> None:
        first = scenarios[0]
        for scenario in scenarios:
            if (scenario.robot, scenario.controller, scenario.plant) != (
                first.robot,
                first.controller,
                first.plant,
            ):
                raise ValueError(
                    f"scenario {scenario.name!r}: a batch shares the robot, gains and plant"
                )
        self.fuzzy_rows = np.array([mode is Mode.FUZZY for mode in modes])
        self.robot, self.config, self.plant = first.robot, first.controller, first.plant
        self.period = self.config.period
        count = len(scenarios)
        self.count = count
        self.ticks = np.array([round(s.duration / self.period) + 1 for s in scenarios])
        self.start = np.array([s.waypoints[0].t for s in scenarios])
        # Each scenario's own law gives its plan, its waypoints' free room (ControlLaw's
        # _free_room) and its segments' windows, taken from there rather than computed a
        # second way.
        laws = [ControlLaw.for_scenario(s) for s in scenarios]
        self.plans = _Plans(
            [law.trajectory for law in laws],
            [law._room for law in laws],
            [law.windows for law in laws],
            [law.leaving for law in laws],
        )
        obstacles = [s.obstacle for s in scenarios]
        self.obstacle = _Sections(obstacles)
        self.aim = _Sections(
            [o.grown(self.config.ao_pass_margin) if o is not None else None for o in obstacles]
        )
        self.reach_squared = (self.obstacle.a + self.config.sensing_range + REACH_MARGIN) ** 2
        self.fuzzy = _Fuzzy(rule_base or RuleBase.load())
        nothing = absent(self.config.sensing_range)
        self.k_t_without_obstacle = self.fuzzy.scalar.weights(nothing.min_distance, nothing.beta)[0]
        self.position = np.array([s.initial_joints() for s in scenarios]).T.copy()
        self.velocity = np.zeros((3, count))
        points = self.plans.points
        self.heading = np.array(
            [math.atan2(p[1][1] - p[0][1], p[1][0] - p[0][0]) for p in points[:, :2].tolist()]
        )
        self.side = np.zeros(count)
        self.previous = np.zeros((3, count))
        self.progress = self.start.copy()
        self.rate = np.ones(count)
        self.last_t = self.start.copy()
        self.reached = np.zeros(count, dtype=np.intp)
        self.rate_step = self.period / RATE_CHANGE
        robot = self.robot
        self.full_reach = reach_radii(robot)[1]
        self.speed_limits = np.array([[limit] for limit in robot.speed_limits])
        self.step_limits = np.array([[limit * self.period] for limit in robot.accel_limits])
        self.joint_low = np.array([[limit] for limit in robot.joint_min])
        self.joint_high = np.array([[limit] for limit in robot.joint_max])
        substep = self.period / self.plant.substeps
        self.substep = substep
        self.blend = 1.0 - math.exp(-substep / self.plant.time_constant)
        self.max_change = np.array([[limit * substep] for limit in robot.accel_limits])

    def keep(self, rows: Index) -> None:
        """Only the scenarios ``rows`` from now on (the others have finished)."""
        by_row = ("ticks", "start", "heading", "side", "progress", "rate", "last_t", "reached")
        _keep(
            self,
            rows,
            (*by_row, "fuzzy_rows", "reach_squared"),
            ("position", "velocity", "previous"),
        )
        self.obstacle, self.aim = self.obstacle.take(rows), self.aim.take(rows)
        self.plans.keep(rows)
        self.count = len(rows)

    def step(self, tick: int) -> dict[str, Array]:
        """One tick for every scenario; the log columns the measures need."""
        config, robot = self.config, self.robot
        t = self.start + tick * self.period
        position = WIRE_POSITION(self.position)
        velocity = WIRE_VELOCITY(self.velocity)
        theta1, theta2, d3 = position

        # forward()
        theta12 = theta1 + theta2
        cos1, sin1, cos12, sin12 = np.cos(theta1), np.sin(theta1), np.cos(theta12), np.sin(theta12)
        px = robot.a1 * cos1 + robot.a2 * cos12
        py = robot.a1 * sin1 + robot.a2 * sin12
        pz = robot.d0 - d3

        plans = self.plans
        progress = self.progress = self.progress + self.rate * _max(t - self.last_t, 0.0)
        self.last_t = t
        plans.advance(progress)
        reference, plan_velocity, plan_acceleration = plans.evaluate(progress)
        tcp = np.stack([px, py, pz])
        # Plane distances several parts of the law use (as ControlLaw.step).
        to_next = _norm2(px - plans.point[0], py - plans.point[1])
        to_before = _norm2(px - plans.point_before[0], py - plans.point_before[1])
        reference_to_next = _norm2(reference[0] - plans.point[0], reference[1] - plans.point[1])
        behind, away_passed = self._behind(tcp, reference, to_next, to_before, reference_to_next)
        self.rate = _min(
            _max(self._wanted_rate(progress, behind, away_passed), self.rate - self.rate_step),
            self.rate + self.rate_step,
        )
        reference_velocity = self.rate * plan_velocity
        squared = self.rate * self.rate
        reference_acceleration = squared * plan_acceleration
        goal_x, goal_y = plans.goal_at(progress, behind)
        heading_cos, heading_sin = np.cos(self.heading), np.sin(self.heading)
        measurement = self._measure(px, py, pz, goal_x, goal_y, heading_cos, heading_sin)
        clearance, d_left, d_right = measurement[1], measurement[2], measurement[3]
        min_distance = _min(d_left, d_right)

        tracking_v, tracking_omega = self._plan_tracking(
            px, py, reference, reference_velocity, reference_acceleration
        )
        avoiding_v, avoiding_omega = self._avoid(measurement, min_distance, px, py)
        depth_next = _depth(plans.room, to_next)
        depth_before = _depth(plans.room_before, to_before)
        at_waypoint = self._at_waypoint(
            progress, depth_next, depth_before, clearance, to_next, to_before
        )
        k_t, k_c = self._weights(measurement, min_distance, at_waypoint)
        total = k_t + k_c
        blended_v = (k_t * tracking_v + k_c * avoiding_v) / total
        blended_omega = (k_t * tracking_omega + k_c * avoiding_omega) / total

        # ControlLaw._waited_for: p_j-1 until the TCP has passed it, then p_j; the TCP is
        # steered to it by (1 - rate) times how deep the TCP is in its free room.
        waited_is_next = (
            np.maximum(plans.index - 1, np.minimum(self.reached + 1, plans.index)) == plans.index
        )
        waited = np.where(waited_is_next, plans.point, plans.point_before)
        depth = np.where(waited_is_next, depth_next, depth_before)
        pull = (1.0 - self.rate) * depth
        vx, vy = self._approach_limited(
            blended_v * heading_cos, blended_v * heading_sin, measurement
        )
        leaving = np.where(waited_is_next, plans.leaving, plans.leaving_before)
        away = np.where(waited_is_next, to_next, to_before)
        approach_x, approach_y, looping = self._final_approach(waited, leaving, away, px, py)
        vx = vx + pull * (approach_x - vx)
        vy = vy + pull * (approach_y - vy)
        vx, vy = self._reach_limited(vx, vy, px, py)
        lead = self._height_lead(waited_is_next, to_next, reference_to_next)
        vz = (1.0 - lead) * reference_velocity[2] + config.height_gain * (
            reference[2] + _max(pull, lead) * (waited[2] - reference[2]) - pz
        )
        rate1, rate2 = self._joint_rates(theta2, sin1, cos1, sin12, cos12, vx, vy)
        command = self._limit(np.stack([rate1, rate2, -vz]))

        # ControlLaw.step: on a loop the heading turns with the TCP's way round.
        omega = blended_omega
        rows = np.flatnonzero(looping > 0.0)
        if len(rows):
            turn = _wrap(np.arctan2(approach_y[rows], approach_x[rows]) - self.heading[rows])
            steer = pull[rows] * looping[rows]
            omega = omega.copy()
            omega[rows] += steer * (config.heading_gain * turn - omega[rows])
        self.heading = _wrap(self.heading + omega * self.period)
        self.previous = command
        self._advance_plant(WIRE_COMMAND(command))
        return {
            "clock": t,
            "theta1": theta1,
            "theta2": theta2,
            "theta1_rate": velocity[0],
            "theta2_rate": velocity[1],
            "d3_rate": velocity[2],
            "command_theta1": command[0],
            "command_theta2": command[1],
            "x": px,
            "y": py,
            "z": pz,
            "reference_speed": _norm2(plan_velocity[0], plan_velocity[1]),
            "clearance": clearance,
            "progress": progress,
            "k_c": k_c,
        }

    def _behind(
        self,
        tcp: Array,
        reference: Array,
        to_next: Array,
        to_before: Array,
        reference_to_next: Array,
    ) -> tuple[Array, Array]:
        """ControlLaw._mark_reached (AO forgets its side where a waypoint is passed), then
        _behind of p_j and _away of p_j-1."""
        plans = self.plans
        index = plans.index
        for candidate, point in ((index - 1, plans.point_before), (index, plans.point)):
            passed = (candidate > self.reached) & (_norm3(tcp - point) <= PASSED)
            self.reached = np.where(passed, candidate, self.reached)
            self.side = np.where(passed, 0.0, self.side)
        behind = 0.5 * (
            to_next + _norm2(tcp[0] - reference[0], tcp[1] - reference[1]) - reference_to_next
        )
        return (
            np.where(index <= self.reached, -math.inf, behind),
            np.where(index - 1 <= self.reached, -math.inf, to_before),
        )

    def _wanted_rate(self, progress: Array, behind: Array, away_passed: Array) -> Array:
        """ControlLaw._wanted_rate: the plan slows near an inner waypoint the arm is off."""
        plans = self.plans
        low, high = BEHIND
        approach = plans.approach
        gate = _smoothstep((progress - plans.time + approach) / approach)
        hold = np.where(plans.inner, gate * _smoothstep((behind - low) / (high - low)), 0.0)
        hold = np.where(
            plans.inner_before,
            _max(hold, _smoothstep((away_passed - low) / (high - low))),
            hold,
        )
        return 1.0 - hold

    def _at_waypoint(
        self,
        progress: Array,
        depth_next: Array,
        depth_before: Array,
        clearance: Array,
        to_next: Array,
        to_before: Array,
    ) -> Array:
        """ControlLaw._at_waypoint, from the TCP's depth in the free rooms of p_j and p_j-1,
        and how much farther the obstacle is than each (``to_next``, ``to_before``)."""
        plans = self.plans
        share = _smoothstep((progress - plans.time_before) / plans.release)
        present = clearance < math.inf
        if present.any():
            depth_next = _clear_way(depth_next, to_next, present, clearance)
            depth_before = _clear_way(depth_before, to_before, present, clearance)
        return _max(share * depth_next, (1.0 - share) * depth_before)

    def _measure(
        self,
        px: Array,
        py: Array,
        pz: Array,
        goal_x: Array,
        goal_y: Array,
        heading_cos: Array,
        heading_sin: Array,
    ) -> _Measurement:
        """Module DM (controller.obstacle.measure): present, clearance, d_L, d_R, beta, ahead,
        toward.

        Measured only where the TCP is below the obstacle's top and within the sensing range
        of a circle round its section: elsewhere the scalar code finds it absent too.
        """
        obstacle = self.obstacle
        sensing_range = self.config.sensing_range
        dx, dy = px - obstacle.x, py - obstacle.y
        rows = np.flatnonzero(~(pz >= obstacle.top) & (dx * dx + dy * dy < self.reach_squared))
        present = np.zeros(self.count, dtype=bool)
        clearance = np.full(self.count, math.inf)
        d_left, d_right = np.full(self.count, sensing_range), np.full(self.count, sensing_range)
        beta, ahead = np.full(self.count, math.pi), np.full(self.count, -1.0)
        toward = np.full(self.count, -1.0)
        to_nearest_x, to_nearest_y = np.zeros(self.count), np.zeros(self.count)
        if len(rows):
            found = _measure(
                obstacle.take(rows),
                sensing_range,
                px[rows],
                py[rows],
                goal_x[rows],
                goal_y[rows],
                heading_cos[rows],
                heading_sin[rows],
            )
            present[rows] = found[0]
            for array, values, nothing in zip(
                (clearance, d_left, d_right, beta, ahead, toward, to_nearest_x, to_nearest_y),
                found[1:],
                (math.inf, sensing_range, sensing_range, math.pi, -1.0, -1.0, 0.0, 0.0),
                strict=True,
            ):
                array[rows] = np.where(found[0], values, nothing)
        return (
            present,
            clearance,
            d_left,
            d_right,
            beta,
            ahead,
            toward,
            to_nearest_x,
            to_nearest_y,
        )

    def _plan_tracking(
        self,
        px: Array,
        py: Array,
        reference: Array,
        reference_velocity: Array,
        reference_acceleration: Array,
    ) -> tuple[Array, Array]:
        """PT (controller.behaviours.plan_tracking): v and omega."""
        config = self.config
        error_x, error_y = reference[0] - px, reference[1] - py
        vx, vy = reference_velocity[0], reference_velocity[1]
        planned_speed = _norm2(vx, vy)
        at_rest = planned_speed < PLANNED_REST_SPEED
        divisor = np.where(at_rest, 1.0, planned_speed)
        along_x, along_y = vx / divisor, vy / divisor
        lag = error_x * along_x + error_y * along_y
        offset = along_x * error_y - along_y * error_x
        along = _max(
            planned_speed + config.position_gain * lag, AHEAD_SPEED_FRACTION * planned_speed
        )
        across = config.position_gain * offset
        speed = _min(_norm2(along, across), config.speed_max)
        target = np.arctan2(vy, vx) + np.arctan2(across, along)
        ax, ay = reference_acceleration[0], reference_acceleration[1]
        feedforward = (vx * ay - vy * ax) / (divisor * divisor)
        error = _wrap(target - self.heading)
        v = speed * _max(np.cos(error), 0.0)
        omega = feedforward + config.heading_gain * error
        if at_rest.any():
            distance = _norm2(error_x, error_y)
            error = _wrap(np.arctan2(error_y, error_x) - self.heading)
            speed = _min(config.position_gain * distance, config.speed_max)
            still = distance < 1e-9
            v = np.where(at_rest, np.where(still, 0.0, speed * _max(np.cos(error), 0.0)), v)
            omega = np.where(at_rest, np.where(still, 0.0, config.heading_gain * error), omega)
        return v, omega

    def _avoid(
        self,
        measurement: _Measurement,
        min_distance: Array,
        px: Array,
        py: Array,
    ) -> tuple[Array, Array]:
        """AO with its TL/TR choice (ControlLaw._avoid, behaviours.avoid_obstacle)."""
        present, clearance, d_left, d_right, _, ahead, toward, _, _ = measurement
        engaged = present & ~((_max(ahead, toward) <= AHEAD_NONE) & (clearance > 0.0))
        chosen = np.where(d_left >= d_right, float(TURN_LEFT), float(TURN_RIGHT))
        self.side = np.where(engaged, np.where(self.side == 0.0, chosen, self.side), 0.0)
        v, omega = np.zeros(self.count), np.zeros(self.count)
        rows = np.flatnonzero(engaged)
        if not len(rows):
            return v, omega
        config = self.config
        aim = self.aim.take(rows)
        side, heading = self.side[rows], self.heading[rows]
        x, y = px[rows], py[rows]
        lx, ly = aim.to_local(x, y)
        outside, left_x, left_y, right_x, right_y = aim.tangent_points(x, y, lx, ly)
        left_hand = side == TURN_LEFT
        edge_x = np.where(left_hand, left_x, right_x)
        edge_y = np.where(left_hand, left_y, right_y)
        edge_angle = np.arctan2(edge_y - y, edge_x - x)
        inside = np.flatnonzero(~outside)
        if len(inside):
            part = aim.take(inside)
            depth, nearest_x, nearest_y = part.nearest_point(lx[inside], ly[inside])
            ix, iy, iside = x[inside], y[inside], side[inside]
            normal_x, normal_y = nearest_x - ix, nearest_y - iy
            flip = depth >= 0.0
            normal_x = np.where(flip, -normal_x, normal_x)
            normal_y = np.where(flip, -normal_y, normal_y)
            zero = (normal_x == 0.0) & (normal_y == 0.0)
            normal_x = np.where(zero, ix - part.x, normal_x)
            normal_y = np.where(zero, iy - part.y, normal_y)
            along_boundary = np.arctan2(normal_y, normal_x) - iside * math.pi / 2.0
            tilt = _min(1.0, np.abs(depth) / _max(part.inflation, 1e-3)) * math.pi / 4.0
            edge_angle[inside] = along_boundary + iside * tilt
        beta = side * _wrap(edge_angle - heading)
        distance = _max(min_distance[rows], 1e-3)
        along = distance * np.cos(beta)
        v[rows] = config.ao_speed_min + (config.ao_speed_max - config.ao_speed_min) * _tanh(
            _max(along, 0.0) / config.ao_speed_distance
        )
        omega[rows] = side * (
            config.ao_turn_max * _tanh(np.sin(beta) / distance / config.ao_turn_scale)
        )
        return v, omega

    def _weights(
        self, measurement: _Measurement, min_distance: Array, at_waypoint: Array
    ) -> tuple[Array, Array]:
        """k_T and k_C of each scenario's coordinator (controller.coordination)."""
        present, clearance, _, _, beta, ahead, toward, _, _ = measurement
        fuzzy_rows = self.fuzzy_rows
        k_t = np.full(self.count, self.k_t_without_obstacle)
        k_c = np.zeros(self.count)
        if not fuzzy_rows.all():
            switched = (
                present
                & (ahead > 0.0)
                & (clearance < self.config.switch_distance)
                & (at_waypoint == 0.0)
            )
            k_t = np.where(fuzzy_rows, k_t, np.where(switched, 0.0, 1.0))
            k_c = np.where(fuzzy_rows, k_c, np.where(switched, 1.0, 0.0))
        rows = np.flatnonzero(present & fuzzy_rows)
        if len(rows):
            sensing_range = self.config.sensing_range
            distance = min_distance[rows]
            fuzzy_t, fuzzy_c = self.fuzzy.weights(distance, beta[rows])
            half = sensing_range / 2.0
            relevance = _smoothstep((sensing_range - distance) / half)
            facing = _max(ahead[rows], toward[rows])
            fading = _smoothstep((facing - AHEAD_NONE) / (AHEAD_FULL - AHEAD_NONE))
            relevance = np.where(clearance[rows] > 0.0, relevance * fading, relevance)
            k_t[rows] = fuzzy_t
            k_c[rows] = fuzzy_c * relevance * (1.0 - at_waypoint[rows])
        return k_t, k_c

    def _final_approach(
        self, waited: Array, leaving: Array, away: Array, px: Array, py: Array
    ) -> tuple[Array, Array, Array]:
        """ControlLaw._final_approach: straight at the waited-for waypoint (``away`` from the
        TCP in the plane), handing over to the loop round LOOP_RADIUS's circle where that way
        points against the plan."""
        gain = self.config.position_gain
        to_x, to_y = waited[0] - px, waited[1] - py
        straight_x, straight_y = gain * to_x, gain * to_y
        out_x, out_y = leaving
        against = -(to_x * out_x + to_y * out_y) / np.where(away == 0.0, 1.0, away)
        share = np.where(away == 0.0, 0.0, _smoothstep(against / LOOP_AGAINST))
        rows = np.flatnonzero(share != 0.0)
        if not len(rows):
            return straight_x, straight_y, np.zeros_like(share)
        tx, ty, ox, oy = to_x[rows], to_y[rows], out_x[rows], out_y[rows]
        side = np.where(ox * ty - oy * tx <= 0.0, 1.0, -1.0)
        radial_x = px[rows] - (waited[0, rows] - side * LOOP_RADIUS * oy)
        radial_y = py[rows] - (waited[1, rows] + side * LOOP_RADIUS * ox)
        radius = _norm2(radial_x, radial_y)
        valid = radius != 0.0
        divisor = np.where(valid, radius, 1.0)
        off = (radius - LOOP_RADIUS) / LOOP_RADIUS
        way_x = (-side * radial_y - off * radial_x) / divisor
        way_y = (side * radial_x - off * radial_y) / divisor
        way_length = _norm2(way_x, way_y)
        speed = gain * away[rows] / np.where(valid, way_length, 1.0)
        share_rows = np.where(valid, share[rows], 0.0)
        sx, sy = straight_x[rows], straight_y[rows]
        approach_x, approach_y = straight_x.copy(), straight_y.copy()
        approach_x[rows] = sx + share_rows * (speed * way_x - sx)
        approach_y[rows] = sy + share_rows * (speed * way_y - sy)
        looping = np.zeros_like(share)
        looping[rows] = share_rows
        return approach_x, approach_y, looping

    @staticmethod
    def _height_lead(ahead: Mask, to_next: Array, reference_to_next: Array) -> Array:
        """ControlLaw._height_lead: the share of the way from the reference to p_j the TCP has
        come, once it is HEIGHT_LEAD nearer p_j (or HEIGHT_LEAD_NEAR_AHEAD, near p_j)."""
        ahead_by = reference_to_next - to_next
        low, high = HEIGHT_LEAD
        far, near = HEIGHT_LEAD_NEAR
        ahead_low, ahead_high = HEIGHT_LEAD_NEAR_AHEAD
        leading = ahead & (ahead_by > 0.0)
        if not leading.any():
            return np.zeros_like(to_next)
        share = np.maximum(
            _smoothstep((ahead_by - low) / (high - low)),
            _smoothstep((far - to_next) / (far - near))
            * _smoothstep((ahead_by - ahead_low) / (ahead_high - ahead_low)),
        )
        divisor = np.where(leading, reference_to_next, 1.0)
        return np.where(leading, ahead_by / divisor * share, 0.0)

    def _approach_limited(
        self, vx: Array, vy: Array, measurement: _Measurement
    ) -> tuple[Array, Array]:
        """ControlLaw._approach_limited: towards the obstacle's margin no faster than
        approach_rate times the clearance."""
        present, clearance, *_, to_x, to_y = measurement
        gap = _norm2(to_x, to_y)
        rows = np.flatnonzero(present & (gap > 0.0))
        if not len(rows):
            return vx, vy
        inside = clearance[rows] < 0.0
        normal_x = np.where(inside, -to_x[rows], to_x[rows]) / gap[rows]
        normal_y = np.where(inside, -to_y[rows], to_y[rows]) / gap[rows]
        allowed = self.config.approach_rate * _max(clearance[rows], 0.0)
        return _capped_along(vx, vy, rows, normal_x, normal_y, allowed)

    def _reach_limited(self, vx: Array, vy: Array, px: Array, py: Array) -> tuple[Array, Array]:
        """ControlLaw._reach_limited: outwards no faster than reach_rate times the distance
        from full reach."""
        radius = _norm2(px, py)
        rows = np.flatnonzero(radius > 0.0)
        radius = radius[rows]
        allowed = self.config.reach_rate * _max(self.full_reach - radius, 0.0)
        return _capped_along(vx, vy, rows, px[rows] / radius, py[rows] / radius, allowed)

    def _joint_rates(
        self,
        theta2: Array,
        sin1: Array,
        cos1: Array,
        sin12: Array,
        cos12: Array,
        vx: Array,
        vy: Array,
    ) -> tuple[Array, Array]:
        """protocol.kinematics.joint_rates_for, reusing forward()'s sines and cosines."""
        robot, damping = self.robot, self.config.damping
        a2s12 = robot.a2 * sin12
        a2c12 = robot.a2 * cos12
        j11 = -robot.a1 * sin1 - a2s12
        j12 = -a2s12
        j21 = robot.a1 * cos1 + a2c12
        j22 = a2c12
        s2 = np.sin(theta2)
        ratio = s2 / DAMPING_S2_REF
        lam2 = np.where(np.abs(ratio) < 1.0, damping * damping * (1.0 - ratio * ratio), 0.0)
        det_j = robot.a1 * robot.a2 * s2
        denominator = det_j * det_j + lam2 * (j11 * j11 + j12 * j12 + j21 * j21 + j22 * j22 + lam2)
        return (
            (det_j * (j22 * vx - j12 * vy) + lam2 * (j11 * vx + j21 * vy)) / denominator,
            (det_j * (j11 * vy - j21 * vx) + lam2 * (j12 * vx + j22 * vy)) / denominator,
        )

    def _limit(self, wanted: Array) -> Array:
        """ControlLaw._limit: one speed scale, then one acceleration scale, on all joints."""
        previous = self.previous
        scale = np.ones(self.count)
        size = np.abs(wanted)
        for joint in range(3):
            limit = self.speed_limits[joint, 0]
            scale = np.where(size[joint] * scale > limit, limit / size[joint], scale)
        scaled = wanted * scale
        step_scale = np.ones(self.count)
        change = np.abs(scaled - previous)
        for joint in range(3):
            limit = self.step_limits[joint, 0]
            step_scale = np.where(
                change[joint] * step_scale > limit, limit / change[joint], step_scale
            )
        return np.asarray(previous + (scaled - previous) * step_scale)

    def _advance_plant(self, command: Array) -> None:
        """PlantModel.advance over one period, all joints of all scenarios at once."""
        target = _min(_max(command, -self.speed_limits), self.speed_limits)
        position, velocity = self.position, self.velocity
        low, high = self.joint_low, self.joint_high
        for _ in range(self.plant.substeps):
            change = (target - velocity) * self.blend
            change = _min(_max(change, -self.max_change), self.max_change)
            new_velocity = velocity + change
            new_position = position + 0.5 * (velocity + new_velocity) * self.substep
            stopped = (new_position < low) | (new_position > high)
            if stopped.any():
                new_position = np.where(stopped, _min(_max(new_position, low), high), new_position)
                new_velocity = np.where(stopped, 0.0, new_velocity)
            position, velocity = new_position, new_velocity
        self.position, self.velocity = position, velocity


@dataclass(frozen=True, slots=True)
class BatchRun:
    """One scenario's run in a batch: its measures, and how far AO ever took over."""

    measures: Measures
    peak_k_c: float
    """The largest k_C of the run (1 when the conventional switch flipped to AO)."""


def trace_batch(scenarios: Sequence[Scenario], modes: Sequence[Mode]) -> list[dict[str, Array]]:
    """Every tick's log columns of each run (``modes``: one per scenario), for comparing the
    batch with the scalar law tick by tick; the runs are kept in the arrays to the end."""
    with np.errstate(all="ignore"):
        batch = _Batch(scenarios, modes, None)
        rows = [batch.step(tick) for tick in range(int(batch.ticks.max()))]
    return [
        {name: np.array([row[name][index] for row in rows[:ticks]]) for name in rows[0]}
        for index, ticks in enumerate(batch.ticks.tolist())
    ]


def simulate_batch(
    scenarios: Sequence[Scenario],
    mode: Mode | Sequence[Mode] | None = None,
    rule_base: RuleBase | None = None,
    on_block: Callable[[int], None] | None = None,
) -> list[BatchRun]:
    """Each scenario's run as :func:`sim.simulation.simulate` gives it, all at once.

    ``mode``: one for the whole batch, or one per scenario, else the scenarios' own (a batch
    may mix them: running both modes of the same scenarios in one batch pays numpy's
    per-tick overhead once for both); ``rule_base`` for the fuzzy coordinator (else Table
    2's); ``on_block(n)`` is told of every n scenario-ticks done (for a progress bar). A
    run's results do not depend on the other scenarios of its batch.
    """
    if not scenarios:
        return []
    if mode is None:
        modes = [scenario.mode for scenario in scenarios]
    elif isinstance(mode, Mode):
        modes = [mode] * len(scenarios)
    else:
        modes = list(mode)
        if len(modes) != len(scenarios):
            raise ValueError(f"{len(modes)} modes for {len(scenarios)} scenarios")
    with np.errstate(all="ignore"):
        batch = _Batch(scenarios, modes, rule_base)
        stream = MeasureStream(scenarios)
        peak_k_c = np.zeros(batch.count)
        runs: list[BatchRun | None] = [None] * len(scenarios)
        original = np.arange(len(scenarios))
        names = (*MeasureStream.COLUMNS, "k_c")
        block_start = 0
        buffers: dict[str, Array] = {}
        while batch.count:
            length = min(BLOCK_TICKS, int(batch.ticks.max()) - block_start)
            if not buffers or buffers["k_c"].shape[1] != batch.count:
                # One set of buffers per batch size: fresh ones for each block would be tens
                # of megabytes of new pages to fault in every BLOCK_TICKS ticks.
                buffers = {name: np.empty((BLOCK_TICKS, batch.count)) for name in names}
            block = {name: buffers[name][:length] for name in names}
            for offset in range(length):
                row = batch.step(block_start + offset)
                for name in names:
                    block[name][offset] = row[name]
            ticks = np.arange(block_start, block_start + length)[:, None]
            valid = ticks < batch.ticks
            stream.update(block, valid)
            peak_k_c = _max(peak_k_c, np.where(valid, block["k_c"], 0.0).max(axis=0))
            if on_block is not None:
                on_block(int(valid.sum()))
            block_start += length
            finished = batch.ticks <= block_start
            if finished.sum() >= COMPACT_SHARE * batch.count:
                # Finished runs leave the arrays: no more work is spent on them.
                done, going = np.flatnonzero(finished), np.flatnonzero(~finished)
                for index, measures, peak in zip(
                    original[done], stream.measures(done), peak_k_c[done], strict=True
                ):
                    runs[index] = BatchRun(measures, float(peak))
                batch.keep(going)
                stream.keep(going)
                peak_k_c, original = peak_k_c[going], original[going]
    return [run for run in runs if run is not None]
