"""Tests of PT, the cubic waypoint planner (paper eq. 20-25)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from controller.planner import CubicSegment, Trajectory, check_plan, waypoint_velocities
from protocol.errors import ConfigError
from protocol.scenario import parse_scenario

Coefficients = tuple[float, float, float, float]


def solve_eq25(
    t_i: float, t_j: float, q_i: float, v_i: float, q_j: float, v_j: float
) -> Coefficients:
    """The paper's eq. 24 solved literally (4x4 system in absolute time): the reference the
    planner's closed form is checked against (slow and, for large t, badly conditioned)."""
    m = np.array(
        [
            [1.0, t_i, t_i**2, t_i**3],
            [0.0, 1.0, 2.0 * t_i, 3.0 * t_i**2],
            [1.0, t_j, t_j**2, t_j**3],
            [0.0, 1.0, 2.0 * t_j, 3.0 * t_j**2],
        ]
    )
    k = np.linalg.solve(m, np.array([q_i, v_i, q_j, v_j]))
    return (float(k[0]), float(k[1]), float(k[2]), float(k[3]))


class OneAxis:
    """A one-axis :class:`Trajectory` seen as scalars, for the single-axis properties."""

    def __init__(
        self,
        times: list[float],
        positions: list[float],
        velocities: list[float] | None = None,
    ) -> None:
        self.trajectory = Trajectory(
            times,
            [(q,) for q in positions],
            None if velocities is None else [(v,) for v in velocities],
        )
        self.times = self.trajectory.times
        self.positions = tuple(point[0] for point in self.trajectory.points)
        self.velocities = tuple(v[0] for v in self.trajectory.velocities)
        self.segments = [self.trajectory.segment(i, 0) for i in range(len(self.times) - 1)]
        self.duration = self.trajectory.duration
        self.segment_index = self.trajectory.segment_index

    def evaluate(self, t: float) -> tuple[float, float, float]:
        q, qd, qdd = self.trajectory.evaluate(t)
        return q[0], qd[0], qdd[0]


# (t_i, t_j, q_i, v_i, q_j, v_j): rest-to-rest, moving ends, reversals, late and short ones.
SEGMENTS = [
    (0.0, 1.0, 0.0, 0.0, 1.0, 0.0),
    (0.0, 2.0, -0.3, 0.5, 0.7, -0.25),
    (1.5, 2.25, 0.2, -1.0, -0.4, 2.0),
    (3.0, 3.05, 1.0, 0.0, 1.0, 0.0),
    (-2.0, -0.5, 0.12, 0.3, 0.12, -0.3),
    (10.0, 10.01, 0.5, 20.0, 0.7, 20.0),
    (100.0, 103.0, -1.7, 0.0, 2.9, 1.1),
]


def _close(a: float, b: float, scale: float, rel: float) -> bool:
    """``|a - b| <= rel * scale`` with the scale of the terms that were summed."""
    return abs(a - b) <= rel * max(1.0, scale)


def _segment_extrema(seg: CubicSegment) -> list[float]:
    """Positions at the segment's ends and at every interior stationary point."""
    h = seg.duration
    taus = [0.0, h]
    a, b, c = 3.0 * seg.k3, 2.0 * seg.k2, seg.k1
    if a == 0.0:
        if b != 0.0:
            taus.append(-c / b)
    else:
        disc = b * b - 4.0 * a * c
        if disc >= 0.0:
            r = math.sqrt(disc)
            taus += [(-b - r) / (2.0 * a), (-b + r) / (2.0 * a)]
    return [seg.position(seg.t_start + tau) for tau in taus if 0.0 <= tau <= h]


# --- one segment: eq. 20-25 -------------------------------------------------------------


