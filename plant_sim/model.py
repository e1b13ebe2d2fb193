"""The joint model the plant simulator integrates: pure, no bus, no clock.

Each joint follows its velocity command through a first-order actuator lag (time constant
``time_constant``), saturated at the joint's speed and acceleration limits. The joint
limits are hard stops: a joint that reaches one stops there and the model reports a fault.
:func:`integrate` is the model, written once over :mod:`protocol.ops`: :class:`PlantModel`
runs it for the plant process (one arm) and ``sim/batch.py`` for the study (many runs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from protocol.config import PlantConfig, RobotConfig
from protocol.messages import Joints
from protocol.ops import SCALAR, Mask, Ops, Real


@dataclass(slots=True)
class PlantModel:
    """Joint positions and velocities of the arm, advanced by :meth:`advance`."""

    robot: RobotConfig
    config: PlantConfig
    position: Joints
    velocity: Joints = (0.0, 0.0, 0.0)
    at_limit: tuple[bool, bool, bool] = field(default=(False, False, False))

    def advance(self, command: Joints, dt: float) -> None:
        """Integrate ``dt`` seconds under the joint velocity ``command``."""
        substep = dt / self.config.substeps
        blend = 1.0 - math.exp(-substep / self.config.time_constant)
        joints = [
            integrate(
                SCALAR,
                self.position[joint],
                self.velocity[joint],
                command[joint],
                (
                    self.robot.speed_limits[joint],
                    self.robot.accel_limits[joint] * substep,
                    self.robot.joint_min[joint],
                    self.robot.joint_max[joint],
                ),
                blend,
                substep,
                self.config.substeps,
            )
            for joint in range(3)
        ]
        self.position = (joints[0][0], joints[1][0], joints[2][0])
        self.velocity = (joints[0][1], joints[1][1], joints[2][1])
        self.at_limit = (
            self.at_limit[0] or joints[0][2],
            self.at_limit[1] or joints[1][2],
            self.at_limit[2] or joints[2][2],
        )


def integrate(
    ops: Ops,
    position: Real,
    velocity: Real,
    command: Real,
    limits: tuple[Real, Real, Real, Real],
    blend: float,
    substep: float,
    substeps: int,
) -> tuple[Real, Real, Mask]:
    """A joint's position and velocity after ``substeps`` steps of ``substep`` s under
    ``command``, and whether it hit a joint limit meanwhile. ``limits``: the speed limit, the
    most the speed may change in a substep, and the joint's low and high limits; ``blend``:
    the share of the way to the command the actuator's lag covers in a substep."""
    speed, max_change, low, high = limits
    target = ops.min(ops.max(command, -speed), speed)
    at_limit: Mask = False
    for _ in range(substeps):
        change = ops.min(ops.max((target - velocity) * blend, -max_change), max_change)
        new_velocity = velocity + change
        new_position = position + 0.5 * (velocity + new_velocity) * substep
        stopped = (new_position < low) | (new_position > high)
        if ops.any(stopped):
            new_position = ops.where(
                stopped, ops.min(ops.max(new_position, low), high), new_position
            )
            new_velocity = ops.where(stopped, 0.0, new_velocity)
            at_limit = at_limit | stopped
        position, velocity = new_position, new_velocity
    return position, velocity, at_limit
