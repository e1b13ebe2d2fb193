"""FC's rule base (paper Table 2) and its exact Mamdani inference."""

from __future__ import annotations

import copy
import json
import math
from importlib import resources
from typing import Any

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from controller.fuzzy import (
    OUTPUT_TERMS,
    FuzzyInference,
    FuzzyInput,
    FuzzyOutput,
    RuleBase,
    centroid_of_partition,
)
from protocol.errors import ConfigError

RULE_BASE = RuleBase.load()
INFERENCE = FuzzyInference(RULE_BASE)

# Table 2 of the paper, cell by cell, as printed: (min(d_L, d_R), beta) -> (k_T, k_C).
PAPER_TABLE_2: dict[tuple[str, str], tuple[str, str]] = {
    ("far", "small"): ("big", "big"),
    ("far", "medium"): ("big", "medium"),
    ("far", "big"): ("big", "small"),
    ("middle", "small"): ("medium", "big"),
    ("middle", "medium"): ("medium", "medium"),
    ("middle", "big"): ("medium", "small"),
    ("near", "small"): ("small", "big"),
    ("near", "medium"): ("small", "medium"),
    ("near", "big"): ("small", "small"),
}


def _shipped_document() -> dict[str, Any]:
    text = resources.files("controller").joinpath("data/fuzzy_rules.json").read_text()
    document: dict[str, Any] = json.loads(text)
    return document


def _pure_point(fuzzy_input: FuzzyInput, name: str) -> float:
    """A point of the universe where term ``name`` is 1 and every other term is 0."""
    term = fuzzy_input.terms[name]
    others = [t for other, t in fuzzy_input.terms.items() if other != name]
    low, high = fuzzy_input.universe
    plateau = (max(term.b, low), min(term.c, high))
    candidates = [0.5 * (plateau[0] + plateau[1]), *plateau]
    candidates += [p for t in others for p in (t.a, t.d) if plateau[0] <= p <= plateau[1]]
    for x in candidates:
        if term(x) == 1.0 and all(t(x) == 0.0 for t in others):
            return x
    raise AssertionError(f"no point where only {fuzzy_input.name}.{name} is fired")


# --------------------------------------------------------------------------- Table 2


def test_rule_base_has_the_table_2_terms() -> None:
    assert set(RULE_BASE.inputs["min_distance"].terms) == {"near", "middle", "far"}
    assert set(RULE_BASE.inputs["beta"].terms) == {"small", "medium", "big"}
    cells = [(rule.min_distance, rule.beta) for rule in RULE_BASE.rules]
    assert sorted(cells) == sorted(PAPER_TABLE_2)


@pytest.mark.parametrize(("distance_term", "beta_term"), sorted(PAPER_TABLE_2))
def test_table_2_corner(distance_term: str, beta_term: str) -> None:
    """Where exactly one cell of Table 2 fires, FC outputs the peaks of that cell's terms.

    The three peaks of each output are distinct, so a wrong entry in the JSON table fails.
    """
    distance = _pure_point(RULE_BASE.inputs["min_distance"], distance_term)
    beta = _pure_point(RULE_BASE.inputs["beta"], beta_term)
    expected_t, expected_c = PAPER_TABLE_2[(distance_term, beta_term)]
    k_t, k_c = INFERENCE.weights(distance, beta)
    for output, value, expected in (("k_T", k_t, expected_t), ("k_C", k_c, expected_c)):
        peaks = RULE_BASE.outputs[output].peaks
        assert len(set(peaks)) == 3
        peak = peaks[OUTPUT_TERMS.index(expected)]
        assert value == pytest.approx(peak, rel=1e-12, abs=1e-15), (output, expected, value)


@pytest.mark.parametrize("output", ["k_T", "k_C"])
@pytest.mark.parametrize("term", OUTPUT_TERMS)
def test_lone_term_defuzzifies_to_its_peak(output: str, term: str) -> None:
    """The JSON's promise: 'a term fired alone defuzzifies exactly to its peak'."""
    peaks = RULE_BASE.outputs[output].peaks
    index = OUTPUT_TERMS.index(term)
    for level in (1.0, 0.5, 0.1):
        fired = [0.0, 0.0, 0.0]
        fired[index] = level
        assert centroid_of_partition(peaks, fired) == pytest.approx(peaks[index], abs=1e-12)


