"""PT, the planning trajectory: cubic segments between waypoints (paper eq. 20-25).

Each segment between adjacent waypoints ``(t_i, q_i, v_i)`` and ``(t_j, q_j, v_j)`` is the
cubic that meets the four boundary conditions of eq. 20-23. The waypoint velocities are
either given or chosen by the usual rule (Craig, *Introduction to Robotics*, section 7.3),
see :func:`waypoint_velocities`.

Evaluation runs every control tick (100-1000 Hz), so it uses plain floats, one
:func:`bisect.bisect_right` for the segment lookup and Horner's scheme; :meth:`Trajectory.sample`
does the same arithmetic on numpy arrays of times, for checks and measures of a whole plan.

This module is pure: no I/O, no clocks; the caller passes the time ``t``. :func:`plan_of`
gives a scenario's plan and :func:`check_plan` checks that it stays in the workspace and
leaves a way round the obstacle (rules 5 and 6 of :mod:`controller.task_rules`).
"""

from __future__ import annotations

import itertools
import math
from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from controller.behaviours import aim_margin
from controller.detour import ways_round
from controller.obstacle import free_room
from protocol.errors import (
    ConfigError,
    KinematicsError,
    NoWayRoundError,
    PathOutsideWorkspaceError,
)
from protocol.kinematics import clearly_reachable, inverse
from protocol.ops import Real
from protocol.scenario import Scenario

__all__ = [
    "CubicSegment",
    "Trajectory",
    "check_plan",
    "plan_of",
    "waypoint_velocities",
]

Array = npt.NDArray[np.float64]
Coefficients = tuple[float, float, float, float]
"""``(k0, k1, k2, k3)`` of ``k0 + k1 x + k2 x^2 + k3 x^3``."""


@dataclass(frozen=True, slots=True)
class CubicSegment:
    """One cubic ``q(t) = k0 + k1 tau + k2 tau^2 + k3 tau^3`` with ``tau = t - t_start``.

    This is eq. 24/25 with ``t_i`` shifted to 0: the coefficients are in the *local* time
    ``tau``, which keeps the powers of ``tau`` within ``[0, h^3]`` instead of ``t^3`` and so
    is far better conditioned than the paper's absolute-time coefficients (see
    :meth:`absolute_coefficients` to get those back). ``t`` is not clamped here.
    """

    t_start: float
    t_end: float
    k0: float
    k1: float
    k2: float
    k3: float

    @classmethod
    def from_boundary(
        cls, t_i: float, t_j: float, q_i: float, v_i: float, q_j: float, v_j: float
    ) -> CubicSegment:
        """Closed-form solution of eq. 24 in local time (``h = t_j - t_i > 0``).

        With ``tau = 0`` at ``t_i`` the system is triangular: ``k0 = q_i``, ``k1 = v_i``,
        ``k2 = (3 dq/h - 2 v_i - v_j) / h`` and ``k3 = (v_i + v_j - 2 dq/h) / h^2``.
        """
        h = t_j - t_i
        if not h > 0.0:
            raise ConfigError("t_j", f"segment end {t_j!r} must be after its start {t_i!r}")
        slope = (q_j - q_i) / h
        k2 = (3.0 * slope - 2.0 * v_i - v_j) / h
        k3 = (v_i + v_j - 2.0 * slope) / (h * h)
        return cls(t_i, t_j, q_i, v_i, k2, k3)

    @property
    def duration(self) -> float:
        """``h = t_end - t_start``."""
        return self.t_end - self.t_start

    @property
    def coefficients(self) -> Coefficients:
        """``(k0, k1, k2, k3)`` in local time ``tau``."""
        return (self.k0, self.k1, self.k2, self.k3)

    def absolute_coefficients(self) -> Coefficients:
        """The paper's ``k0..k3`` in absolute time (eq. 25), by expanding ``(t - t_start)^n``.

        Only for comparison with eq. 25; evaluate with the local form.
        """
        a = self.t_start
        k0, k1, k2, k3 = self.k0, self.k1, self.k2, self.k3
        return (
            k0 - k1 * a + k2 * a * a - k3 * a * a * a,
            k1 - 2.0 * k2 * a + 3.0 * k3 * a * a,
            k2 - 3.0 * k3 * a,
            k3,
        )

    def position(self, t: float) -> float:
        """Position at absolute time ``t`` (Horner)."""
        return self.evaluate(t)[0]

    def velocity(self, t: float) -> float:
        """Velocity at absolute time ``t`` (eq. 21/23 in local time)."""
        return self.evaluate(t)[1]

    def acceleration(self, t: float) -> float:
        """Acceleration at absolute time ``t``; linear in ``t`` for a cubic."""
        return self.evaluate(t)[2]

    def evaluate(self, t: float) -> tuple[float, float, float]:
        """``(position, velocity, acceleration)`` in one pass."""
        return cubic(self.k0, self.k1, self.k2, self.k3, t - self.t_start)


