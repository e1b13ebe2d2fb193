"""The safety filter: the last word on every command the control law sends.

Whatever PT, AO, the coordinator and the output limits ask (``wanted``), the command sent is
the one nearest to it, in joint rates, that keeps two promises for the coming tick:

- **the barrier**: the TCP's distance h to the inflated obstacle, less ``safety_buffer``,
  shrinks no faster than :func:`approach_speed` allows, ``dh/dt = a . qdot >= -s(h)``, where
  ``a`` is h's gradient through the arm's Jacobian and ``s(h)`` is ``safety_rate`` times h,
  or less where the joints could not brake from that. h is the larger of the distance in the
  plane and the height above the obstacle's inflated top: the arm is safe when either is
  positive, and keeping the larger one from falling to zero keeps it so. From h >= 0 it
  falls at most exponentially, so it never reaches zero: the arm never enters the inflated
  obstacle (the buffer takes up what the drives' lag adds, ``docs/design.md``). The joints
  follow the command ``drive_lag`` late, and at fast joint rates the TCP's way bends: where
  it bends towards the obstacle, h falls faster than ``a . qdot`` says, by ``drive_lag``
  times the bend's share towards it, and the barrier asks that much more (its ``b``);
- **the box**: each joint rate within its speed limit, within one tick's acceleration of the
  last command, and moving towards its joint stop no faster than :func:`approach_speed`
  allows for the way left to STOP_MARGIN before it (the same promise for the joint stops).

The nearest such command solves a quadratic programme with one linear constraint and a box:
``qdot(l) = clip(u + l a, low, high)`` for the least ``l >= 0`` with ``a . qdot(l) >= b``
(``u``: ``wanted`` clipped into the box, ``b = -s(h)``). ``a . qdot(l)`` grows piecewise
linearly in ``l``, with a kink where each joint reaches its bound, and is concave, so the
least ``l`` is the largest of the values at which each piece, extended, reaches ``b``: a
closed form of a few dozen operations, the same on floats and arrays (:mod:`protocol.ops`).
Where even the best command of the box cannot keep the barrier (``a . qdot`` at its most is
below ``b``: the arm pinned at a joint stop against the obstacle, or already inside it) the
filter sends that best command and says so: the controller faults (``no_safe_motion``) and
brakes.
"""

from __future__ import annotations

import math
from typing import NamedTuple

from controller.obstacle import ObstacleMeasurement
from protocol.config import ControllerConfig, RobotConfig
from protocol.geometry import Section, nearest_to
from protocol.kinematics import ArmTrig, planar_jacobian
from protocol.ops import Mask, Ops, Real

Point3 = tuple[Real, Real, Real]

SLACK = 1.0 + 1e-9
"""The speed and acceleration limits as the box takes them: the law's output limits have
applied them already, up to the last bit of their rounding, which the box must not undo."""
BRAKING = 0.8
"""The share of the joints' acceleration limits the approach to a bound counts on to brake
with (:func:`approach_speed`)."""
STOP_MARGIN = (1e-3, 1e-3, 2e-4)
"""rad, rad, m: how far before each joint stop the approach to it aims. Aimed at the stop
itself, the exponential approach ends on it (the plant's joint-limit fault) once the
actuators' lag has had its say; at most 0.6 mm of the TCP's way."""


class Box(NamedTuple):
    """The joint rates allowed for the coming tick, per joint."""

    low: Point3
    high: Point3


class Barrier(NamedTuple):
    """The barrier constraint ``a . qdot >= b`` of one tick."""

    a: Point3
    b: Real


class Filtered(NamedTuple):
    """The command sent, and whether no command of the box keeps the barrier."""

    command: Point3
    no_safe_motion: Mask


class Limits(NamedTuple):
    """The box's fixed numbers, per joint (:func:`limits_of`)."""

    speed: Point3
    step: Point3
    """The most a joint's command may change in one tick."""
    decel: Point3
    """What the approach to a stop counts on to brake with."""
    far: Point3
    """Farther from a stop than this, the approach to it allows more than the speed limit."""
    low: Point3
    """The points the approach to each stop aims at."""
    high: Point3
    rate: float
    lag: float


def limits_of(robot: RobotConfig, config: ControllerConfig) -> Limits:
    """The box's numbers for ``robot`` under ``config``."""
    speed = tuple(SLACK * limit for limit in robot.speed_limits)
    step = tuple(SLACK * limit * config.period for limit in robot.accel_limits)
    decel = tuple(BRAKING * limit for limit in robot.accel_limits)
    rate, lag = config.limit_rate, config.drive_lag
    far = tuple(max(v / rate, v * lag + v * v / d) for v, d in zip(speed, decel, strict=True))
    low = tuple(stop + margin for stop, margin in zip(robot.joint_min, STOP_MARGIN, strict=True))
    high = tuple(stop - margin for stop, margin in zip(robot.joint_max, STOP_MARGIN, strict=True))
    return Limits(
        (speed[0], speed[1], speed[2]),
        (step[0], step[1], step[2]),
        (decel[0], decel[1], decel[2]),
        (far[0], far[1], far[2]),
        (low[0], low[1], low[2]),
        (high[0], high[1], high[2]),
        rate,
        lag,
    )