# --------------------------------------------------------------------------- scikit-fuzzy

# Output universe samples for scikit-fuzzy. Its centroid is a pure-Python loop, about
# 0.6 us per sample per output, so 2 x 2500 evaluations x 20001 samples would take about
# a minute; 2001 samples keep the whole comparison near 6 s and the error bound below is
# still 1e-5 or smaller.
SKFUZZY_OUTPUT_SAMPLES = 2001
SKFUZZY_INPUT_SAMPLES = 2001


def _skfuzzy_error_bound(output: FuzzyOutput, universe: np.ndarray) -> float:
    """Worst-case |skfuzzy - exact| of one output's centroid, from the sampling step h.

    scikit-fuzzy fuzzifies inputs by linear interpolation on the input universe, which holds
    every trapezoid corner (below), so input memberships are exact. On the output side it
    adds the points where each term meets its cut level, and the universe holds the peaks
    and the mid-points between them, so its piecewise-linear centroid is exact except on
    the sample interval holding a kink of the aggregate that is none of those: where a
    clipped term's flat top meets its neighbour's edge. That is at most one kink per pair
    of neighbouring peaks, with a slope change of at most 1 / width of that pair. Linear
    interpolation over an interval of length h containing one kink of slope change s errs
    by at most s h / 4 and, in area, by at most s h^2 / 8. With e the interpolation error,
    A the area and c the centroid, the centroid is off by at most |int (x - c) e(x) dx| /
    (A - dA) <= W dA / (A - dA), W the universe width.

    A is bounded below by the smallest area the aggregate can have: every input value
    has some term at membership >= lam (the smallest max-membership over each input's
    universe, 0.5 for the shipped trapezoids) and every cell has a rule, so some output
    term is fired at >= lam, whose clipped triangle has area (right - left) / 2 (1 - (1 -
    lam)^2).
    """
    h = float(np.diff(universe).max())
    small, medium, big = output.peaks
    widths = (medium - small, big - medium)
    area_error = sum(h * h / (8.0 * width) for width in widths)
    lam = min(_min_max_membership(RULE_BASE.inputs[name]) for name in RULE_BASE.inputs)
    smallest_area = min(
        (peak - left + right - peak) / 2.0 * (1.0 - (1.0 - lam) ** 2)
        for left, peak, right in output.triangles().values()
    )
    low, high = output.universe
    return (high - low) * area_error / (smallest_area - area_error)


def _min_max_membership(fuzzy_input: FuzzyInput) -> float:
    """Smallest over the universe of the largest term membership (dense grid + corners)."""
    low, high = fuzzy_input.universe
    corners = [p for t in fuzzy_input.terms.values() for p in (t.a, t.b, t.c, t.d)]
    xs = np.union1d(np.linspace(low, high, 20001), np.clip(corners, low, high))
    return min(max(t(float(x)) for t in fuzzy_input.terms.values()) for x in xs)


