"""Module FC: how PT and AO are blended, eq. 30: v_E = k_T v_T + k_C v_A (same for omega).

Two coordinators share one interface, ``weights(measurement) -> (k_T, k_C)``:
:class:`FuzzyCoordinator` (Table 2) and :class:`ConventionalCoordinator`, the hard switch of
the paper's Fig. 8.
"""

from __future__ import annotations

from enum import Enum
from typing import Protocol

from controller.fuzzy import FuzzyInference, RuleBase
from controller.obstacle import ObstacleMeasurement


class Mode(Enum):
    FUZZY = "fuzzy"
    CONVENTIONAL = "conventional"


class Coordinator(Protocol):
    def weights(self, measurement: ObstacleMeasurement) -> tuple[float, float]: ...


class FuzzyCoordinator:
    """k_T and k_C from min(d_L, d_R) and beta through the rule base of Table 2."""

    def __init__(self, rule_base: RuleBase | None = None) -> None:
        self.inference = FuzzyInference(rule_base or RuleBase.load())

    def weights(self, measurement: ObstacleMeasurement) -> tuple[float, float]:
        return self.inference.weights(measurement.min_distance, measurement.beta)


class ConventionalCoordinator:
    """PT alone, or AO alone while an obstacle ahead is closer than ``switch_distance``."""

    def __init__(self, switch_distance: float) -> None:
        self.switch_distance = switch_distance

    def weights(self, measurement: ObstacleMeasurement) -> tuple[float, float]:
        if (
            measurement.present
            and measurement.ahead > 0.0
            and measurement.clearance < self.switch_distance
        ):
            return (0.0, 1.0)
        return (1.0, 0.0)


def make_coordinator(mode: Mode, switch_distance: float) -> Coordinator:
    if mode is Mode.FUZZY:
        return FuzzyCoordinator()
    return ConventionalCoordinator(switch_distance)