def cubic(k0: Real, k1: Real, k2: Real, k3: Real, tau: Real) -> tuple[Real, Real, Real]:
    """Position (Horner), velocity and acceleration of ``k0 + k1 tau + k2 tau^2 + k3 tau^3``,
    for floats or arrays alike: the one place a plan is evaluated."""
    return (
        ((k3 * tau + k2) * tau + k1) * tau + k0,
        (3.0 * k3 * tau + 2.0 * k2) * tau + k1,
        6.0 * k3 * tau + 2.0 * k2,
    )


# --- validation (construction time only) ------------------------------------------------


def _finite(value: object, field: str) -> float:
    """``value`` as a finite float, or a ConfigError naming ``field``."""
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise ConfigError(field, f"expected a number, got {value!r}") from exc
    if not math.isfinite(x):
        raise ConfigError(field, f"must be finite, got {x!r}")
    return x


def _check_times(times: Sequence[float]) -> tuple[float, ...]:
    """At least two finite, strictly increasing waypoint times."""
    if len(times) < 2:
        raise ConfigError("waypoints", f"need at least 2 waypoints, got {len(times)}")
    out = tuple(_finite(t, f"waypoints[{i}].t") for i, t in enumerate(times))
    for i in range(1, len(out)):
        if not out[i] > out[i - 1]:
            raise ConfigError(
                f"waypoints[{i}].t",
                f"times must be strictly increasing: {out[i]!r} after {out[i - 1]!r}",
            )
    return out


def _check_len(values: Sequence[object], n: int, field: str, what: str) -> None:
    """``values`` has one entry per waypoint."""
    if len(values) != n:
        raise ConfigError(field, f"got {n} waypoint times but {len(values)} {what}")


def _rule_velocities(times: Sequence[float], positions: Sequence[float]) -> list[float]:
    """The Craig 7.3 rule on already validated input (see :func:`waypoint_velocities`)."""
    n = len(times)
    out = [0.0] * n
    for i in range(1, n - 1):
        left = (positions[i] - positions[i - 1]) / (times[i] - times[i - 1])
        right = (positions[i + 1] - positions[i]) / (times[i + 1] - times[i])
        if left == 0.0 or right == 0.0 or (left > 0.0) != (right > 0.0):
            continue  # a stop, or the slope changes sign: pause here rather than overshoot
        out[i] = 0.5 * (left + right)
    return out


def waypoint_velocities(times: Sequence[float], positions: Sequence[float]) -> list[float]:
    """Velocities at the waypoints by the usual heuristic (Craig, section 7.3).

    Zero at the first and last waypoint (start and stop at rest); inside, the mean of the
    two neighbouring segment slopes, or zero where the slope changes sign or either slope is
    zero (so the path pauses at a local extremum instead of overshooting it).
    """
    ts = _check_times(times)
    _check_len(positions, len(ts), "waypoints", "positions")
    qs = [_finite(q, f"waypoints[{i}].q") for i, q in enumerate(positions)]
    return _rule_velocities(ts, qs)