@pytest.mark.parametrize(("t_i", "t_j", "q_i", "v_i", "q_j", "v_j"), SEGMENTS)
def test_closed_form_meets_eq24_boundary_conditions(
    t_i: float, t_j: float, q_i: float, v_i: float, q_j: float, v_j: float
) -> None:
    seg = CubicSegment.from_boundary(t_i, t_j, q_i, v_i, q_j, v_j)
    h = t_j - t_i
    scale = max(abs(q_i), abs(q_j), abs(v_i) * h, abs(v_j) * h)
    assert seg.position(t_i) == q_i  # eq. 20: tau = 0 makes these exact
    assert seg.velocity(t_i) == v_i  # eq. 21
    assert _close(seg.position(t_j), q_j, scale, 1e-12)  # eq. 22
    assert _close(seg.velocity(t_j), v_j, scale / h, 1e-12)  # eq. 23
    q, qd, qdd = seg.evaluate(t_j)
    assert (q, qd, qdd) == (seg.position(t_j), seg.velocity(t_j), seg.acceleration(t_j))


@pytest.mark.parametrize(("t_i", "t_j", "q_i", "v_i", "q_j", "v_j"), SEGMENTS)
def test_closed_form_equals_literal_eq25(
    t_i: float, t_j: float, q_i: float, v_i: float, q_j: float, v_j: float
) -> None:
    seg = CubicSegment.from_boundary(t_i, t_j, q_i, v_i, q_j, v_j)
    paper = solve_eq25(t_i, t_j, q_i, v_i, q_j, v_j)
    ours = seg.absolute_coefficients()
    # The absolute-time system gets ill-conditioned as t grows (the reason for local time),
    # so the agreement is bounded by its condition number, not by machine epsilon.
    m = np.array(
        [
            [1.0, t_i, t_i**2, t_i**3],
            [0.0, 1.0, 2.0 * t_i, 3.0 * t_i**2],
            [1.0, t_j, t_j**2, t_j**3],
            [0.0, 1.0, 2.0 * t_j, 3.0 * t_j**2],
        ]
    )
    tol = 1e-15 * float(np.linalg.cond(m)) + 1e-12
    np.testing.assert_allclose(ours, paper, rtol=tol, atol=tol * max(map(abs, paper)))
    # Both are the same polynomial: compare values across the segment.
    for t in np.linspace(t_i, t_j, 7):
        s_paper = sum(k * float(t) ** n for n, k in enumerate(paper))
        assert s_paper == pytest.approx(seg.position(float(t)), rel=tol, abs=tol)


@given(
    t_i=st.floats(-5.0, 5.0),
    h=st.floats(0.05, 3.0),
    q=st.lists(st.floats(-10.0, 10.0), min_size=2, max_size=2),
    v=st.lists(st.floats(-20.0, 20.0), min_size=2, max_size=2),
)
def test_closed_form_equals_eq25_random(
    t_i: float, h: float, q: list[float], v: list[float]
) -> None:
    t_j = t_i + h
    assume(t_j > t_i)
    seg = CubicSegment.from_boundary(t_i, t_j, q[0], v[0], q[1], v[1])
    paper = solve_eq25(t_i, t_j, q[0], v[0], q[1], v[1])
    for t in (t_i, 0.5 * (t_i + t_j), t_j):
        s_paper = sum(k * t**n for n, k in enumerate(paper))
        assert s_paper == pytest.approx(seg.position(t), rel=1e-7, abs=1e-7)


def test_from_boundary_refuses_empty_interval() -> None:
    with pytest.raises(ConfigError) as info:
        CubicSegment.from_boundary(1.0, 1.0, 0.0, 0.0, 1.0, 0.0)
    assert info.value.field == "t_j"


# --- the velocity rule ------------------------------------------------------------------


def test_rule_on_a_hand_example() -> None:
    times = [0.0, 1.0, 2.0, 4.0, 5.0, 6.0]
    positions = [0.0, 1.0, 3.0, 1.0, 1.0, 2.0]
    # slopes: 1, 2, -1, 0, 1
    assert waypoint_velocities(times, positions) == [0.0, 1.5, 0.0, 0.0, 0.0, 0.0]


