"""Kinematics: FK/IK round trips, reach and joint-limit errors, Jacobian and damped inverse."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from protocol.config import RobotConfig
from protocol.errors import JointLimitError, ScaraError, UnreachableError
from protocol.kinematics import (
    CLEAR_MARGIN,
    DAMPING_S2_REF,
    Elbow,
    clearly_reachable,
    forward,
    inverse,
    jacobian_planar,
    joint_rates_for,
    reach_radii,
    tcp_velocity,
)

CONFIG = RobotConfig()
R_MIN, R_MAX = reach_radii(CONFIG)
Z_MID = 0.5 * (CONFIG.z_min + CONFIG.z_max)


def _elbow_of(theta2: float) -> Elbow:
    return Elbow.DOWN if theta2 >= 0.0 else Elbow.UP


def test_forward_matches_eq_10_at_known_poses() -> None:
    assert forward(CONFIG, 0.0, 0.0, 0.0) == pytest.approx((0.6, 0.0, 0.387))
    assert forward(CONFIG, math.pi / 2, -math.pi / 2, 0.1) == pytest.approx((0.275, 0.325, 0.287))


def test_joint_grid_round_trips_through_both_elbows() -> None:
    theta2s = [t for t in np.linspace(CONFIG.theta2_min, CONFIG.theta2_max, 59) if abs(t) >= 1e-3]
    for theta1 in np.linspace(CONFIG.theta1_min, CONFIG.theta1_max, 61):
        for theta2 in theta2s:
            for d3 in (CONFIG.d3_min, 0.5 * (CONFIG.d3_min + CONFIG.d3_max), CONFIG.d3_max):
                joints = (float(theta1), float(theta2), d3)
                solved = inverse(CONFIG, *forward(CONFIG, *joints), _elbow_of(theta2))
                assert solved == pytest.approx(joints, abs=1e-9, rel=0.0), joints


def test_cartesian_grid_over_annulus_round_trips() -> None:
    checked = 0
    for x in np.linspace(-R_MAX, R_MAX, 81):
        for y in np.linspace(-R_MAX, R_MAX, 81):
            if not R_MIN <= math.hypot(x, y) <= R_MAX:
                continue
            for elbow in Elbow:
                point = (float(x), float(y), Z_MID)
                try:
                    joints = inverse(CONFIG, *point, elbow)
                except JointLimitError:  # behind the robot, past the theta1 limits
                    continue
                assert forward(CONFIG, *joints) == pytest.approx(point, abs=1e-9, rel=0.0)
                checked += 1
    assert checked > 5000


@pytest.mark.parametrize("phi", np.linspace(-1.5, 1.5, 7))  # in front, clear of theta1 limits
@pytest.mark.parametrize("elbow", Elbow)
def test_workspace_boundary_is_reachable(phi: float, elbow: Elbow) -> None:
    for radius in (R_MIN, R_MAX):
        point = (radius * math.cos(phi), radius * math.sin(phi), CONFIG.z_min)
        joints = inverse(CONFIG, *point, elbow)
        assert forward(CONFIG, *joints) == pytest.approx(point, abs=1e-9, rel=0.0)
        assert all(
            lo <= q <= hi
            for lo, q, hi in zip(CONFIG.joint_min, joints, CONFIG.joint_max, strict=True)
        )


def test_elbow_sets_sign_of_theta2_and_down_is_eq_15() -> None:
    x, y = 0.3, 0.2
    down = inverse(CONFIG, x, y, Z_MID, Elbow.DOWN)
    up = inverse(CONFIG, x, y, Z_MID, Elbow.UP)
    assert down[1] > 0.0 > up[1]
    assert up[1] == pytest.approx(-down[1])
    r = math.hypot(x, y)
    alpha = math.acos((CONFIG.a1**2 + r**2 - CONFIG.a2**2) / (2 * CONFIG.a1 * r))
    assert down[0] == pytest.approx(math.atan2(y, x) - alpha)
    assert up[0] == pytest.approx(math.atan2(y, x) + alpha)


@pytest.mark.parametrize(
    ("point", "fragment"),
    [
        ((R_MAX + 1e-6, 0.0, Z_MID), "planar radius"),
        ((0.0, -0.7, Z_MID), "planar radius"),
        ((0.03, 0.02, Z_MID), "planar radius"),  # inside |a1 - a2| = 0.05
        ((0.4, 0.0, CONFIG.z_max + 1e-6), "z must lie"),
        ((0.4, 0.0, CONFIG.z_min - 1e-6), "z must lie"),
        ((math.nan, 0.3, Z_MID), "planar radius"),
    ],
)
@pytest.mark.parametrize("elbow", Elbow)
def test_unreachable_points_raise(
    point: tuple[float, float, float], fragment: str, elbow: Elbow
) -> None:
    with pytest.raises(UnreachableError, match=fragment) as caught:
        inverse(CONFIG, *point, elbow)
    assert isinstance(caught.value, ScaraError)


def test_behind_the_robot_violates_theta1_on_both_elbows() -> None:
    # At r = 0.59 on the negative x axis both branches need |theta1| of about 170 deg.
    for elbow in Elbow:
        with pytest.raises(JointLimitError, match=r"theta1 = .*limits \[-150\.000, 150\.000\]"):
            inverse(CONFIG, -0.59, 0.0, Z_MID, elbow)


def test_inside_min_radius_violates_theta2() -> None:
    # Between |a1 - a2| and r_min the elbow would have to bend past 145 deg.
    assert abs(CONFIG.a1 - CONFIG.a2) < 0.08 < R_MIN
    with pytest.raises(JointLimitError, match="theta2") as caught:
        inverse(CONFIG, 0.08, 0.0, Z_MID)
    assert isinstance(caught.value, ScaraError)


def test_reach_radii() -> None:
    a1, a2 = CONFIG.a1, CONFIG.a2
    expected_min = math.sqrt(a1**2 + a2**2 + 2 * a1 * a2 * math.cos(math.radians(145)))
    assert reach_radii(CONFIG) == pytest.approx((expected_min, a1 + a2))
    full = RobotConfig(theta2_min=-math.pi, theta2_max=math.pi)
    assert reach_radii(full) == pytest.approx((abs(a1 - a2), a1 + a2))
    one_sided = RobotConfig(theta2_min=0.5, theta2_max=2.0)
    r_low, r_high = reach_radii(one_sided)
    assert r_low == pytest.approx(math.hypot(*forward(one_sided, 0.0, 2.0, 0.0)[:2]))
    assert r_high == pytest.approx(math.hypot(*forward(one_sided, 0.0, 0.5, 0.0)[:2]))


@pytest.mark.parametrize("theta1", np.linspace(-2.6, 2.6, 7))
@pytest.mark.parametrize("theta2", np.linspace(-2.5, 2.5, 9))
def test_jacobian_matches_central_difference(theta1: float, theta2: float) -> None:
    h = 1e-6
    columns = []
    for dt1, dt2 in ((h, 0.0), (0.0, h)):
        plus = forward(CONFIG, theta1 + dt1, theta2 + dt2, 0.0)
        minus = forward(CONFIG, theta1 - dt1, theta2 - dt2, 0.0)
        columns.append(((plus[0] - minus[0]) / (2 * h), (plus[1] - minus[1]) / (2 * h)))
    numeric = (columns[0][0], columns[1][0], columns[0][1], columns[1][1])
    assert jacobian_planar(CONFIG, theta1, theta2) == pytest.approx(numeric, abs=1e-8, rel=0.0)


def _apply(
    jacobian: tuple[float, float, float, float], qdot: tuple[float, float]
) -> tuple[float, float]:
    j11, j12, j21, j22 = jacobian
    return (j11 * qdot[0] + j12 * qdot[1], j21 * qdot[0] + j22 * qdot[1])


def test_tcp_velocity_is_the_jacobian_times_the_joint_rates_for_floats_and_arrays() -> None:
    rng = np.random.default_rng(7)
    theta1, theta2 = rng.uniform(-2.5, 2.5, 50), rng.uniform(-2.5, 2.5, 50)
    rate1, rate2 = rng.uniform(-3.0, 3.0, 50), rng.uniform(-3.0, 3.0, 50)
    vx, vy = tcp_velocity(CONFIG, theta1, theta2, rate1, rate2, np)
    for i in range(50):
        j11, j12, j21, j22 = jacobian_planar(CONFIG, theta1[i], theta2[i])
        expected = (j11 * rate1[i] + j12 * rate2[i], j21 * rate1[i] + j22 * rate2[i])
        one = tcp_velocity(CONFIG, float(theta1[i]), float(theta2[i]), rate1[i], rate2[i])
        assert one == pytest.approx(expected, abs=1e-12)
        assert (vx[i], vy[i]) == one  # the same formula on arrays, bit for bit


@pytest.mark.parametrize("theta2", [-2.5, -1.0, -0.2, -math.asin(DAMPING_S2_REF), 0.2, 1.0, 2.5])
@pytest.mark.parametrize("velocity", [(0.3, -0.1), (-1.0, 0.5), (0.0, 0.2)])
def test_damped_inverse_is_exact_away_from_singularity(
    theta2: float, velocity: tuple[float, float]
) -> None:
    theta1 = 0.7
    qdot = joint_rates_for(CONFIG, theta1, theta2, *velocity)
    jacobian = jacobian_planar(CONFIG, theta1, theta2)
    assert _apply(jacobian, qdot) == pytest.approx(velocity, abs=1e-9, rel=0.0)


@pytest.mark.parametrize("theta2", [1e-6, 0.01, -0.05, 0.09])
def test_zero_damping_is_the_exact_inverse_even_near_singularity(theta2: float) -> None:
    qdot = joint_rates_for(CONFIG, 0.3, theta2, 0.2, -0.4, damping=0.0)
    exact = np.linalg.solve(np.reshape(jacobian_planar(CONFIG, 0.3, theta2), (2, 2)), [0.2, -0.4])
    assert qdot == pytest.approx(tuple(exact), rel=1e-9)


@pytest.mark.parametrize("theta2", [0.0, 1e-4, -0.03, 0.08, math.pi])
def test_damped_inverse_matches_dls_formula_inside_damping_zone(theta2: float) -> None:
    damping = 0.01
    ratio = math.sin(theta2) / DAMPING_S2_REF
    lam2 = damping**2 * (1.0 - ratio**2)
    jac = np.reshape(jacobian_planar(CONFIG, -0.4, theta2), (2, 2))
    expected = jac.T @ np.linalg.solve(jac @ jac.T + lam2 * np.eye(2), [0.5, 0.8])
    qdot = joint_rates_for(CONFIG, -0.4, theta2, 0.5, 0.8, damping=damping)
    assert qdot == pytest.approx(tuple(expected), rel=1e-9)


@pytest.mark.parametrize("theta2", [0.0, math.pi])
@pytest.mark.parametrize("velocity", [(1.0, 0.0), (0.0, 1.0), (-0.6, 0.8)])
def test_damped_inverse_is_bounded_at_singularity(
    theta2: float, velocity: tuple[float, float]
) -> None:
    damping = 0.01
    qdot = joint_rates_for(CONFIG, 0.2, theta2, *velocity, damping=damping)
    assert all(math.isfinite(q) for q in qdot)
    # Each singular value sigma maps to sigma / (sigma^2 + lambda^2) <= 1 / (2 lambda).
    assert math.hypot(*qdot) <= math.hypot(*velocity) / (2 * damping)


@given(
    theta1=st.floats(CONFIG.theta1_min, CONFIG.theta1_max),
    theta2=st.floats(1e-3, CONFIG.theta2_max),
    negative=st.booleans(),
    d3=st.floats(CONFIG.d3_min, CONFIG.d3_max),
)
def test_round_trip_property(theta1: float, theta2: float, negative: bool, d3: float) -> None:
    theta2 = -theta2 if negative else theta2
    point = forward(CONFIG, theta1, theta2, d3)
    elbow = _elbow_of(theta2)
    assert inverse(CONFIG, *point, elbow) == pytest.approx((theta1, theta2, d3), abs=1e-9, rel=0.0)


def _inverse_accepts(x: float, y: float, z: float, elbow: Elbow) -> bool:
    try:
        inverse(CONFIG, x, y, z, elbow)
    except ScaraError:
        return False
    return True


@pytest.mark.parametrize("elbow", Elbow)
def test_clearly_reachable_never_claims_a_point_inverse_refuses(elbow: Elbow) -> None:
    """On a grid over and past the workspace, and on and just across each of its edges
    (reach, stroke, both joint limits): where it says yes, inverse says yes; and it says no
    only near an edge (the one by one check that follows it stays rare)."""
    rng = np.random.default_rng(5)
    points = [rng.uniform((-0.8, -0.8, CONFIG.z_min - 0.05), (0.8, 0.8, CONFIG.z_max + 0.05))
              for _ in range(20000)]  # fmt: skip
    for theta1 in np.linspace(CONFIG.theta1_min, CONFIG.theta1_max, 41):
        for theta2 in (CONFIG.theta2_min, 0.0, CONFIG.theta2_max):
            for nudge in (-1e-8, -CLEAR_MARGIN, 0.0, CLEAR_MARGIN, 1e-8):
                for z in (CONFIG.z_min + nudge, Z_MID, CONFIG.z_max + nudge):
                    points.append(np.array(forward(CONFIG, theta1 + nudge, theta2 + nudge, 0.0)))
                    points[-1][2] = z
    grid = np.array(points)
    claimed = clearly_reachable(CONFIG, grid[:, 0], grid[:, 1], grid[:, 2], elbow)
    accepted = np.array([_inverse_accepts(*point, elbow) for point in grid.tolist()])
    assert not (claimed & ~accepted).any(), grid[claimed & ~accepted][:5]
    assert np.array_equal(claimed[:20000], accepted[:20000])  # the random points: no edge cases


def test_clearly_reachable_says_no_to_nan() -> None:
    nan = np.array([math.nan])
    assert not clearly_reachable(CONFIG, nan, nan, nan).any()
