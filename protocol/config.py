"""The typed, validated configurations a run is made of: the robot, the controller's gains and
rate, and the plant model. Every value is checked when built, and an error names its field
(``robot.a1``, ``controller.rate_hz``, ...); a scenario carries one of each."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

from protocol.errors import ConfigError


@dataclass(frozen=True, slots=True)
class RobotConfig:
    """Geometry and joint limits of an RRP SCARA (defaults: a Cobra600 / HS-class arm).

    Lengths in metres, angles in radians, speeds in rad/s or m/s, accelerations in
    rad/s^2 or m/s^2. ``d0`` is the height of joint 1 above the base; the tool is at
    ``z = d0 - d3``.
    """

    a1: float = 0.325
    a2: float = 0.275
    d0: float = 0.387
    d3_min: float = 0.0
    d3_max: float = 0.200
    theta1_min: float = math.radians(-150.0)
    theta1_max: float = math.radians(150.0)
    theta2_min: float = math.radians(-145.0)
    theta2_max: float = math.radians(145.0)
    speed_limit_theta1: float = 7.85
    speed_limit_theta2: float = 12.5
    speed_limit_d3: float = 1.0
    accel_limit_theta1: float = 40.0
    accel_limit_theta2: float = 60.0
    accel_limit_d3: float = 10.0

    def __post_init__(self) -> None:
        for spec in fields(self):
            value = getattr(self, spec.name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(f"robot.{spec.name}", f"must be a finite number, got {value!r}")
        for name in ("a1", "a2", "d0"):
            if getattr(self, name) <= 0.0:
                raise ConfigError(f"robot.{name}", "must be positive")
        for low, high in (
            ("d3_min", "d3_max"),
            ("theta1_min", "theta1_max"),
            ("theta2_min", "theta2_max"),
        ):
            if getattr(self, low) >= getattr(self, high):
                raise ConfigError(f"robot.{low}", f"must be below robot.{high}")
        if self.d3_max > self.d0:
            raise ConfigError("robot.d3_max", "the tool cannot go below the base (d3_max > d0)")
        for name in (
            "speed_limit_theta1",
            "speed_limit_theta2",
            "speed_limit_d3",
            "accel_limit_theta1",
            "accel_limit_theta2",
            "accel_limit_d3",
        ):
            if getattr(self, name) <= 0.0:
                raise ConfigError(f"robot.{name}", "must be positive")

    @property
    def joint_min(self) -> tuple[float, float, float]:
        return (self.theta1_min, self.theta2_min, self.d3_min)

    @property
    def joint_max(self) -> tuple[float, float, float]:
        return (self.theta1_max, self.theta2_max, self.d3_max)

    @property
    def speed_limits(self) -> tuple[float, float, float]:
        return (self.speed_limit_theta1, self.speed_limit_theta2, self.speed_limit_d3)

    @property
    def accel_limits(self) -> tuple[float, float, float]:
        return (self.accel_limit_theta1, self.accel_limit_theta2, self.accel_limit_d3)

    @property
    def z_min(self) -> float:
        return self.d0 - self.d3_max

    @property
    def z_max(self) -> float:
        return self.d0 - self.d3_min

    @classmethod
    def from_mapping(cls, values: dict[str, Any], *, degrees: bool = True) -> RobotConfig:
        """Build from a scenario table; angles there are in degrees (``*_deg`` keys)."""
        known = {spec.name for spec in fields(cls)}
        kwargs: dict[str, float] = {}
        for key, value in values.items():
            name = key.removesuffix("_deg") if degrees and key.endswith("_deg") else key
            if name not in known:
                raise ConfigError(f"robot.{key}", "unknown parameter")
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                raise ConfigError(f"robot.{key}", f"must be a number, got {value!r}")
            kwargs[name] = math.radians(value) if key.endswith("_deg") else float(value)
        return cls(**kwargs)


MIN_RATE_HZ = 100.0
"""Below this a single lost command would let the plant's 20 ms brake fire between two ticks."""
MAX_RATE_HZ = 1000.0
"""Above this the wire's worst-case load passes half of 1 Mbit/s, and a command's round trip
over the portable transport (p99 about 0.5 ms) no longer fits in a tick."""