@st.composite
def waypoint_sets(draw: st.DrawFn) -> tuple[list[float], list[float]]:
    """2-8 waypoints, gaps >= 0.05 s, bounded positions with some ties and reversals."""
    n = draw(st.integers(2, 8))
    t0 = draw(st.floats(-10.0, 10.0))
    gaps = draw(st.lists(st.floats(0.05, 2.0), min_size=n - 1, max_size=n - 1))
    times = [t0]
    for g in gaps:
        times.append(times[-1] + g)
    value = st.floats(-10.0, 10.0) | st.sampled_from([-1.0, 0.0, 1.0])
    positions = draw(st.lists(value, min_size=n, max_size=n))
    return times, positions


def _slopes(times: Sequence[float], positions: Sequence[float]) -> list[float]:
    return [
        (positions[i + 1] - positions[i]) / (times[i + 1] - times[i]) for i in range(len(times) - 1)
    ]


@given(waypoint_sets())
def test_rule_velocities(data: tuple[list[float], list[float]]) -> None:
    times, positions = data
    vs = waypoint_velocities(times, positions)
    slopes = _slopes(times, positions)
    assert len(vs) == len(times)
    assert vs[0] == 0.0
    assert vs[-1] == 0.0
    for i in range(1, len(times) - 1):
        left, right = slopes[i - 1], slopes[i]
        if left == 0.0 or right == 0.0 or (left > 0.0) != (right > 0.0):
            assert vs[i] == 0.0
        else:
            assert vs[i] == pytest.approx(0.5 * (left + right))
            # the mean always has the sign of both neighbouring slopes
            assert (vs[i] > 0.0) == (left > 0.0)


# --- whole trajectories -----------------------------------------------------------------


@given(waypoint_sets())
def test_trajectory_passes_waypoints_with_continuous_velocity(
    data: tuple[list[float], list[float]],
) -> None:
    times, positions = data
    traj = OneAxis(times, positions)
    vs = traj.velocities
    for t, q, v in zip(times, positions, vs, strict=True):
        p, pd, _ = traj.evaluate(t)
        assert p == pytest.approx(q, rel=1e-12, abs=1e-12)
        # the end waypoint's velocity is 0 by the rule; the end acceleration need not be
        assert pd == pytest.approx(v, rel=1e-9, abs=1e-9)
    segs = traj.segments
    for j in range(1, len(times) - 1):
        left, right = segs[j - 1], segs[j]
        scale = max(1.0, *(abs(s) for s in _slopes(times, positions)))
        assert left.position(times[j]) == pytest.approx(right.position(times[j]), abs=1e-12)
        assert left.velocity(times[j]) == pytest.approx(right.velocity(times[j]), abs=1e-11 * scale)
        assert right.velocity(times[j]) == vs[j]


@given(waypoint_sets())
def test_rule_does_not_overshoot_when_slopes_are_comparable(
    data: tuple[list[float], list[float]],
) -> None:
    """No overshoot of a monotone pair when both end velocities lie in [0, 3] x the slope.

    That is inside the Fritsch-Carlson monotonicity region of a cubic Hermite segment. With
    the mean rule, the velocities always have the slope's sign (or are 0), but their size is
    (1 + m_other / m) / 2 times the slope m, so the bound holds only when a neighbouring
    slope is at most 5x this one; see test_rule_can_overshoot_next_to_a_steep_segment.
    """
    times, positions = data
    traj = OneAxis(times, positions)
    vs = traj.velocities
    for i, seg in enumerate(traj.segments):
        q_i, q_j = positions[i], positions[i + 1]
        m = (q_j - q_i) / (times[i + 1] - times[i])
        if m == 0.0:
            # a flat pair: the rule gives zero velocity at both ends, so it stays flat
            assert vs[i] == 0.0 and vs[i + 1] == 0.0
            assert seg.k2 == 0.0 and seg.k3 == 0.0
            continue
        a, b = vs[i] / m, vs[i + 1] / m
        assert a >= 0.0 and b >= 0.0  # always true for the rule
        if a <= 3.0 and b <= 3.0:
            lo, hi = min(q_i, q_j), max(q_i, q_j)
            tol = 1e-12 * max(1.0, abs(q_i), abs(q_j))
            for q in _segment_extrema(seg):
                assert lo - tol <= q <= hi + tol