@pytest.mark.filterwarnings("ignore::DeprecationWarning:skfuzzy")
def test_agrees_with_scikit_fuzzy() -> None:
    """Same rule base through scikit-fuzzy's Mamdani ControlSystem, on a 50x50 grid.

    The tolerance is derived from the output sampling step h in ``_skfuzzy_error_bound``
    (about 2.1e-6 for either output with h = 8e-4, O(h^2)), times a margin of 4 for the
    floating-point work on 2000-odd samples and the rough bounds on A: about 8.5e-6.
    Measured: about 2e-7 for k_T and 8e-8 for k_C; 10 times more samples make it about
    100 times smaller, as h^2 predicts. For scale: a wrong rule moves the output by 0.1
    or more, and a relative error of 1e-4 in one piece of the closed-form centroid
    already shows as 2.5e-5.
    """
    fuzz = pytest.importorskip("skfuzzy")
    ctrl = pytest.importorskip("skfuzzy.control")

    antecedents = {}
    for name, fuzzy_input in RULE_BASE.inputs.items():
        low, high = fuzzy_input.universe
        corners = [p for t in fuzzy_input.terms.values() for p in (t.a, t.b, t.c, t.d)]
        universe = np.union1d(
            np.linspace(low, high, SKFUZZY_INPUT_SAMPLES), np.clip(corners, low, high)
        )
        antecedent = ctrl.Antecedent(universe, name)
        for term_name, t in fuzzy_input.terms.items():
            antecedent[term_name] = fuzz.trapmf(universe, [t.a, t.b, t.c, t.d])
        antecedents[name] = antecedent
    consequents = {}
    tolerances = {}
    for name, output in RULE_BASE.outputs.items():
        low, high = output.universe
        small, medium, big = output.peaks
        universe = np.union1d(
            np.linspace(low, high, SKFUZZY_OUTPUT_SAMPLES),
            [small, medium, big, (small + medium) / 2.0, (medium + big) / 2.0],
        )
        consequent = ctrl.Consequent(universe, name)  # default: centroid
        for term_name, triangle in output.triangles().items():
            consequent[term_name] = fuzz.trimf(universe, list(triangle))
        consequents[name] = consequent
        tolerances[name] = 4.0 * _skfuzzy_error_bound(output, universe) + 1e-12
        assert tolerances[name] < 1e-5
    rules = [
        ctrl.Rule(
            antecedents["min_distance"][rule.min_distance] & antecedents["beta"][rule.beta],
            (consequents["k_T"][rule.k_T], consequents["k_C"][rule.k_C]),
        )
        for rule in RULE_BASE.rules
    ]
    simulation = ctrl.ControlSystemSimulation(ctrl.ControlSystem(rules))

    distances = np.linspace(*RULE_BASE.inputs["min_distance"].universe, 50)
    betas = np.linspace(*RULE_BASE.inputs["beta"].universe, 50)
    grid_d, grid_b = (g.ravel() for g in np.meshgrid(distances, betas, indexing="ij"))
    simulation.input["min_distance"] = grid_d
    simulation.input["beta"] = grid_b
    simulation.compute()
    ours = np.array(
        [INFERENCE.weights(float(d), float(b)) for d, b in zip(grid_d, grid_b, strict=True)]
    )
    for column, name in enumerate(("k_T", "k_C")):
        theirs = np.asarray(simulation.output[name], dtype=float)
        error = np.abs(ours[:, column] - theirs)
        worst = int(np.argmax(error))
        assert error[worst] <= tolerances[name], (
            name,
            grid_d[worst],
            grid_b[worst],
            error[worst],
            tolerances[name],
        )


# --------------------------------------------------------------------------- centroid

BRUTE_FORCE_SAMPLES = 400_001
firing = st.one_of(
    st.just(0.0), st.just(1.0), st.floats(min_value=1e-3, max_value=1.0, allow_nan=False)
)


def _brute_force_centroid(peaks: tuple[float, float, float], fired: list[float]) -> float:
    """Trapezoid-rule centroid of max_k min(fired_k, triangle_k) on a very fine grid."""
    output = FuzzyOutput("brute", peaks)
    low, high = output.universe
    small, medium, big = peaks
    xs = np.union1d(
        np.linspace(low, high, BRUTE_FORCE_SAMPLES),
        [small, medium, big, (small + medium) / 2.0, (medium + big) / 2.0],
    )
    membership = np.zeros_like(xs)
    for level, (left, peak, right) in zip(fired, output.triangles().values(), strict=True):
        triangle = np.interp(xs, [left, peak, right], [0.0, 1.0, 0.0])
        membership = np.maximum(membership, np.minimum(level, triangle))
    dx = np.diff(xs)
    area = np.sum(dx * (membership[1:] + membership[:-1]) / 2.0)
    moment_density = xs * membership
    moment = np.sum(dx * (moment_density[1:] + moment_density[:-1]) / 2.0)
    return float(moment / area)


