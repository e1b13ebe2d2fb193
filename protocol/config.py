"""The typed, validated configurations a run is made of: the robot, the controller's gains and
rate, and the plant model. Every value is checked when built, against the table of a scenario
file that the schema defines (``definitions.schema.json``: finite, positive, ranges) and then
for what a schema cannot say (a minimum below its maximum, ...); an error names its field
(``robot.a1``, ``controller.rate_hz``, ...). A scenario carries one of each."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from functools import lru_cache
from typing import Any, Final

from protocol.errors import ConfigError
from protocol.validation import check, shipped_schemas

_TABLES: Final = "definitions.schema.json#/$defs/"
"""Where the schema of each table (``robot``, ``controller``, ``plant``) is."""
_ANGLES: Final = ("theta1_min", "theta1_max", "theta2_min", "theta2_max")
"""Fields in radians, which a scenario file gives in degrees (``theta1_min_deg``)."""


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
        _check_table("robot", self.table())
        for low, high in (
            ("d3_min", "d3_max"),
            ("theta1_min", "theta1_max"),
            ("theta2_min", "theta2_max"),
        ):
            if getattr(self, low) >= getattr(self, high):
                raise ConfigError(f"robot.{low}", f"must be below robot.{high}")
        if self.d3_max > self.d0:
            raise ConfigError("robot.d3_max", "the tool cannot go below the base (d3_max > d0)")

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

    def table(self) -> dict[str, float]:
        """This robot as a scenario file's ``[robot]`` table: angles in degrees (``*_deg``)."""
        return {
            (f"{spec.name}_deg" if spec.name in _ANGLES else spec.name): (
                math.degrees(value) if spec.name in _ANGLES else value
            )
            for spec, value in ((spec, getattr(self, spec.name)) for spec in fields(self))
        }

    @classmethod
    def from_table(cls, table: Mapping[str, Any]) -> RobotConfig:
        """From a scenario file's ``[robot]`` table that fits its schema (angles in degrees)."""
        return cls(
            **{
                key.removesuffix("_deg"): math.radians(value)
                if key.endswith("_deg")
                else float(value)
                for key, value in table.items()
            }
        )


_RATE_HZ: Final = shipped_schemas()["definitions"]["$defs"]["controller"]["properties"]["rate_hz"]
MIN_RATE_HZ: Final = float(_RATE_HZ["minimum"])
"""The lowest control rate (the schema of ``controller.rate_hz`` says why)."""
MAX_RATE_HZ: Final = float(_RATE_HZ["maximum"])
"""The highest control rate (the schema of ``controller.rate_hz`` says why)."""


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
    distance from the arm's full reach (``ControlLaw._reach_limited``). Last, the safety
    filter (``controller/safety.py``) keeps the TCP's clearance to the inflated obstacle, less
    ``safety_buffer``, from falling faster than ``safety_rate`` times itself, and each joint
    from nearing its stop faster than ``limit_rate`` times the way left or than it can brake
    from, after drives that lag by up to ``drive_lag`` (s).
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
    safety_rate: float = 10.0
    safety_buffer: float = 0.001
    limit_rate: float = 20.0
    drive_lag: float = 0.01

    def __post_init__(self) -> None:
        _check_table("controller", asdict(self))
        if self.ao_speed_min > self.ao_speed_max:
            raise ConfigError("controller.ao_speed_min", "must not exceed ao_speed_max")

    @property
    def period(self) -> float:
        return 1.0 / self.rate_hz

    @classmethod
    def from_table(cls, table: Mapping[str, Any]) -> ControllerConfig:
        """From a scenario file's ``[controller]`` table that fits its schema."""
        return cls(**{key: float(value) for key, value in table.items()})


@dataclass(frozen=True, slots=True)
class PlantConfig:
    """Actuator lag (s) and how many integration substeps one step is split into."""

    time_constant: float = 0.008
    substeps: int = 4

    def __post_init__(self) -> None:
        _check_table("plant", asdict(self))


def _check_table(name: str, table: Mapping[str, Any]) -> None:
    """Check a configuration, as table ``name`` of a scenario file, against its schema."""
    _check_typed_items(name, tuple((key, type(value), value) for key, value in table.items()))


@lru_cache(maxsize=256)
def _check_typed_items(name: str, items: tuple[tuple[str, type, Any], ...]) -> None:
    """Cached, as a check takes about a millisecond and a study builds thousands of equal
    configurations (the generator's, each variant's); the types are part of the key, as 4.0
    equals 4 but is no integer."""
    check({key: value for key, _, value in items}, f"{_TABLES}{name}", name)