@given(
    t0=st.floats(-5.0, 5.0),
    gaps=st.lists(st.floats(0.05, 2.0), min_size=1, max_size=7),
    q0=st.floats(-10.0, 10.0),
    base=st.floats(0.01, 5.0),
    factors=st.lists(st.floats(1.0, 5.0), min_size=7, max_size=7),
    sign=st.sampled_from([-1.0, 1.0]),
)
def test_monotone_waypoints_with_bounded_slope_ratio_give_monotone_path(
    t0: float,
    gaps: list[float],
    q0: float,
    base: float,
    factors: list[float],
    sign: float,
) -> None:
    """Slopes within a factor 5 of each other: the whole path is monotone between waypoints."""
    times = [t0]
    positions = [q0]
    for g, f in zip(gaps, factors, strict=False):
        times.append(times[-1] + g)
        positions.append(positions[-1] + sign * base * f * g)
    traj = OneAxis(times, positions)
    for i, seg in enumerate(traj.segments):
        lo, hi = sorted((positions[i], positions[i + 1]))
        tol = 1e-12 * max(1.0, abs(lo), abs(hi))
        for q in _segment_extrema(seg):
            assert lo - tol <= q <= hi + tol
        for t in np.linspace(seg.t_start, seg.t_end, 11):
            assert sign * seg.velocity(float(t)) >= -1e-9 * base


def test_rule_can_overshoot_next_to_a_steep_segment() -> None:
    """The mean rule is not monotone in general: a gentle segment next to a steep one dips."""
    traj = OneAxis([0.0, 1.0, 2.0], [0.0, 0.01, 10.0])
    assert traj.velocities[1] == pytest.approx(5.0)
    q_mid, _, _ = traj.evaluate(0.5)
    assert q_mid < 0.0  # below both waypoints of the first segment


def test_given_velocities_are_used() -> None:
    traj = OneAxis([0.0, 1.0, 3.0], [0.0, 1.0, 0.0], velocities=[0.5, 0.2, -0.1])
    assert traj.velocities == (0.5, 0.2, -0.1)
    for t, q, v in zip(traj.times, traj.positions, traj.velocities, strict=True):
        p, pd, _ = traj.evaluate(t)
        assert p == pytest.approx(q, abs=1e-12)
        assert pd == pytest.approx(v, abs=1e-12)


def test_clamping_and_segment_index() -> None:
    traj = OneAxis([1.0, 2.0, 4.0], [0.0, 2.0, 1.0])
    assert traj.duration == 3.0
    assert traj.evaluate(0.0) == (0.0, 0.0, 0.0)
    assert traj.evaluate(-math.inf) == (0.0, 0.0, 0.0)
    assert traj.evaluate(4.5) == (1.0, 0.0, 0.0)
    assert traj.evaluate(math.inf) == (1.0, 0.0, 0.0)
    assert traj.evaluate(4.0)[0] == pytest.approx(1.0, abs=1e-12)
    assert [traj.segment_index(t) for t in (0.0, 1.0, 1.5, 2.0, 3.9, 4.0, 9.0)] == [
        1,
        1,
        1,
        2,
        2,
        2,
        2,
    ]
    with pytest.raises(ConfigError) as info:
        traj.evaluate(math.nan)
    assert info.value.field == "t"