@settings(max_examples=60, deadline=None)
@given(
    fired=st.lists(firing, min_size=3, max_size=3),
    small=st.floats(min_value=-2.0, max_value=2.0),
    gaps=st.lists(st.floats(min_value=0.05, max_value=1.0), min_size=2, max_size=2),
    shipped=st.booleans(),
)
def test_centroid_of_partition_matches_brute_force(
    fired: list[float], small: float, gaps: list[float], shipped: bool
) -> None:
    assume(max(fired) > 0.0)
    peaks = (
        RULE_BASE.outputs["k_T"].peaks
        if shipped
        else (small, small + gaps[0], small + gaps[0] + gaps[1])
    )
    exact = centroid_of_partition(peaks, fired)
    brute = _brute_force_centroid(peaks, fired)
    # The grid holds the peaks and the mid-points between them; every other kink of the
    # aggregate (where a term meets its cut level: at most 2 per term; where two
    # neighbours cross: at most 1 per pair; so at most 8) changes the slope by at most
    # 1 / w, w the narrowest peak spacing. The trapezoid rule over the interval of length
    # <= h holding such a kink errs by at most (1 / w) h^2 / 8 in area, so dA <= h^2 / w
    # in all, and the centroid moves by at most |int (x - c) e(x) dx| / (A - dA) <=
    # W dA / (A - dA), W the universe width. The most fired term alone, at level lam,
    # covers A >= lam (2 - lam) w >= lam w. Margin: 2.
    low, high = FuzzyOutput("p", peaks).universe
    width = min(peaks[1] - peaks[0], peaks[2] - peaks[1])
    h = (high - low) / (BRUTE_FORCE_SAMPLES - 1)
    area_error = h * h / width
    area_floor = max(fired) * width
    tolerance = 2.0 * (high - low) * area_error / (area_floor - area_error) + 1e-12
    assert abs(exact - brute) <= tolerance, (exact, brute, tolerance)
    assert low <= exact <= high


@pytest.mark.parametrize("index", range(3))
@pytest.mark.parametrize("level", [1.0, 0.37, 1e-6])
def test_lone_term_of_a_symmetric_partition_gives_its_peak(index: int, level: float) -> None:
    for peaks in ((0.25, 0.6, 0.95), (-1.0, 0.5, 2.0), (0.2, 0.6, 1.0)):
        fired = [0.0, 0.0, 0.0]
        fired[index] = level
        assert centroid_of_partition(peaks, fired) == pytest.approx(peaks[index], abs=1e-12)


@pytest.mark.parametrize("level", [1.0, 0.4])
def test_lone_outer_term_of_an_uneven_partition_gives_its_peak(level: float) -> None:
    peaks = (0.1, 0.3, 0.7)
    assert centroid_of_partition(peaks, [level, 0.0, 0.0]) == pytest.approx(0.1, abs=1e-12)
    assert centroid_of_partition(peaks, [0.0, 0.0, level]) == pytest.approx(0.7, abs=1e-12)
    # The lone middle triangle (0.1, 0.3, 0.7) at full height: its centroid, not its peak.
    assert centroid_of_partition(peaks, [0.0, 1.0, 0.0]) == pytest.approx(1.1 / 3.0, abs=1e-12)


# --------------------------------------------------------------------------- monotonicity


def test_weights_are_monotone_in_the_table_2_directions() -> None:
    """Far -> k_T grows; beta grows -> k_C shrinks (Table 2's rows and columns are sorted)."""
    distances = np.linspace(*RULE_BASE.inputs["min_distance"].universe, 201)
    betas = np.linspace(*RULE_BASE.inputs["beta"].universe, 201)
    table = np.array([[INFERENCE.weights(float(d), float(b)) for b in betas] for d in distances])
    k_t, k_c = table[:, :, 0], table[:, :, 1]
    assert np.all(np.diff(k_t, axis=0) >= -1e-12)  # along min_distance, beta fixed
    assert np.all(np.diff(k_c, axis=1) <= 1e-12)  # along beta, distance fixed
    # ... and neither is constant: they span their outputs' lone-term values.
    assert k_t.max() - k_t.min() > 0.5
    assert k_c.max() - k_c.min() > 0.5


def test_weights_clamp_inputs_to_their_universes() -> None:
    (d_low, d_high), (b_low, b_high) = (
        RULE_BASE.inputs["min_distance"].universe,
        RULE_BASE.inputs["beta"].universe,
    )
    assert INFERENCE.weights(d_high + 5.0, b_low - 5.0) == INFERENCE.weights(d_high, b_low)
    assert INFERENCE.weights(math.inf, 0.2) == INFERENCE.weights(d_high, 0.2)
    assert INFERENCE.weights(-1.0, b_high + 1.0) == INFERENCE.weights(d_low, b_high)


# --------------------------------------------------------------------------- validation


def test_shipped_document_round_trips() -> None:
    assert RuleBase.from_mapping(_shipped_document()) == RULE_BASE


def _unknown_rule_term(document: dict[str, Any]) -> None:
    document["rules"][4]["min_distance"] = "close"


