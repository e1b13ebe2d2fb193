"""The joint model the plant simulator integrates: pure, no bus, no clock.

Each joint follows its velocity command through a first-order actuator lag (time constant
``time_constant``), saturated at the joint's speed and acceleration limits. The joint
limits are hard stops: a joint that reaches one stops there and the model reports a fault.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from protocol.config import PlantConfig, RobotConfig
from protocol.messages import Joints


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
        h = dt / self.config.substeps
        blend = 1.0 - math.exp(-h / self.config.time_constant)
        low, high = self.robot.joint_min, self.robot.joint_max
        speed, accel = self.robot.speed_limits, self.robot.accel_limits
        position = list(self.position)
        velocity = list(self.velocity)
        at_limit = list(self.at_limit)
        for _ in range(self.config.substeps):
            for joint in range(3):
                target = min(max(command[joint], -speed[joint]), speed[joint])
                change = (target - velocity[joint]) * blend
                max_change = accel[joint] * h
                change = min(max(change, -max_change), max_change)
                new_velocity = velocity[joint] + change
                new_position = position[joint] + 0.5 * (velocity[joint] + new_velocity) * h
                if new_position < low[joint] or new_position > high[joint]:
                    new_position = min(max(new_position, low[joint]), high[joint])
                    new_velocity = 0.0
                    at_limit[joint] = True
                position[joint] = new_position
                velocity[joint] = new_velocity
        self.position = (position[0], position[1], position[2])
        self.velocity = (velocity[0], velocity[1], velocity[2])
        self.at_limit = (at_limit[0], at_limit[1], at_limit[2])
