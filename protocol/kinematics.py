"""Kinematics of the RRP SCARA arm (paper section 2).

Pure functions on plain floats, written with :mod:`math` rather than numpy: they run on
every control tick (500-1000 Hz), where numpy's per-call overhead would dominate; only
:func:`clearly_reachable` takes arrays, to check a whole planned path at once, and
:func:`reaches` takes either (:mod:`protocol.ops`).

Angles are in radians and lengths in metres. ``theta2`` is the elbow angle relative to
link 1: ``theta2 = 0`` is the stretched arm and ``|theta2| = pi`` the folded one, the two
singularities of the planar Jacobian (``det J = a1 a2 sin theta2``).
"""

from __future__ import annotations

import math
from enum import Enum
from typing import Any, NamedTuple, TypeVar

import numpy as np
import numpy.typing as npt

from protocol.config import RobotConfig
from protocol.errors import JointLimitError, UnreachableError
from protocol.ops import ARRAY, SCALAR, Ops, Real

Values = TypeVar("Values", float, npt.NDArray[np.float64])
"""For :func:`tcp_velocity`: one state, or a whole log's arrays."""

# Round-off allowed on cos(theta2), z and the joint limits, so that points exactly on the
# workspace boundary (e.g. forward() of a joint limit) stay reachable; results are clamped.
_TOL = 1e-12

DAMPING_S2_REF = 0.1
"""``|sin theta2|`` below which :func:`joint_rates_for` damps (about 5.7 deg from a singularity)."""


class Elbow(Enum):
    """The inverse-kinematics branch; the value is the sign of ``theta2``.

    ``DOWN``: ``theta2 >= 0``, the paper's eq. 15 (``theta1 = phi - alpha``).
    ``UP``: ``theta2 <= 0`` (``theta1 = phi + alpha``). Both coincide at ``theta2 = 0``.
    """

    DOWN = 1
    UP = -1


class ArmTrig(NamedTuple):
    """The sines and cosines of theta1 and theta1 + theta2 that the arm's formulas share."""

    sin1: Real
    cos1: Real
    sin12: Real
    cos12: Real


def arm_trig(ops: Ops, theta1: Real, theta2: Real) -> ArmTrig:
    theta12 = theta1 + theta2
    return ArmTrig(ops.sin(theta1), ops.cos(theta1), ops.sin(theta12), ops.cos(theta12))


def tool_position(config: RobotConfig, trig: ArmTrig, d3: Real) -> tuple[Real, Real, Real]:
    """Tool position ``(x, y, z)`` (eq. 10), from the joints' :class:`ArmTrig` and ``d3``."""
    return (
        config.a1 * trig.cos1 + config.a2 * trig.cos12,
        config.a1 * trig.sin1 + config.a2 * trig.sin12,
        config.d0 - d3,
    )


def forward(
    config: RobotConfig, theta1: float, theta2: float, d3: float
) -> tuple[float, float, float]:
    """Tool position ``(x, y, z)`` for the joint values (eq. 10)."""
    return tool_position(config, arm_trig(SCALAR, theta1, theta2), d3)


def inverse(
    config: RobotConfig, x: float, y: float, z: float, elbow: Elbow = Elbow.DOWN
) -> tuple[float, float, float]:
    """Joint values ``(theta1, theta2, d3)`` putting the tool at ``(x, y, z)`` (eq. 17).

    Uses atan2 throughout, so every quadrant is right, unlike eq. 15's ``atan(y / x)``.
    ``theta1`` is normalised to ``(-pi, pi]``.

    Raises:
        UnreachableError: the point is outside the annulus ``|a1 - a2| <= r <= a1 + a2``
            or ``z`` is outside the stroke ``[d0 - d3_max, d0 - d3_min]``.
        JointLimitError: this elbow branch needs ``theta1`` or ``theta2`` beyond its limits.
    """
    a1, a2 = config.a1, config.a2
    if not config.z_min - _TOL <= z <= config.z_max + _TOL:
        raise UnreachableError(
            f"point ({x:.6g}, {y:.6g}, {z:.6g}) m is out of reach: z must lie in "
            f"[{config.z_min:.6g}, {config.z_max:.6g}] m"
        )
    c2 = (x * x + y * y - a1 * a1 - a2 * a2) / (2.0 * a1 * a2)
    if not abs(c2) <= 1.0 + _TOL:  # written so that NaN fails too
        raise UnreachableError(
            f"point ({x:.6g}, {y:.6g}, {z:.6g}) m is out of reach: planar radius "
            f"{math.hypot(x, y):.6g} m must lie in [{abs(a1 - a2):.6g}, {a1 + a2:.6g}] m"
        )
    c2 = _clip(c2, -1.0, 1.0)
    s2 = elbow.value * math.sqrt((1.0 - c2) * (1.0 + c2))
    theta2 = math.atan2(s2, c2)
    theta1 = math.remainder(math.atan2(y, x) - math.atan2(a2 * s2, a1 + a2 * c2), math.tau)
    if theta1 == -math.pi:
        theta1 = math.pi
    for name, value, low, high in (
        ("theta2", theta2, config.theta2_min, config.theta2_max),
        ("theta1", theta1, config.theta1_min, config.theta1_max),
    ):
        if not low - _TOL <= value <= high + _TOL:
            raise JointLimitError(
                f"point ({x:.6g}, {y:.6g}, {z:.6g}) m needs {name} = "
                f"{math.degrees(value):.3f} deg with elbow {elbow.name}, outside its limits "
                f"[{math.degrees(low):.3f}, {math.degrees(high):.3f}] deg"
            )
    return (
        _clip(theta1, config.theta1_min, config.theta1_max),
        _clip(theta2, config.theta2_min, config.theta2_max),
        _clip(config.d0 - z, config.d3_min, config.d3_max),
    )