def _unordered_trapezoid(document: dict[str, Any]) -> None:
    a, b, c, d = document["inputs"]["beta"]["terms"]["small"]
    document["inputs"]["beta"]["terms"]["small"] = [a, b, d, c]


def _peaks_not_increasing(document: dict[str, Any]) -> None:
    peaks = document["outputs"]["k_T"]["peaks"]
    peaks["small"], peaks["medium"] = peaks["medium"], peaks["small"]


def _peaks_unevenly_spaced(document: dict[str, Any]) -> None:
    document["outputs"]["k_C"]["peaks"]["small"] = 0.25


def _missing_rule(document: dict[str, Any]) -> None:
    del document["rules"][7]


def _duplicated_instead_of_missing(document: dict[str, Any]) -> None:
    document["rules"][2] = copy.deepcopy(document["rules"][1])


def _gap_between(name: str, first: str, second: str) -> Any:
    def edit(document: dict[str, Any]) -> None:
        terms = document["inputs"][name]["terms"]
        a, b, c, _ = terms[first]
        # Make ``first`` end before ``second`` starts, everything else unchanged.
        new_d = c + 0.25 * (terms[second][1] - c)
        terms[first] = [a, b, c, new_d]
        terms[second][0] = new_d + 0.5 * (terms[second][1] - new_d)

    return edit


def _short_of_the_end(name: str, term: str, corner: int) -> Any:
    """Pull the shoulder term ``term`` in from its universe end, leaving that end uncovered."""

    def edit(document: dict[str, Any]) -> None:
        points = document["inputs"][name]["terms"][term]
        inner = points[2] if corner == 0 else points[1]
        end = points[corner]
        pulled = end + 0.5 * (inner - end)
        if corner == 0:
            points[0] = points[1] = pulled
        else:
            points[2] = points[3] = pulled

    return edit


def _set(path: list[str | int], value: Any) -> Any:
    """Set the value at ``path`` (``None``: delete it)."""

    def edit(document: dict[str, Any]) -> None:
        target: Any = document
        for key in path[:-1]:
            target = target[key]
        if value is None:
            del target[path[-1]]
        else:
            target[path[-1]] = value

    return edit


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (
            _set(["inputs", "min_distance", "terms", "near", 1], math.nan),
            "inputs.min_distance.terms.near[1]",
        ),
        (_set(["inputs", "beta", "terms", "big"], [0.35, 0.8, 3.2]), "inputs.beta.terms.big"),
        (_set(["inputs", "beta", "universe"], [-1.0, "pi"]), "inputs.beta.universe[1]"),
        (_set(["inputs", "beta", "terms"], {}), "inputs.beta.terms"),
        (_set(["inputs", "min_distance"], None), "inputs.min_distance"),
        (_set(["outputs", "k_C", "peaks", "big"], math.inf), "outputs.k_C.peaks.big"),
        (_set(["outputs", "k_T", "peaks", "huge"], 2.0), "outputs.k_T.peaks.huge"),
        (_set(["rules", 0, "k_T"], "huge"), "rules[0].k_T"),
        (_set(["rules", 3, "beta"], None), "rules[3].beta"),
        (_set(["rules"], []), "rules"),
        (_set(["defuzzify"], "mean of maxima"), "defuzzify"),
        (_set(["inputs", "beta", "universe"], [1.0, -1.0]), "inputs.beta.universe"),
        (_unknown_rule_term, "rules[4].min_distance"),
        (_unordered_trapezoid, "inputs.beta.terms.small"),
        (_peaks_not_increasing, "outputs.k_T.peaks"),
        (_peaks_unevenly_spaced, "outputs.k_C.peaks"),
        (_missing_rule, "rules"),
        (_duplicated_instead_of_missing, "rules"),
        (_gap_between("min_distance", "near", "middle"), "inputs.min_distance.terms"),
        (_gap_between("beta", "small", "medium"), "inputs.beta.terms"),
        (_short_of_the_end("min_distance", "far", 3), "inputs.min_distance.terms"),
        (_short_of_the_end("min_distance", "near", 0), "inputs.min_distance.terms"),
        (_short_of_the_end("beta", "big", 3), "inputs.beta.terms"),
    ],
)
def test_broken_rule_file_names_the_field(edit: Any, field: str) -> None:
    document = _shipped_document()
    edit(document)
    with pytest.raises(ConfigError) as raised:
        RuleBase.from_mapping(document)
    assert raised.value.field == field
