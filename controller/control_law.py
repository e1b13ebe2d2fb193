"""One control step: measure, behave, coordinate, map to joints, limit (Fig. 6 end to end).

:class:`ControlLaw` is pure in the simple-pid sense: it owns the few values a controller
must remember between ticks (the unicycle heading, the TL/TR choice, the last command) and
is handed the time and the measured joints; it knows nothing of buses or clocks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from controller.behaviours import STOP, Command, avoid_obstacle, choose_side, plan_tracking
from controller.coordination import AHEAD_NONE, Coordinator, make_coordinator, smoothstep
from controller.obstacle import ObstacleMeasurement, measure
from controller.planner import Trajectory, plan_of
from protocol.config import ControllerConfig, RobotConfig
from protocol.geometry import EllipticCylinder, wrap_angle
from protocol.kinematics import forward, joint_rates_for
from protocol.scenario import Scenario

GOAL_HANDOVER = 0.5
"""s: how long before a waypoint's time DM starts looking towards the one after it."""


@dataclass(frozen=True, slots=True)
class ControlOutput:
    """The joint velocity command of one tick and what led to it (for logs and figures)."""

    command: tuple[float, float, float]
    tcp: tuple[float, float, float]
    reference: tuple[float, float, float]
    reference_speed: float
    measurement: ObstacleMeasurement
    tracking: Command
    avoiding: Command
    k_t: float
    k_c: float
    blended: Command
    heading: float
    limited: bool


class ControlLaw:
    """The controller's law for one scenario: call :meth:`step` once per tick."""

    def __init__(
        self,
        robot: RobotConfig,
        config: ControllerConfig,
        trajectory: Trajectory,
        obstacle: EllipticCylinder | None,
        coordinator: Coordinator,
    ) -> None:
        self.robot = robot
        self.config = config
        self.trajectory = trajectory
        self.obstacle = obstacle
        self._aim = obstacle.grown(config.ao_pass_margin) if obstacle is not None else None
        self.coordinator = coordinator
        self.period = config.period
        self._speed_limits = robot.speed_limits
        self._step_limits = tuple(limit * self.period for limit in robot.accel_limits)
        self.reset()

    @classmethod
    def for_scenario(cls, scenario: Scenario) -> ControlLaw:
        """The law of ``scenario``: its robot, gains, plan, obstacle and coordination mode."""
        config = scenario.controller
        return cls(
            scenario.robot,
            config,
            plan_of(scenario),
            scenario.obstacle,
            make_coordinator(scenario.mode, config.switch_distance, config.sensing_range),
        )

    def reset(self) -> None:
        """Back to the state before the first tick."""
        points = self.trajectory.points
        self.heading = math.atan2(points[1][1] - points[0][1], points[1][0] - points[0][0])
        self.side = 0
        self.previous_command: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def resume_from_rest(self) -> None:
        """Take up control again after zero was commanded (a hold): the next command ramps up
        from zero within the acceleration limit instead of jumping back to the last one."""
        self.previous_command = (0.0, 0.0, 0.0)

    def step(self, t: float, joint_position: tuple[float, float, float]) -> ControlOutput:
        config = self.config
        theta1, theta2, d3 = joint_position
        tcp = forward(self.robot, theta1, theta2, d3)
        reference, reference_velocity, reference_acceleration = self.trajectory.evaluate(t)
        measurement = measure(self.obstacle, tcp, self._goal(t), config.sensing_range)

        tracking = plan_tracking(
            config,
            self.heading,
            (tcp[0], tcp[1]),
            (reference[0], reference[1]),
            (reference_velocity[0], reference_velocity[1]),
            (reference_acceleration[0], reference_acceleration[1]),
        )
        avoiding = self._avoid(measurement, (tcp[0], tcp[1]))
        k_t, k_c = self.coordinator.weights(measurement)
        total = k_t + k_c
        blended = Command(
            (k_t * tracking.v + k_c * avoiding.v) / total,
            (k_t * tracking.omega + k_c * avoiding.omega) / total,
        )

        vx = blended.v * math.cos(self.heading)
        vy = blended.v * math.sin(self.heading)
        vz = reference_velocity[2] + config.height_gain * (reference[2] - tcp[2])
        rate1, rate2 = joint_rates_for(self.robot, theta1, theta2, vx, vy, config.damping)
        command, limited = self._limit((rate1, rate2, -vz))

        self.heading = wrap_angle(self.heading + blended.omega * self.period)
        self.previous_command = command
        return ControlOutput(
            command=command,
            tcp=tcp,
            reference=(reference[0], reference[1], reference[2]),
            reference_speed=math.hypot(reference_velocity[0], reference_velocity[1]),
            measurement=measurement,
            tracking=tracking,
            avoiding=avoiding,
            k_t=k_t,
            k_c=k_c,
            blended=blended,
            heading=self.heading,
            limited=limited,
        )

    def _goal(self, t: float) -> tuple[float, float]:
        """The next waypoint p_j that DM looks towards.

        Over the last GOAL_HANDOVER of a segment (at most half of it) the point slides from
        p_j to p_j+1, so that the direction DM measures from does not jump when the plan
        moves on to the next segment.
        """
        trajectory = self.trajectory
        index = trajectory.segment_index(t)
        goal = trajectory.points[index]
        if index + 1 >= len(trajectory.points):
            return (goal[0], goal[1])
        end = trajectory.times[index]
        handover = min(GOAL_HANDOVER, (end - trajectory.times[index - 1]) / 2.0)
        share = smoothstep((t - end + handover) / handover)
        following = trajectory.points[index + 1]
        return (
            goal[0] + share * (following[0] - goal[0]),
            goal[1] + share * (following[1] - goal[1]),
        )

    def _avoid(self, measurement: ObstacleMeasurement, position: tuple[float, float]) -> Command:
        """AO with its TL/TR choice, held while the obstacle is ahead (or the TCP inside)."""
        if (
            self._aim is None
            or not measurement.present
            or (measurement.ahead <= AHEAD_NONE and measurement.clearance > 0.0)
        ):
            self.side = 0
            return STOP
        if self.side == 0:
            self.side = choose_side(measurement)
        return avoid_obstacle(
            self.config, self._aim, measurement, self.side, self.heading, position
        )

    def _limit(self, wanted: tuple[float, float, float]) -> tuple[tuple[float, float, float], bool]:
        """Joint speed, then acceleration limits, each by one common scale factor.

        Scaling all joints together keeps the direction the TCP moves in (speed limit) and the
        direction of the change (acceleration limit), unlike clipping each joint on its own.
        """
        scale = 1.0
        for rate, limit in zip(wanted, self._speed_limits, strict=True):
            if abs(rate) * scale > limit:
                scale = limit / abs(rate)
        step_scale = 1.0
        for rate, previous, limit in zip(
            wanted, self.previous_command, self._step_limits, strict=True
        ):
            change = abs(rate * scale - previous)
            if change * step_scale > limit:
                step_scale = limit / change
        command = (
            self.previous_command[0] + (wanted[0] * scale - self.previous_command[0]) * step_scale,
            self.previous_command[1] + (wanted[1] * scale - self.previous_command[1]) * step_scale,
            self.previous_command[2] + (wanted[2] * scale - self.previous_command[2]) * step_scale,
        )
        return command, scale < 1.0 or step_scale < 1.0
