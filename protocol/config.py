"""The robot's parameters: one typed, validated configuration (DESIGN.md section 2)."""

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