CLEAR_MARGIN = 1e-9
"""How far inside every limit :func:`clearly_reachable` wants a point (rad, m, and on
cos theta2): far more than numpy's and :mod:`math`'s last-bit differences."""


def clearly_reachable(
    config: RobotConfig,
    x: npt.NDArray[np.float64],
    y: npt.NDArray[np.float64],
    z: npt.NDArray[np.float64],
    elbow: Elbow = Elbow.DOWN,
) -> npt.NDArray[np.bool_]:
    """Which points :func:`inverse` certainly accepts, CLEAR_MARGIN inside every limit it
    checks, for many points at once; ``False`` where it may refuse (ask it there)."""
    margin = CLEAR_MARGIN
    inside = (config.z_min + margin < z) & (z < config.z_max - margin)
    return np.asarray(inside & reaches(ARRAY, config, x, y, elbow.value, margin, margin))


def reaches(
    ops: Ops,
    config: RobotConfig,
    x: Real,
    y: Real,
    elbow: Real,
    margin: float,
    cos_margin: float = 0.0,
) -> Real:
    """Whether the arm reaches the plane point (x, y) with its elbow on the side ``elbow``
    (+1 as :attr:`Elbow.DOWN`, -1 as UP), theta1 and theta2 at least ``margin`` rad inside
    their limits and cos theta2 ``cos_margin`` inside +-1 (:func:`inverse`'s arithmetic, over
    :mod:`protocol.ops`: for the detours the control law checks on floats and the batch and
    the planner on arrays)."""
    a1, a2 = config.a1, config.a2
    c2 = (x * x + y * y - a1 * a1 - a2 * a2) / (2.0 * a1 * a2)
    inside = abs(c2) < 1.0 - cos_margin
    c2 = ops.clip(c2, -1.0, 1.0)
    s2 = elbow * ops.sqrt((1.0 - c2) * (1.0 + c2))
    theta2 = ops.atan2(s2, c2)
    theta1 = ops.atan2(y, x) - ops.atan2(a2 * s2, a1 + a2 * c2)
    theta1 = (theta1 + math.pi) % math.tau - math.pi  # the wrap near +-pi is left to inverse
    return (
        inside
        & (abs(theta1) < math.pi - margin)
        & (config.theta2_min + margin < theta2)
        & (theta2 < config.theta2_max - margin)
        & (config.theta1_min + margin < theta1)
        & (theta1 < config.theta1_max - margin)
    )


def jacobian_planar(
    config: RobotConfig, theta1: float, theta2: float
) -> tuple[float, float, float, float]:
    """``d(x, y) / d(theta1, theta2)`` as row-major ``(j11, j12, j21, j22)``."""
    return planar_jacobian(config, arm_trig(SCALAR, theta1, theta2))


def planar_jacobian(config: RobotConfig, trig: ArmTrig) -> tuple[Real, Real, Real, Real]:
    """:func:`jacobian_planar` from the joints' :class:`ArmTrig`."""
    a2s12 = config.a2 * trig.sin12
    a2c12 = config.a2 * trig.cos12
    return (-config.a1 * trig.sin1 - a2s12, -a2s12, config.a1 * trig.cos1 + a2c12, a2c12)


