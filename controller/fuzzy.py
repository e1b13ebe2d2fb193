"""The fuzzy rule base of Table 2 and its exact, fast Mamdani inference.

The rule base (membership functions and the 3x3 table) lives in ``data/fuzzy_rules.json``.
Inference is textbook Mamdani, the one scikit-fuzzy's ``ControlSystem`` computes: ``min`` for
AND and for implication (clipping), ``max`` to aggregate, centroid to defuzzify. The centroid
is computed in closed form rather than on a sampled universe: the output terms form a
triangular partition, so between two neighbouring peaks only two clipped edges are non-zero
and their union integrates exactly. That makes one evaluation a few microseconds of plain
Python and free of any sampling error.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cache
from importlib import resources
from itertools import pairwise
from pathlib import Path
from typing import Any

from protocol.errors import ConfigError
from protocol.ops import SCALAR, Ops, Real
from protocol.validation import check

INPUT_NAMES = ("min_distance", "beta")
OUTPUT_NAMES = ("k_T", "k_C")
OUTPUT_TERMS = ("small", "medium", "big")


@dataclass(frozen=True, slots=True)
class Trapezoid:
    """Membership rising a->b, 1 on [b, c], falling c->d (a == b or c == d: a shoulder)."""

    a: float
    b: float
    c: float
    d: float

    def __call__(self, x: float) -> float:
        shoulder = self.a == self.b or self.c == self.d
        return float(memberships(SCALAR, x, ((self.a, self.b, self.c, self.d, shoulder),))[0])


@dataclass(frozen=True, slots=True)
class FuzzyInput:
    name: str
    universe: tuple[float, float]
    terms: dict[str, Trapezoid]


@dataclass(frozen=True, slots=True)
class FuzzyOutput:
    """Three triangles peaking at small < medium < big, each reaching its neighbours' peaks.

    The outer two are mirrored about their peaks; with evenly spaced peaks the middle one is
    symmetric too, so that any term fired alone defuzzifies to exactly its peak.
    """

    name: str
    peaks: tuple[float, float, float]

    @property
    def universe(self) -> tuple[float, float]:
        small, medium, big = self.peaks
        return (small - (medium - small), big + (big - medium))

    def triangles(self) -> dict[str, tuple[float, float, float]]:
        """The terms as (foot, peak, foot) triangles, for independent implementations."""
        low, high = self.universe
        small, medium, big = self.peaks
        return {
            "small": (low, small, medium),
            "medium": (small, medium, big),
            "big": (medium, big, high),
        }


@dataclass(frozen=True, slots=True)
class Rule:
    min_distance: str
    beta: str
    k_T: str  # noqa: N815 - the paper's symbol
    k_C: str  # noqa: N815 - the paper's symbol


@dataclass(frozen=True, slots=True)
class RuleBase:
    inputs: dict[str, FuzzyInput]
    outputs: dict[str, FuzzyOutput]
    rules: tuple[Rule, ...]

    @classmethod
    def load(cls, path: str | Path | None = None) -> RuleBase:
        """Read a rule base file; the packaged Table 2 when ``path`` is None."""
        if path is None:
            text = resources.files("controller").joinpath("data/fuzzy_rules.json").read_text()
            source = "fuzzy_rules.json"
        else:
            text = Path(path).read_text()
            source = str(path)
        try:
            document = json.loads(text)
        except json.JSONDecodeError as error:
            raise ConfigError(source, f"not valid JSON: {error}") from error
        return cls.from_mapping(document)

    @classmethod
    def from_mapping(cls, document: Mapping[str, Any]) -> RuleBase:
        """A rule base from the document of a rule file, checked against the rule file's
        schema (``fuzzy-rules``) and then for what a schema cannot say: points in order, rules
        naming the inputs' terms, every input covered."""
        check(document, "fuzzy-rules.schema.json")
        inputs = {name: _parse_input(name, document["inputs"][name]) for name in INPUT_NAMES}
        outputs = {name: _parse_output(name, document["outputs"][name]) for name in OUTPUT_NAMES}
        rules = []
        for index, raw in enumerate(document["rules"]):
            for name in INPUT_NAMES:
                if raw[name] not in inputs[name].terms:
                    raise ConfigError(
                        f"rules[{index}].{name}",
                        f"unknown term {raw[name]!r}; known: {sorted(inputs[name].terms)}",
                    )
            rules.append(Rule(raw["min_distance"], raw["beta"], raw["k_T"], raw["k_C"]))
        base = cls(inputs, outputs, tuple(rules))
        base._check_coverage()
        return base

    def _check_coverage(self) -> None:
        """Every input pair must fire some rule, or the centroid would be undefined."""
        for name, fuzzy_input in self.inputs.items():
            low, high = fuzzy_input.universe
            corners = {p for t in fuzzy_input.terms.values() for p in (t.a, t.b, t.c, t.d)}
            points = sorted(corners | {low, high})
            probes = points + [(p + q) / 2.0 for p, q in pairwise(points)]
            for x in probes:
                if low <= x <= high and max(t(x) for t in fuzzy_input.terms.values()) <= 0.0:
                    raise ConfigError(f"inputs.{name}.terms", f"no term covers {x:g}")
        pairs = {(rule.min_distance, rule.beta) for rule in self.rules}
        for distance_term in self.inputs["min_distance"].terms:
            for beta_term in self.inputs["beta"].terms:
                if (distance_term, beta_term) not in pairs:
                    raise ConfigError(
                        "rules", f"no rule for min_distance={distance_term}, beta={beta_term}"
                    )


