"""Gains and rates of the control law: one typed, validated configuration."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

from protocol.errors import ConfigError


@dataclass(frozen=True, slots=True)
class ControllerConfig:
    """Everything the control law is tuned by (SI units; rates in Hz).

    PT tracks the planned cubic with a unicycle law (see ``behaviours.plan_tracking``): the
    speed is the planned speed plus ``position_gain`` times the lag along the path, and the
    heading aims back at the path with ``heading_gain``; speed is capped at ``speed_max``.
    AO is the paper's eq. 28-29 with
    ``f_vA(s) = ao_speed_min + (ao_speed_max - ao_speed_min) tanh(max(s, 0) / ao_speed_distance)``
    and ``f_omegaA(s) = ao_turn_max tanh(s / ao_turn_scale)``, steering at the edge of the
    obstacle grown by ``ao_pass_margin``.
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

    def __post_init__(self) -> None:
        for spec in fields(self):
            value = getattr(self, spec.name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ConfigError(
                    f"controller.{spec.name}", f"must be a finite number >= 0, got {value!r}"
                )
        if not 1.0 <= self.rate_hz <= 2000.0:
            raise ConfigError("controller.rate_hz", "must be between 1 and 2000 Hz")
        if self.ao_speed_min > self.ao_speed_max:
            raise ConfigError("controller.ao_speed_min", "must not exceed ao_speed_max")
        for name in ("ao_speed_distance", "ao_turn_scale", "sensing_range", "position_gain"):
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