def tcp_velocity(
    config: RobotConfig,
    theta1: Values,
    theta2: Values,
    rate1: Values,
    rate2: Values,
    trig: Any = math,
) -> tuple[Values, Values]:
    """Planar tool velocity ``J(theta) (theta1_dot, theta2_dot)`` (eq. 10 differentiated).

    ``trig`` supplies ``sin`` and ``cos``: :mod:`math` for one state, :mod:`numpy` for the
    arrays of a whole log (the measures of a run).
    """
    theta12 = theta1 + theta2
    sines = ArmTrig(trig.sin(theta1), trig.cos(theta1), trig.sin(theta12), trig.cos(theta12))
    return tool_velocity(config, sines, rate1, rate2)


def tool_velocity(
    config: RobotConfig, trig: ArmTrig, rate1: Values, rate2: Values
) -> tuple[Values, Values]:
    """:func:`tcp_velocity` from the joints' :class:`ArmTrig`, which the law has already."""
    rate12 = rate1 + rate2
    return (
        -config.a1 * trig.sin1 * rate1 - config.a2 * trig.sin12 * rate12,
        config.a1 * trig.cos1 * rate1 + config.a2 * trig.cos12 * rate12,
    )


def joint_rates_for(
    config: RobotConfig,
    theta1: float,
    theta2: float,
    vx: float,
    vy: float,
    damping: float = 0.01,
) -> tuple[float, float]:
    """Joint rates ``(theta1_dot, theta2_dot)`` giving the planar tool velocity ``(vx, vy)``
    (:func:`joint_rates`)."""
    return joint_rates(SCALAR, config, theta2, arm_trig(SCALAR, theta1, theta2), vx, vy, damping)


def joint_rates(
    ops: Ops,
    config: RobotConfig,
    theta2: Real,
    trig: ArmTrig,
    vx: Real,
    vy: Real,
    damping: float,
) -> tuple[Real, Real]:
    """Joint rates ``(theta1_dot, theta2_dot)`` giving the planar tool velocity ``(vx, vy)``.

    Damped least squares, ``qdot = J^T (J J^T + lambda^2 I)^-1 v``, so the rates stay
    bounded (``|qdot| <= |v| / (2 lambda)``) through the stretched/folded-arm singularity.
    ``lambda^2 = damping^2 (1 - (s2 / s2_ref)^2)`` for ``|s2| < s2_ref`` (``s2 = sin theta2``,
    ``s2_ref =`` :data:`DAMPING_S2_REF`), else 0: elsewhere this is the exact inverse, and
    the damping fades in continuously. ``damping`` (lambda at the singularity) is in metres.

    For 2x2 ``J`` with ``d = det J = a1 a2 s2``, ``J^T adj(J J^T + lambda^2 I) = d adj(J) +
    lambda^2 J^T`` and ``det(J J^T + lambda^2 I) = d^2 + lambda^2 (|J|_F^2 + lambda^2)``;
    the closed form below uses these, which avoids the cancellation of forming ``J J^T``.
    """
    j11, j12, j21, j22 = planar_jacobian(config, trig)
    s2 = ops.sin(theta2)
    ratio = s2 / DAMPING_S2_REF
    lam2 = ops.where(abs(ratio) < 1.0, damping * damping * (1.0 - ratio * ratio), 0.0)
    det_j = config.a1 * config.a2 * s2
    denominator = det_j * det_j + lam2 * (j11 * j11 + j12 * j12 + j21 * j21 + j22 * j22 + lam2)
    return (
        (det_j * (j22 * vx - j12 * vy) + lam2 * (j11 * vx + j21 * vy)) / denominator,
        (det_j * (j11 * vy - j21 * vx) + lam2 * (j12 * vx + j22 * vy)) / denominator,
    )


def reach_radii(config: RobotConfig) -> tuple[float, float]:
    """Min and max planar radius reachable within the ``theta2`` limits.

    The radius ``hypot(a1 + a2 cos theta2, a2 sin theta2)`` falls as ``|theta2|`` goes
    from 0 to pi, so the extremes come from the largest and smallest allowed ``|theta2|``
    (a limit at or beyond pi gives ``|a1 - a2|``).
    """
    low, high = config.theta2_min, config.theta2_max
    least_bend = 0.0 if low <= 0.0 <= high else min(abs(low), abs(high))
    most_bend = min(max(abs(low), abs(high)), math.pi)
    return (_radius(config, most_bend), _radius(config, least_bend))


def _radius(config: RobotConfig, theta2: float) -> float:
    return math.hypot(config.a1 + config.a2 * math.cos(theta2), config.a2 * math.sin(theta2))


def _clip(value: float, low: float, high: float) -> float:
    return min(max(value, low), high)