# --- trajectories -----------------------------------------------------------------------


class Trajectory:
    """A multi-axis cubic reference (e.g. x, y, z) through waypoints at shared times.

    One time lookup per tick serves every axis. ``evaluate`` is clamped: before ``t_0`` and
    after ``t_n`` it holds the first/last point
    with zero velocity and acceleration.
    """

    __slots__ = (
        "_coeffs",
        "_dims",
        "_first",
        "_last",
        "_points",
        "_rest",
        "_starts",
        "_t0",
        "_times",
        "_tn",
        "_velocities",
    )

    def __init__(
        self,
        times: Sequence[float],
        points: Sequence[Sequence[float]],
        velocities: Sequence[Sequence[float]] | None = None,
    ) -> None:
        ts = _check_times(times)
        n = len(ts)
        _check_len(points, n, "waypoints", "points")
        dims = len(points[0])
        if dims < 1:
            raise ConfigError("waypoints[0].p", "a point needs at least one coordinate")
        pts = tuple(self._row(p, i, dims, "p") for i, p in enumerate(points))
        if velocities is None:
            axes = [_rule_velocities(ts, [p[k] for p in pts]) for k in range(dims)]
            vel = tuple(tuple(axes[k][i] for k in range(dims)) for i in range(n))
        else:
            _check_len(velocities, n, "velocities", "velocity rows")
            vel = tuple(self._row(v, i, dims, "v") for i, v in enumerate(velocities))
        self._times = ts
        self._points = pts
        self._velocities = vel
        self._dims = dims
        self._starts = ts[:-1]
        self._t0 = ts[0]
        self._tn = ts[-1]
        # Per segment, per axis: the local-time coefficients, as plain float tuples.
        self._coeffs: tuple[tuple[Coefficients, ...], ...] = tuple(
            tuple(
                CubicSegment.from_boundary(
                    ts[i], ts[i + 1], pts[i][k], vel[i][k], pts[i + 1][k], vel[i + 1][k]
                ).coefficients
                for k in range(dims)
            )
            for i in range(n - 1)
        )
        self._first = pts[0]
        self._last = pts[-1]
        self._rest = (0.0,) * dims

    @staticmethod
    def _row(row: Sequence[float], i: int, dims: int, name: str) -> tuple[float, ...]:
        """One waypoint's coordinates: ``dims`` finite floats."""
        if len(row) != dims:
            raise ConfigError(
                f"waypoints[{i}].{name}",
                f"expected {dims} coordinates like waypoint 0, got {len(row)}",
            )
        return tuple(_finite(x, f"waypoints[{i}].{name}[{k}]") for k, x in enumerate(row))

    @property
    def times(self) -> tuple[float, ...]:
        """Waypoint times ``t_0 < ... < t_n``."""
        return self._times

    @property
    def points(self) -> tuple[tuple[float, ...], ...]:
        """Waypoints, ``n x dims``."""
        return self._points

    @property
    def velocities(self) -> tuple[tuple[float, ...], ...]:
        """Waypoint velocities actually used (given, or from the rule per axis)."""
        return self._velocities

    @property
    def dims(self) -> int:
        """Number of axes."""
        return self._dims

    @property
    def duration(self) -> float:
        """``t_n - t_0``."""
        return self._tn - self._t0

    def segment(self, index: int, axis: int) -> CubicSegment:
        """Segment ``index`` (from waypoint ``index`` to ``index + 1``) of one axis."""
        k0, k1, k2, k3 = self._coeffs[index][axis]
        return CubicSegment(self._times[index], self._times[index + 1], k0, k1, k2, k3)

    def segment_index(self, t: float) -> int:
        """Index ``j`` of the next waypoint being approached: ``t`` in ``[t_{j-1}, t_j)``.

        Clamped to ``1`` before ``t_1`` and to ``n - 1`` (the last waypoint) from ``t_n`` on.
        """
        j = bisect_right(self._times, t)
        return 1 if j < 1 else min(j, len(self._times) - 1)

    def evaluate(self, t: float) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        """``(position, velocity, acceleration)``, each a tuple with one entry per axis."""
        if not self._t0 <= t <= self._tn:
            if t < self._t0:
                return (self._first, self._rest, self._rest)
            if t > self._tn:
                return (self._last, self._rest, self._rest)
            raise ConfigError("t", f"time must be a number, got {t!r}")
        i = bisect_right(self._starts, t) - 1
        tau = t - self._starts[i]
        q: list[float] = []
        qd: list[float] = []
        qdd: list[float] = []
        for coefficients in self._coeffs[i]:
            position, velocity, acceleration = cubic(*coefficients, tau)
            q.append(position)
            qd.append(velocity)
            qdd.append(acceleration)
        return (tuple(q), tuple(qd), tuple(qdd))

    def sample(self, times: Array) -> tuple[Array, Array]:
        """Positions and velocities, ``(len(times), dims)`` each, at ``times`` within
        ``[t_0, t_n]``: :meth:`evaluate`'s arithmetic on arrays, so equal to it bit for bit."""
        starts = np.array(self._starts)
        segment = np.searchsorted(starts, times, side="right") - 1
        k = np.array(self._coeffs)[segment]  # (len(times), dims, 4)
        tau = (times - starts[segment])[:, None]
        positions, velocities, _ = cubic(k[..., 0], k[..., 1], k[..., 2], k[..., 3], tau)
        return positions, velocities


