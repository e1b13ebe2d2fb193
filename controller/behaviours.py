"""The two behaviours of the paper's Fig. 5: PT (planning trajectory) and AO (avoiding
obstacle, made of TL and TR), each giving a unicycle command (v, omega) for the TCP.

The TCP is steered in the XY plane like a unicycle with a virtual heading phi
(x' = v cos phi, y' = v sin phi, phi' = omega), as the paper's (v, omega) commands imply.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from controller.obstacle import ObstacleMeasurement
from protocol.config import ControllerConfig
from protocol.geometry import EllipticCylinder, length, wrap_angle

TURN_LEFT = 1
TURN_RIGHT = -1
PLANNED_REST_SPEED = 0.005
"""m/s: below this the plan is taken to stand still and PT aims at the planned point."""
AHEAD_SPEED_FRACTION = 0.25
"""A TCP ahead of the moving plan slows down to this fraction of the planned speed."""


@dataclass(frozen=True, slots=True)
class Command:
    """A unicycle command: speed along the heading (m/s) and turn rate (rad/s, CCW > 0)."""

    v: float
    omega: float


STOP = Command(0.0, 0.0)


def plan_tracking(
    config: ControllerConfig,
    heading: float,
    position: tuple[float, float],
    reference: tuple[float, float],
    reference_velocity: tuple[float, float],
    reference_acceleration: tuple[float, float],
) -> Command:
    """PT: follow the planned point; eq. 26's (v_T, omega_T).

    The wanted velocity is the plan's plus ``position_gain`` times the position error, split
    along and across the planned direction of travel; the TCP steers to its direction and
    moves at its size (so an arm beside a plan that slows down or waits still closes the
    gap). Along, it is never below AHEAD_SPEED_FRACTION of the planned speed: a TCP ahead of
    the plan (AO may drive it faster than planned) lets the plan catch up at a crawl rather
    than turning round, or standing still while the plan moves. The plan's own turn rate is
    fed forward. Where the plan is at rest the heading simply aims at the planned point.
    """
    error_x, error_y = reference[0] - position[0], reference[1] - position[1]
    vx, vy = reference_velocity
    planned_speed = length(vx, vy)
    if planned_speed < PLANNED_REST_SPEED:
        distance = length(error_x, error_y)
        if distance < 1e-9:
            return STOP
        error = wrap_angle(math.atan2(error_y, error_x) - heading)
        speed = min(config.position_gain * distance, config.speed_max)
        return Command(speed * max(math.cos(error), 0.0), config.heading_gain * error)
    along_x, along_y = vx / planned_speed, vy / planned_speed
    lag = error_x * along_x + error_y * along_y
    offset = along_x * error_y - along_y * error_x
    along = max(planned_speed + config.position_gain * lag, AHEAD_SPEED_FRACTION * planned_speed)
    across = config.position_gain * offset
    speed = min(length(along, across), config.speed_max)
    target = math.atan2(vy, vx) + math.atan2(across, along)
    ax, ay = reference_acceleration
    feedforward = (vx * ay - vy * ax) / (planned_speed * planned_speed)
    error = wrap_angle(target - heading)
    return Command(speed * max(math.cos(error), 0.0), feedforward + config.heading_gain * error)


def choose_side(measurement: ObstacleMeasurement) -> int:
    """AO's choice between TL and TR: away from the side the obstacle is nearer on."""
    return TURN_LEFT if measurement.d_left >= measurement.d_right else TURN_RIGHT


def avoid_obstacle(
    config: ControllerConfig,
    aim: EllipticCylinder,
    measurement: ObstacleMeasurement,
    side: int,
    heading: float,
    position: tuple[float, float],
) -> Command:
    """AO (TL when ``side`` is +1, TR when -1): eq. 28-29.

    v_A = f_vA(min(d_L, d_R) cos beta), omega_A = f_omegaA(sin beta / min(d_L, d_R)) times the
    side. Here beta is taken from the heading to the chosen edge of ``aim``, the obstacle
    grown by ``config.ao_pass_margin``: while PT drives, the heading points at p_j and this
    is the paper's beta; once AO has turned the TCP, measuring from the heading makes AO
    settle on the tangent (pure pursuit: curvature 2 sin beta / d) instead of turning
    without end.
    """
    if not measurement.present:
        return STOP
    px, py = position
    edge_angle = _edge_direction(aim, side, px, py)
    beta = side * wrap_angle(edge_angle - heading)
    distance = max(measurement.min_distance, 1e-3)
    along = distance * math.cos(beta)
    v = config.ao_speed_min + (config.ao_speed_max - config.ao_speed_min) * math.tanh(
        max(along, 0.0) / config.ao_speed_distance
    )
    omega = config.ao_turn_max * math.tanh(math.sin(beta) / distance / config.ao_turn_scale)
    return Command(v, side * omega)


def _edge_direction(aim: EllipticCylinder, side: int, px: float, py: float) -> float:
    """Direction from the TCP to the chosen edge of ``aim``.

    Inside ``aim`` there is no tangent: go along the boundary through the TCP, on the
    chosen side, tilted outwards by how deep the TCP is.
    """
    edges = aim.tangent_points(px, py)
    if edges is not None:
        edge = edges[0] if side == TURN_LEFT else edges[1]
        return math.atan2(edge[1] - py, edge[0] - px)
    depth, nearest = aim.nearest_point(px, py)
    normal_x, normal_y = nearest[0] - px, nearest[1] - py
    if depth >= 0.0:
        normal_x, normal_y = -normal_x, -normal_y
    if normal_x == 0.0 and normal_y == 0.0:
        normal_x, normal_y = px - aim.x, py - aim.y
    along_boundary = math.atan2(normal_y, normal_x) - side * math.pi / 2.0
    tilt = min(1.0, abs(depth) / max(aim.inflation, 1e-3)) * math.pi / 4.0
    return along_boundary + side * tilt