@dataclass(frozen=True, slots=True)
class ControllerConfig:
    """Everything the control law is tuned by (SI units; rates in Hz).

    PT tracks the planned cubic with a unicycle law (see ``behaviours.plan_tracking``): the
    speed is the planned speed plus ``position_gain`` times the lag along the path, and the
    heading aims back at the path with ``heading_gain``; speed is capped at ``speed_max``.
    AO is the paper's eq. 28-29 with
    ``f_vA(s) = ao_speed_min + (ao_speed_max - ao_speed_min) tanh(max(s, 0) / ao_speed_distance)``
    and ``f_omegaA(s) = ao_turn_max tanh(s / ao_turn_scale)``, steering at the edge of the
    obstacle grown by ``ao_pass_margin``. Whatever the blend, the TCP never moves towards the
    obstacle's margin faster than ``approach_rate`` times its clearance (see
    ``ControlLaw._approach_limited``), nor outwards faster than ``reach_rate`` times its
    distance from the arm's full reach (``ControlLaw._reach_limited``).
    """

    rate_hz: float = 500.0
    position_gain: float = 10.0
    heading_gain: float = 15.0
    height_gain: float = 10.0
    speed_max: float = 0.6
    ao_speed_max: float = 0.25
    ao_speed_min: float = 0.05
    ao_speed_distance: float = 0.03
    ao_turn_max: float = 20.0
    ao_turn_scale: float = 4.0
    ao_pass_margin: float = 0.015
    sensing_range: float = 0.2
    switch_distance: float = 0.05
    damping: float = 0.01
    approach_rate: float = 5.0
    reach_rate: float = 10.0

    def __post_init__(self) -> None:
        for spec in fields(self):
            value = getattr(self, spec.name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ConfigError(
                    f"controller.{spec.name}", f"must be a finite number >= 0, got {value!r}"
                )
        if not MIN_RATE_HZ <= self.rate_hz <= MAX_RATE_HZ:
            raise ConfigError(
                "controller.rate_hz",
                f"must be between {MIN_RATE_HZ:g} and {MAX_RATE_HZ:g} Hz, got {self.rate_hz:g}",
            )
        if self.ao_speed_min > self.ao_speed_max:
            raise ConfigError("controller.ao_speed_min", "must not exceed ao_speed_max")
        for name in (
            "ao_speed_distance",
            "ao_turn_scale",
            "sensing_range",
            "position_gain",
            "approach_rate",
            "reach_rate",
        ):
            if getattr(self, name) <= 0.0:
                raise ConfigError(f"controller.{name}", "must be positive")

    @property
    def period(self) -> float:
        return 1.0 / self.rate_hz

    @classmethod
    def from_mapping(cls, values: dict[str, Any]) -> ControllerConfig:
        known = {spec.name for spec in fields(cls)}
        for key, value in values.items():
            if key not in known:
                raise ConfigError(f"controller.{key}", "unknown parameter")
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"controller.{key}", f"must be a number, got {value!r}")
        return cls(**{key: float(value) for key, value in values.items()})


@dataclass(frozen=True, slots=True)
class PlantConfig:
    """Actuator lag (s) and how many integration substeps one step is split into."""

    time_constant: float = 0.008
    substeps: int = 4

    def __post_init__(self) -> None:
        if not math.isfinite(self.time_constant) or self.time_constant <= 0.0:
            raise ConfigError("plant.time_constant", "must be a positive number of seconds")
        if not isinstance(self.substeps, int) or not 1 <= self.substeps <= 100:
            raise ConfigError("plant.substeps", "must be an integer from 1 to 100")