# --- a scenario's plan --------------------------------------------------------------------

PATH_CHECK_STEP = 0.005
"""s between the planned points checked against the workspace."""


def plan_of(scenario: Scenario) -> Trajectory:
    """The cubic reference through a scenario's waypoints."""
    return Trajectory(
        [w.t for w in scenario.waypoints], [(w.x, w.y, w.z) for w in scenario.waypoints]
    )


def check_plan(scenario: Scenario) -> None:
    """The planned path between the waypoints must stay inside the workspace (every
    :data:`PATH_CHECK_STEP`), and a segment the obstacle stands across must leave a way round
    it inside the joint limits (:func:`controller.detour.ways_round`); a :class:`ConfigError`
    names the segment if not.

    The points are checked all at once with a margin; only those not clearly inside go
    through :func:`inverse` one by one, which has the last word (and the message).
    """
    trajectory = plan_of(scenario)
    start, end = scenario.waypoints[0].t, scenario.waypoints[-1].t
    steps = max(1, math.ceil((end - start) / PATH_CHECK_STEP))
    times = start + (end - start) * np.arange(steps + 1) / steps
    positions = trajectory.sample(times)[0]
    doubtful = ~clearly_reachable(
        scenario.robot, positions[:, 0], positions[:, 1], positions[:, 2], scenario.elbow
    )
    for index in np.flatnonzero(doubtful):
        t = float(times[index])
        x, y, z = positions[index].tolist()
        try:
            inverse(scenario.robot, x, y, z, scenario.elbow)
        except KinematicsError as error:
            segment = trajectory.segment_index(t)
            raise PathOutsideWorkspaceError(
                f"waypoints[{segment - 1}..{segment}]",
                f"the planned path leaves the workspace at t = {t:.3f} s: {error}",
            ) from error
    if scenario.obstacle is None:
        return
    obstacle, pass_margin = scenario.obstacle, scenario.controller.ao_pass_margin
    for segment, (here, there) in enumerate(itertools.pairwise(scenario.waypoints)):
        room = free_room(obstacle, (there.x, there.y, there.z))
        ways = ways_round(
            scenario.robot,
            obstacle.grown(aim_margin(pass_margin, room)),  # what AO steers round to there
            (here.x, here.y, here.z),
            (there.x, there.y, there.z),
            scenario.elbow,
        )
        if ways is not None and not any(ways):
            raise NoWayRoundError(
                f"waypoints[{segment}..{segment + 1}]",
                "no way round the obstacle inside the joint limits",
            )