def box(ops: Ops, limits: Limits, joints: Point3, previous: Point3) -> Box:
    """The rates allowed: speed and acceleration limits first (the drives cannot do more),
    then the approach to the joint stops (:func:`approach_speed`), as far as those leave room
    for it."""
    low: list[Real] = []
    high: list[Real] = []
    rate, lag = limits.rate, limits.lag
    for joint in range(3):
        speed, step, last = limits.speed[joint], limits.step[joint], previous[joint]
        low_dynamic = ops.max(-speed, last - step)
        high_dynamic = ops.min(speed, last + step)
        far, decel = limits.far[joint], limits.decel[joint]
        low_way = joints[joint] - limits.low[joint]
        high_way = limits.high[joint] - joints[joint]
        low_stop = -ops.branch(low_way < far, approach_speed, speed, ops, low_way, rate, decel, lag)
        high_stop = ops.branch(
            high_way < far, approach_speed, speed, ops, high_way, rate, decel, lag
        )
        low.append(ops.clip(low_dynamic, low_stop, high_dynamic))
        high.append(ops.max(ops.min(high_dynamic, high_stop), low_dynamic))
    return Box((low[0], low[1], low[2]), (high[0], high[1], high[2]))


def approach_speed(ops: Ops, way: Real, rate: float, decel: Real, lag: float) -> Real:
    """The most a joint, or the TCP, may move towards a bound ``way`` ahead: ``rate`` times
    the way, and never more than it can stop from within the way braking at half of
    ``decel`` after drives that lag ``lag`` s (``way = v lag + v^2 / decel``). Where the two
    meet, following ``rate`` times the way asks for at most ``decel``. Past the bound (``way``
    below zero) it is brought back at ``rate``; with nothing to brake with (``decel`` 0) it
    may not move towards the bound at all."""
    half = 0.5 * decel
    braking = half > 0.0
    ahead = ops.max(way, 0.0)
    divisor = ops.where(braking, half, 1.0)
    brake = ops.where(braking, half * (ops.sqrt(lag * lag + 2.0 * ahead / divisor) - lag), 0.0)
    return ops.where(way >= 0.0, ops.min(rate * way, brake), rate * way)


def barrier(
    ops: Ops,
    robot: RobotConfig,
    config: ControllerConfig,
    section: Section,
    trig: ArmTrig,
    tcp: Point3,
    measurement: ObstacleMeasurement,
    rates: Point3,
) -> Barrier:
    """The barrier of the obstacle ``section`` (inflated) for the arm at ``tcp``: on the plane
    distance where that is the larger, else on the height above the top. ``measurement``
    (module DM's, this tick) gives the plane distance where DM measured it; above the top DM
    does not, and it is measured here. ``rates`` (the last command sent, which the joints
    still follow) give the bend of the TCP's way."""
    px, py, pz = tcp
    dx, dy = px - section.x, py - section.y
    reach = section.a + config.sensing_range
    unmeasured = (
        ops.not_(measurement.present) & (pz >= section.top) & (dx * dx + dy * dy < reach * reach)
    )
    # Beyond the sensing range the clearance allows more than any speed: no barrier.
    return ops.branch(
        measurement.present | unmeasured,
        _near_barrier,
        Barrier((0.0, 0.0, 0.0), -math.inf),
        ops,
        robot,
        config,
        section,
        trig,
        tcp,
        measurement,
        unmeasured,
        rates,
    )