@cache
def packaged_rule_base() -> RuleBase:
    """The packaged Table 2, read and checked once: each run's start builds its law, and
    checking the file against its schema took 5-7 ms of the tick that starts the run."""
    return RuleBase.load()


class FuzzyInference:
    """Evaluates a :class:`RuleBase`: ``weights(min_distance, beta) -> (k_T, k_C)``."""

    def __init__(self, rule_base: RuleBase) -> None:
        self.rule_base = rule_base
        distance, beta = rule_base.inputs["min_distance"], rule_base.inputs["beta"]
        self.distance_terms = _shapes(distance)
        self.beta_terms = _shapes(beta)
        self.distance_range = distance.universe
        self.beta_range = beta.universe
        distance_index = {name: i for i, name in enumerate(distance.terms)}
        beta_index = {name: i for i, name in enumerate(beta.terms)}
        output_index = {name: i for i, name in enumerate(OUTPUT_TERMS)}
        self.rules = tuple(
            (
                distance_index[rule.min_distance],
                beta_index[rule.beta],
                output_index[rule.k_T],
                output_index[rule.k_C],
            )
            for rule in rule_base.rules
        )
        """Per rule: its min_distance term, beta term, k_T term and k_C term (indices)."""
        self.peaks_t = rule_base.outputs["k_T"].peaks
        self.peaks_c = rule_base.outputs["k_C"].peaks

    def weights(self, min_distance: float, beta: float) -> tuple[float, float]:
        """k_T and k_C for one pair of inputs (clamped to their universes)."""
        if min_distance != min_distance or beta != beta:
            raise ValueError(f"fuzzy inputs must not be NaN: ({min_distance}, {beta})")
        return infer(SCALAR, self, min_distance, beta)


def infer(ops: Ops, inference: FuzzyInference, min_distance: Real, beta: Real) -> tuple[Real, Real]:
    """k_T and k_C of ``inference``'s rule base for the inputs (clamped to their universes)."""
    low, high = inference.distance_range
    min_distance = ops.clip(min_distance, low, high)
    low, high = inference.beta_range
    beta = ops.clip(beta, low, high)
    mu_distance = memberships(ops, min_distance, inference.distance_terms)
    mu_beta = memberships(ops, beta, inference.beta_terms)
    fired_t: list[Real] = [0.0, 0.0, 0.0]
    fired_c: list[Real] = [0.0, 0.0, 0.0]
    minimum, maximum = ops.min, ops.max  # bound once: this runs on most control ticks
    for distance_term, beta_term, term_t, term_c in inference.rules:
        strength = minimum(mu_distance[distance_term], mu_beta[beta_term])
        fired_t[term_t] = maximum(fired_t[term_t], strength)
        fired_c[term_c] = maximum(fired_c[term_c], strength)
    return (
        centroid(ops, inference.peaks_t, fired_t),
        centroid(ops, inference.peaks_c, fired_c),
    )


Shape = tuple[float, float, float, float, bool]
"""A trapezoid for :func:`memberships`: a, b, c, d and ``feet``."""


def memberships(ops: Ops, x: Real, terms: Sequence[Shape]) -> list[Real]:
    """How far ``x`` is in each of ``terms``: trapezoids (a, b, c, d, feet) rising a->b, 1 on
    [b, c], falling c->d (a == b or c == d: a shoulder); ``feet``: whether ``x`` may lie
    beyond the foot of a shoulder (not where it is clamped to a universe the shoulder ends).

    The lesser of the rising and the falling edge, capped at 1 (not needed for a triangle:
    one edge is below 1 wherever the other is above) and not below 0: the piecewise
    definition to the last bit.
    """
    minimum, maximum = ops.min, ops.max  # bound once: this runs on most control ticks
    levels = []
    for a, b, c, d, feet in terms:
        if a < b and c < d:
            level = minimum((x - a) / (b - a), (d - x) / (d - c))
            if b < c:
                level = minimum(level, 1.0)
            level = maximum(level, 0.0)
        elif a < b:
            level = maximum(minimum((x - a) / (b - a), 1.0), 0.0)
        elif c < d:
            level = maximum(minimum((d - x) / (d - c), 1.0), 0.0)
        else:
            level = 1.0
        if feet:
            level = ops.where((x < a) | (x > d), 0.0, level)
        levels.append(level)
    return levels