def test_acceleration_is_the_derivative_of_velocity() -> None:
    traj = OneAxis([0.0, 0.7, 1.5, 2.0], [0.0, 0.4, -0.2, 0.3])
    eps = 1e-6
    for t in (0.1, 0.69, 0.71, 1.2, 1.9):
        _, v_lo, _ = traj.evaluate(t - eps)
        _, v_hi, _ = traj.evaluate(t + eps)
        _, _, a = traj.evaluate(t)
        assert (v_hi - v_lo) / (2 * eps) == pytest.approx(a, rel=1e-5, abs=1e-5)


@settings(max_examples=50)
@given(waypoint_sets(), st.integers(1, 3), st.data())
def test_multi_axis_matches_single_axis(
    data: tuple[list[float], list[float]], dims: int, draw: st.DataObject
) -> None:
    times, first_axis = data
    axes = [first_axis] + [
        draw.draw(st.lists(st.floats(-10.0, 10.0), min_size=len(times), max_size=len(times)))
        for _ in range(dims - 1)
    ]
    points = [[axes[k][i] for k in range(dims)] for i in range(len(times))]
    traj = Trajectory(times, points)
    singles = [OneAxis(times, axis) for axis in axes]
    assert traj.dims == dims
    assert traj.times == tuple(times)
    assert traj.points == tuple(tuple(p) for p in points)
    assert traj.duration == times[-1] - times[0]
    t_lo, t_hi = times[0] - 1.0, times[-1] + 1.0
    for t in [*times, *np.linspace(t_lo, t_hi, 23).tolist()]:
        q, qd, qdd = traj.evaluate(t)
        assert len(q) == len(qd) == len(qdd) == dims
        for k, single in enumerate(singles):
            assert (q[k], qd[k], qdd[k]) == single.evaluate(t)
        assert traj.segment_index(t) == singles[0].segment_index(t)


def test_multi_axis_given_velocities_and_segments() -> None:
    times = [0.0, 1.0, 2.0]
    points = [(0.0, 0.0, 0.1), (0.2, 0.1, 0.1), (0.3, 0.3, 0.0)]
    vels = [(0.0, 0.0, 0.0), (0.1, 0.2, -0.05), (0.0, 0.0, 0.0)]
    traj = Trajectory(times, points, velocities=vels)
    q, qd, _ = traj.evaluate(1.0)
    assert q == pytest.approx(points[1])
    assert qd == pytest.approx(vels[1])
    assert traj.segment(1, 2) == CubicSegment.from_boundary(1.0, 2.0, 0.1, -0.05, 0.0, 0.0)
    assert traj.evaluate(-1.0) == (points[0], (0.0,) * 3, (0.0,) * 3)
    assert traj.evaluate(3.0) == (points[2], (0.0,) * 3, (0.0,) * 3)


# --- validation -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("times", "positions", "velocities", "field"),
    [
        ([0.0], [1.0], None, "waypoints"),
        ([], [], None, "waypoints"),
        ([0.0, 1.0, 2.0], [0.0, 1.0], None, "waypoints"),
        ([0.0, 1.0, 2.0, 2.0], [0.0, 1.0, 2.0, 3.0], None, "waypoints[3].t"),
        ([0.0, 1.0, 0.5], [0.0, 1.0, 2.0], None, "waypoints[2].t"),
        ([0.0, math.nan, 2.0], [0.0, 1.0, 2.0], None, "waypoints[1].t"),
        ([0.0, 1.0, math.inf], [0.0, 1.0, 2.0], None, "waypoints[2].t"),
        ([0.0, 1.0], [0.0, math.nan], None, "waypoints[1].p[0]"),
        ([0.0, 1.0], [-math.inf, 0.0], None, "waypoints[0].p[0]"),
        ([0.0, 1.0], [0.0, 1.0], [0.0], "velocities"),
        ([0.0, 1.0], [0.0, 1.0], [0.0, math.nan], "waypoints[1].v[0]"),
    ],
)
def test_one_axis_validation_names_the_field(
    times: list[float],
    positions: list[float],
    velocities: list[float] | None,
    field: str,
) -> None:
    with pytest.raises(ConfigError) as info:
        OneAxis(times, positions, velocities)
    assert info.value.field == field
    assert str(info.value).startswith(f"{field}: ")