def _near_barrier(
    ops: Ops,
    robot: RobotConfig,
    config: ControllerConfig,
    section: Section,
    trig: ArmTrig,
    tcp: Point3,
    measurement: ObstacleMeasurement,
    unmeasured: Mask,
    rates: Point3,
) -> Barrier:
    """:func:`barrier` within the sensing range of the obstacle."""
    px, py, pz = tcp
    clearance, to_x, to_y = ops.branch(
        unmeasured,
        _plane_clearance,
        (measurement.clearance, measurement.to_nearest[0], measurement.to_nearest[1]),
        ops,
        section,
        px,
        py,
    )
    gap = ops.sqrt(to_x * to_x + to_y * to_y)
    apart = gap > 0.0
    divisor = ops.where(apart, gap, 1.0)
    # h grows away from the boundary: against the way to it outside, along it inside.
    sign = ops.where(clearance < 0.0, 1.0, -1.0)
    normal_x = ops.where(apart, sign * to_x / divisor, 0.0)
    normal_y = ops.where(apart, sign * to_y / divisor, 0.0)
    j11, j12, j21, j22 = planar_jacobian(robot, trig)
    buffer = config.safety_buffer
    plane = clearance - buffer
    height = pz - section.top - buffer
    over = height > plane
    h = ops.where(over, height, plane)
    a = (
        ops.where(over, 0.0, normal_x * j11 + normal_y * j21),
        ops.where(over, 0.0, normal_x * j12 + normal_y * j22),
        ops.where(over, -1.0, 0.0),  # z = d0 - d3
    )
    # How hard the joints can brake the TCP's approach: each at BRAKING of its limit.
    accel = robot.accel_limits
    decel = BRAKING * (abs(a[0]) * accel[0] + abs(a[1]) * accel[1] + abs(a[2]) * accel[2])
    # The bend: at constant joint rates the TCP accelerates towards the base axis and the
    # elbow (each link's centripetal pull, -rate^2 times the link, the links read off the
    # Jacobian). Its share towards the obstacle, over the drives' lag, is what h loses beyond
    # a . qdot while the joints catch up with the command (module docstring).
    rate12 = rates[0] + rates[1]
    pull = rates[0] * rates[0] * (normal_x * (j21 - j22) + normal_y * (j12 - j11))
    pull = pull + rate12 * rate12 * (normal_x * j22 - normal_y * j12)
    inward = ops.where(over, 0.0, ops.max(pull, 0.0))
    lag = config.drive_lag
    return Barrier(a, lag * inward - approach_speed(ops, h, config.safety_rate, decel, lag))


def _plane_clearance(ops: Ops, section: Section, px: Real, py: Real) -> tuple[Real, Real, Real]:
    """The signed plane distance from (px, py) to ``section`` and the way to its nearest
    point."""
    clearance, nearest_x, nearest_y = nearest_to(ops, section, px, py)
    return clearance, nearest_x - px, nearest_y - py


def filtered(ops: Ops, wanted: Point3, allowed: Box, constraint: Barrier) -> Filtered:
    """The command nearest ``wanted`` inside ``allowed`` that keeps ``constraint``, or the
    box's best for the barrier where none does (module docstring)."""
    low, high = allowed
    u = (
        ops.clip(wanted[0], low[0], high[0]),
        ops.clip(wanted[1], low[1], high[1]),
        ops.clip(wanted[2], low[2], high[2]),
    )
    a = constraint.a
    need = constraint.b - (a[0] * u[0] + a[1] * u[1] + a[2] * u[2])
    return ops.branch(
        need > 0.0, _pushed, Filtered(u, ops.full(need, False)), ops, u, a, low, high, need
    )


def _pushed(ops: Ops, u: Point3, a: Point3, low: Point3, high: Point3, need: Real) -> Filtered:
    """:func:`filtered` where ``u`` breaks the barrier by ``need``: the least push ``l a``."""
    # How far l may go before joint i reaches its bound, and how much a . qdot gains per l.
    reach: list[Real] = []
    weight: list[Real] = []
    for joint in range(3):
        aj = a[joint]
        moving = aj != 0.0
        bound = ops.where(aj > 0.0, high[joint], low[joint])
        reach.append(ops.where(moving, (bound - u[joint]) / ops.where(moving, aj, 1.0), 0.0))
        weight.append(aj * aj)
    full = weight[0] * reach[0] + weight[1] * reach[1] + weight[2] * reach[2]
    feasible = need <= full
    # The piece of a . qdot(l) that starts at kink k (k = 0: at l = 0) reaches ``need`` at
    # l_k + (need - gain_k) / slope_k; by concavity the least l is the largest of these.
    push: Real = 0.0
    for start in (0.0, reach[0], reach[1], reach[2]):
        gain = (
            weight[0] * ops.min(start, reach[0])
            + weight[1] * ops.min(start, reach[1])
            + weight[2] * ops.min(start, reach[2])
        )
        slope = (
            weight[0] * (reach[0] > start)
            + weight[1] * (reach[1] > start)
            + weight[2] * (reach[2] > start)
        )
        sloped = slope > 0.0
        at = start + (need - gain) / ops.where(sloped, slope, 1.0)
        push = ops.where(sloped, ops.max(push, at), push)
    push = ops.where(feasible, push, ops.max(ops.max(reach[0], reach[1]), reach[2]))
    command = (
        u[0] + ops.min(push, reach[0]) * a[0],
        u[1] + ops.min(push, reach[1]) * a[1],
        u[2] + ops.min(push, reach[2]) * a[2],
    )
    return Filtered(command, ops.not_(feasible))