def _shapes(fuzzy_input: FuzzyInput) -> tuple[Shape, ...]:
    """An input's terms for :func:`memberships`, clamped to its universe."""
    low, high = fuzzy_input.universe
    return tuple(
        (t.a, t.b, t.c, t.d, (t.a == t.b and t.a > low) or (t.c == t.d and t.d < high))
        for t in fuzzy_input.terms.values()
    )


def centroid_of_partition(peaks: Sequence[float], fired: Sequence[float]) -> float:
    """:func:`centroid` of one set of fired levels."""
    return float(centroid(SCALAR, peaks, fired))


def centroid(ops: Ops, peaks: Sequence[float], fired: Sequence[Real]) -> Real:
    """Exact centroid of max(min(fired_k, term_k)) over a three-triangle partition.

    The union splits at the peaks into four pieces; on each piece, in the normalised
    coordinate u in [0, 1], it is a clipped rising edge, a clipped falling edge, or the
    larger of one of each, all of which integrate in closed form.
    """
    small, medium, big = peaks
    low_width = medium - small
    high_width = big - medium
    # Each level's whole rising edge, _rising(level, 1): both of its branches give the same
    # bits at level == 1 (a membership is at most 1), so the general one serves.
    whole = [
        (
            level * (1.0 - level * 0.5),
            level * level * level / 3.0 + level * (1.0 - level * level) * 0.5,
        )
        for level in fired
    ]
    # Left tail: min(w_small, u); right tail: min(w_big, 1 - u).
    piece_area, piece_moment = whole[0]
    area = 0.0 + low_width * piece_area
    moment = 0.0 + low_width * ((small - low_width) * piece_area + low_width * piece_moment)
    piece_area, piece_moment = whole[2]
    area = area + high_width * piece_area
    moment = moment + high_width * (big * piece_area + high_width * (piece_area - piece_moment))
    for start, width, falling, rising in ((small, low_width, 0, 1), (medium, high_width, 1, 2)):
        piece_area, piece_moment = _falling_then_rising(
            ops, fired[falling], fired[rising], whole[falling], whole[rising]
        )
        area = area + width * piece_area
        moment = moment + width * (start * piece_area + width * piece_moment)
    return moment / area


def _rising(ops: Ops, level: Real, upto: Real) -> tuple[Real, Real]:
    """Integrals of min(level, u) and u*min(level, u) over [0, upto], upto in [0, 1].

    Where upto <= level the edge is u all the way: the formula with level = upto gives
    upto^2 / 2 and upto^3 / 3 to the last bit (halving is exact, and the second term is 0)."""
    level = ops.min(level, upto)
    return (
        level * (upto - level * 0.5),
        level * level * level / 3.0 + level * (upto * upto - level * level) * 0.5,
    )


def _falling_then_rising(
    ops: Ops,
    falling: Real,
    rising: Real,
    falling_whole: tuple[Real, Real],
    rising_whole: tuple[Real, Real],
) -> tuple[Real, Real]:
    """Integrals of max(min(falling, 1 - u), min(rising, u)) over [0, 1], given each level's
    whole rising edge.

    The falling part wins on [0, c] and the rising part on [c, 1], with c where they cross.
    With v = 1 - u the falling part is min(falling, v) over [1 - c, 1], and u = 1 - v.
    """
    crossing = ops.where(
        (falling <= rising) & (falling <= 0.5),
        falling,
        ops.where((rising < falling) & (rising <= 0.5), 1.0 - rising, 0.5),
    )
    full_area, full_moment = falling_whole
    part_area, part_moment = _rising(ops, falling, 1.0 - crossing)
    falling_area = full_area - part_area
    falling_moment = falling_area - (full_moment - part_moment)
    full_area, full_moment = rising_whole
    part_area, part_moment = _rising(ops, rising, crossing)
    return (
        falling_area + full_area - part_area,
        falling_moment + full_moment - part_moment,
    )


def _parse_input(name: str, raw: Mapping[str, Any]) -> FuzzyInput:
    low, high = (float(value) for value in raw["universe"])
    if low >= high:
        raise ConfigError(f"inputs.{name}.universe", "must be [low, high] with low < high")
    terms = {}
    for term, points in raw["terms"].items():
        where = f"inputs.{name}.terms.{term}"
        a, b, c, d = (float(point) for point in points)
        if not a <= b <= c <= d or a == d:
            raise ConfigError(where, "must satisfy a <= b <= c <= d with a < d")
        terms[term] = Trapezoid(a, b, c, d)
    return FuzzyInput(name, (low, high), terms)


def _parse_output(name: str, raw: Mapping[str, Any]) -> FuzzyOutput:
    small, medium, big = (float(raw["peaks"][term]) for term in OUTPUT_TERMS)
    if not small < medium < big:
        raise ConfigError(f"outputs.{name}.peaks", "must satisfy small < medium < big")
    if not math.isclose(medium - small, big - medium, rel_tol=1e-9):
        raise ConfigError(f"outputs.{name}.peaks", "must be evenly spaced (medium halfway)")
    return FuzzyOutput(name, (small, medium, big))