@pytest.mark.parametrize(
    ("times", "positions", "field"),
    [
        ([0.0], [1.0], "waypoints"),
        ([0.0, 1.0, 1.0], [0.0, 1.0, 2.0], "waypoints[2].t"),
        ([0.0, 1.0], [0.0, math.nan], "waypoints[1].q"),
    ],
)
def test_waypoint_velocities_validation(
    times: list[float], positions: list[float], field: str
) -> None:
    with pytest.raises(ConfigError) as info:
        waypoint_velocities(times, positions)
    assert info.value.field == field


@pytest.mark.parametrize(
    ("times", "points", "velocities", "field"),
    [
        ([0.0], [(0.0, 0.0)], None, "waypoints"),
        ([0.0, 1.0, 2.0, 3.0, 2.5], [(0.0,)] * 5, None, "waypoints[4].t"),
        ([0.0, 1.0], [(0.0, 0.0)], None, "waypoints"),
        ([0.0, 1.0], [(), ()], None, "waypoints[0].p"),
        ([0.0, 1.0, 2.0], [(0.0, 0.0), (1.0, 1.0), (1.0,)], None, "waypoints[2].p"),
        ([0.0, 1.0], [(0.0, 0.0), (1.0, math.nan)], None, "waypoints[1].p[1]"),
        ([0.0, 1.0], [(0.0, 0.0), (1.0, 1.0)], [(0.0, 0.0)], "velocities"),
        ([0.0, 1.0], [(0.0, 0.0), (1.0, 1.0)], [(0.0, 0.0), (0.0,)], "waypoints[1].v"),
        ([0.0, 1.0], [(0.0, 0.0), (1.0, 1.0)], [(math.inf, 0.0), (0.0, 0.0)], "waypoints[0].v[0]"),
    ],
)
def test_trajectory_validation_names_the_field(
    times: list[float],
    points: list[tuple[float, ...]],
    velocities: list[tuple[float, ...]] | None,
    field: str,
) -> None:
    with pytest.raises(ConfigError) as info:
        Trajectory(times, points, velocities)
    assert info.value.field == field


@settings(max_examples=50)
@given(st.integers(2, 7), st.integers(0, 2**32 - 1))
def test_sample_is_evaluate_bit_for_bit(count: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    times = np.cumsum(rng.uniform(0.1, 3.0, count)) - 1.0
    trajectory = Trajectory(times.tolist(), rng.uniform(-1.0, 1.0, (count, 3)).tolist())
    at = np.concatenate([times, rng.uniform(times[0], times[-1], 200)])
    positions, velocities = trajectory.sample(at)
    for t, position, velocity in zip(
        at.tolist(), positions.tolist(), velocities.tolist(), strict=True
    ):
        expected = trajectory.evaluate(t)
        assert (tuple(position), tuple(velocity)) == (expected[0], expected[1])


# --- a scenario's plan ------------------------------------------------------------------


def test_path_leaving_the_workspace_between_waypoints_is_rejected() -> None:
    # Both ends are reachable, but the straight move between them cuts into the inner
    # hole of the annulus, where theta2 would pass its limit.
    document = {
        "waypoints": [
            {"t": 0.0, "x": 0.2, "y": -0.05, "z": 0.22},
            {"t": 2.0, "x": 0.0, "y": -0.2, "z": 0.22},
        ]
    }
    with pytest.raises(ConfigError, match="leaves the workspace") as error:
        check_plan(parse_scenario(document))
    assert error.value.field == "waypoints[0..1]"
