"""Module FC: how PT and AO are blended, eq. 30: v_E = k_T v_T + k_C v_A (same for omega).

Two coordinators: the fuzzy one of Table 2 and the conventional hard switch of the paper's
Fig. 8, both in :func:`weights`, which picks per run (the batch study mixes them).
``at_waypoint`` (0..1) is how deep the TCP is in the free room around the waypoint it heads
for, where the straight way to it cannot touch the obstacle: 1 means AO is not needed there
(the control law measures it).
"""

from __future__ import annotations

from dataclasses import dataclass

from controller.fuzzy import FuzzyInference, RuleBase, infer, packaged_rule_base
from controller.obstacle import ObstacleMeasurement, absent
from protocol.ops import Mask, Ops, Real

AHEAD_FULL = 0.3
"""How far ahead an obstacle is, as the cosine of the angle between "towards p_j" (or the way
the TCP moves) and "towards the obstacle", from which AO counts fully."""
AHEAD_NONE = -0.2
"""Below this AO does not count at all, and the controller forgets its TL/TR choice."""
HEIGHT_FADE = 0.01
"""m below the obstacle's top (its height plus the inflation) from which AO counts fully in
the fuzzy mode; at the top, where DM stops seeing the obstacle, not at all."""
WAY_PASSING_FULL = 0.02
"""m: AO counts fully in the fuzzy mode where the straight way to p_j passes the obstacle
this near or nearer (DM's ``passing``), fading to nothing where it passes as far as the
conventional switch's distance: there the hard switch never switches, and an obstacle the way
keeps clear of does not matter (AO would only draw the arm off a plan that clears it)."""


@dataclass(frozen=True, slots=True)
class Coordination:
    """What both coordinators need: the fuzzy rule base's inference, the sensing range and
    the conventional switch's distance."""

    inference: FuzzyInference
    sensing_range: float
    switch_distance: float
    k_t_without_obstacle: float
    """The fuzzy k_T where nothing is in reach (its inputs then never change)."""

    @classmethod
    def of(
        cls, sensing_range: float, switch_distance: float, rule_base: RuleBase | None = None
    ) -> Coordination:
        inference = FuzzyInference(rule_base or packaged_rule_base())
        nothing = absent(sensing_range)
        k_t = inference.weights(nothing.min_distance, nothing.beta)[0]
        return cls(inference, sensing_range, switch_distance, k_t)


def weights(
    ops: Ops,
    coordination: Coordination,
    fuzzy: Mask,
    measurement: ObstacleMeasurement,
    min_distance: Real,
    at_waypoint: Real,
    below_top: Real,
) -> tuple[Real, Real]:
    """k_T and k_C: Table 2's where ``fuzzy``, else the hard switch.

    Fuzzy: Table 2 speaks of an obstacle that matters; k_C is scaled by how much it does, so
    that AO fades in and out instead of switching: fully within half the sensing range, not
    at all at the range; fully while the obstacle is ahead, towards p_j or the way the TCP
    moves (or the TCP is inside it), fading as it falls behind (smoothsteps of the distance
    and of the larger of ``ahead`` and ``toward``); fully where the straight way to p_j
    passes the obstacle within WAY_PASSING_FULL, not at all where it keeps the switch
    distance from it; not at all deep in a waypoint's free room; and fully from HEIGHT_FADE
    below the obstacle's top (``below_top``: how far the TCP is below it), not at all at the
    top, where DM stops seeing it (an arm rising over a low obstacle lost AO in one tick, its
    peak jerk ten times the hard switch's).
    Conventional: PT alone, or AO alone while an obstacle ahead is closer than the switch
    distance (and the TCP is not in the free room of its waypoint).
    """
    present, clearance = measurement.present, measurement.clearance
    switched = (
        present
        & (measurement.ahead > 0.0)
        & (clearance < coordination.switch_distance)
        & (at_waypoint == 0.0)
    )
    k_t, k_c = ops.branch(
        present & fuzzy,
        _fuzzy_weights,
        (coordination.k_t_without_obstacle, 0.0),
        ops,
        coordination,
        min_distance,
        measurement.beta,
        clearance,
        ops.max(measurement.ahead, measurement.toward),
        at_waypoint,
        below_top,
        measurement.passing,
    )
    return (
        ops.where(fuzzy, k_t, ops.where(switched, 0.0, 1.0)),
        ops.where(fuzzy, k_c, ops.where(switched, 1.0, 0.0)),
    )


def _fuzzy_weights(
    ops: Ops,
    coordination: Coordination,
    min_distance: Real,
    beta: Real,
    clearance: Real,
    facing: Real,
    at_waypoint: Real,
    below_top: Real,
    passing: Real,
) -> tuple[Real, Real]:
    """:func:`weights` of the fuzzy coordinator with an obstacle present."""
    k_t, k_c = infer(ops, coordination.inference, min_distance, beta)
    sensing_range = coordination.sensing_range
    half = sensing_range / 2.0
    relevance = smoothstep(ops, (sensing_range - min_distance) / half)
    fading = smoothstep(ops, (facing - AHEAD_NONE) / (AHEAD_FULL - AHEAD_NONE))
    fade = coordination.switch_distance
    in_the_way = smoothstep(ops, (fade - passing) / (fade - WAY_PASSING_FULL))
    relevance = ops.where(clearance > 0.0, relevance * fading * in_the_way, relevance)
    height = smoothstep(ops, below_top / HEIGHT_FADE)
    return k_t, k_c * relevance * height * (1.0 - at_waypoint)


def smoothstep(ops: Ops, x: Real) -> Real:
    """0 below 0, 1 above 1, and 3x^2 - 2x^3 between: a ramp with flat ends."""
    x = ops.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)
