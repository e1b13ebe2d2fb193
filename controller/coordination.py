"""Module FC: how PT and AO are blended, eq. 30: v_E = k_T v_T + k_C v_A (same for omega).

Two coordinators share one interface, ``weights(measurement, at_waypoint) -> (k_T, k_C)``:
:class:`FuzzyCoordinator` (Table 2) and :class:`ConventionalCoordinator`, the hard switch of
the paper's Fig. 8. ``at_waypoint`` (0..1) is how deep the TCP is in the free room around the
waypoint it heads for, where the straight way to it cannot touch the obstacle: 1 means AO is
not needed there (``ControlLaw`` measures it).
"""

from __future__ import annotations

from typing import Protocol

from controller.fuzzy import FuzzyInference, RuleBase
from controller.obstacle import ObstacleMeasurement, absent
from protocol.scenario import Mode

# How far ahead an obstacle is, as the cosine of the angle between "towards p_j" and
# "towards the obstacle": AO counts fully above AHEAD_FULL and not at all below AHEAD_NONE,
# where the controller also forgets its TL/TR choice.
AHEAD_FULL = 0.3
AHEAD_NONE = -0.2


class Coordinator(Protocol):
    def weights(
        self, measurement: ObstacleMeasurement, at_waypoint: float = 0.0
    ) -> tuple[float, float]: ...


class FuzzyCoordinator:
    """k_T and k_C from min(d_L, d_R) and beta through the rule base of Table 2.

    Table 2 speaks of an obstacle that matters; k_C is scaled by how much it does, so that
    AO fades in and out instead of switching: fully within half the sensing range, not at
    all at the range; fully while the obstacle is ahead, towards p_j or the way the TCP moves
    (or the TCP is inside it), fading as it falls behind (smoothsteps of the distance and of
    the larger of ``measurement.ahead`` and ``measurement.toward``).
    """

    def __init__(self, sensing_range: float, rule_base: RuleBase | None = None) -> None:
        self.sensing_range = sensing_range
        self.inference = FuzzyInference(rule_base or RuleBase.load())
        nothing = absent(sensing_range)
        self._k_t_without_obstacle = self.inference.weights(nothing.min_distance, nothing.beta)[0]

    def weights(
        self, measurement: ObstacleMeasurement, at_waypoint: float = 0.0
    ) -> tuple[float, float]:
        if not measurement.present:  # the inputs of "no obstacle" never change: k_C is 0
            return self._k_t_without_obstacle, 0.0
        k_t, k_c = self.inference.weights(measurement.min_distance, measurement.beta)
        return k_t, k_c * self.relevance(measurement) * (1.0 - at_waypoint)

    def relevance(self, measurement: ObstacleMeasurement) -> float:
        """How much a present obstacle matters, 0..1 (see the class docstring)."""
        half = self.sensing_range / 2.0
        relevance = smoothstep((self.sensing_range - measurement.min_distance) / half)
        if measurement.clearance > 0.0:
            ahead = max(measurement.ahead, measurement.toward)
            relevance *= smoothstep((ahead - AHEAD_NONE) / (AHEAD_FULL - AHEAD_NONE))
        return relevance


class ConventionalCoordinator:
    """PT alone, or AO alone while an obstacle ahead is closer than ``switch_distance`` (and the
    TCP is not in the free room of its waypoint)."""

    def __init__(self, switch_distance: float) -> None:
        self.switch_distance = switch_distance

    def weights(
        self, measurement: ObstacleMeasurement, at_waypoint: float = 0.0
    ) -> tuple[float, float]:
        if (
            measurement.present
            and measurement.ahead > 0.0
            and measurement.clearance < self.switch_distance
            and at_waypoint == 0.0
        ):
            return (0.0, 1.0)
        return (1.0, 0.0)


def make_coordinator(mode: Mode, switch_distance: float, sensing_range: float) -> Coordinator:
    if mode is Mode.FUZZY:
        return FuzzyCoordinator(sensing_range)
    return ConventionalCoordinator(switch_distance)


def smoothstep(x: float) -> float:
    """0 below 0, 1 above 1, and 3x^2 - 2x^3 between: a ramp with flat ends."""
    x = 0.0 if x < 0.0 else 1.0 if x > 1.0 else x
    return x * x * (3.0 - 2.0 * x)
