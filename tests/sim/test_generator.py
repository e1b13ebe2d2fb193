"""Generated scenarios: the same seed gives the same study, and every scenario is one a user
could have written (same checks) that keeps its waypoints clear of the obstacle."""

from __future__ import annotations

import itertools
import statistics

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controller.planner import check_plan, plan_of
from protocol.kinematics import inverse, reach_radii
from protocol.scenario import Mode, Scenario, parse_scenario, scenario_document
from sim.generator import (
    HEIGHT_GAP,
    MIN_SPACING,
    SETTLE_TIME,
    WAYPOINT_CLEARANCE,
    Case,
    case_of,
    generate_scenario,
    generate_scenario_at,
    generate_scenarios,
    waypoints_clear,
)

STUDY = generate_scenarios(3 * len(Case), seed=11)


def test_the_same_seed_gives_the_same_scenarios() -> None:
    assert generate_scenarios(len(Case), seed=11) == STUDY[: len(Case)]
    assert generate_scenarios(len(Case), seed=12) != STUDY[: len(Case)]


def test_a_scenario_depends_on_its_seed_and_index_only() -> None:
    assert generate_scenario_at(11, 9) == STUDY[9]


def test_the_mode_is_the_one_asked_for() -> None:
    assert {scenario.mode for scenario in STUDY} == {Mode.FUZZY}
    conventional = generate_scenarios(2, seed=11, mode=Mode.CONVENTIONAL)
    assert [s.mode for s in conventional] == [Mode.CONVENTIONAL] * 2
    assert [s.with_mode(Mode.FUZZY) for s in conventional] == STUDY[:2]


def test_every_case_is_present_and_named() -> None:
    assert [case_of(s) for s in STUDY[: len(Case)]] == list(Case)
    for index, scenario in enumerate(STUDY):
        assert scenario.name == f"gen-11-{index}-{case_of(scenario).value}"


def test_a_generated_scenario_passes_the_checks_of_a_scenario_file() -> None:
    for scenario in STUDY:
        reread = parse_scenario(scenario_document(scenario), default_name=scenario.name)
        check_plan(reread)
        assert reread.waypoints == scenario.waypoints
        assert reread.obstacle == scenario.obstacle


def test_runs_last_about_ten_seconds() -> None:
    durations = [s.duration for s in generate_scenarios(70, seed=3)]
    assert 7.0 <= statistics.median(durations) <= 15.0
    assert min(durations) >= 1.0 + SETTLE_TIME


def test_the_stretched_case_comes_near_the_singularity() -> None:
    stretched = [s for s in STUDY if case_of(s) is Case.STRETCHED]
    for scenario in stretched:
        bends = [
            abs(inverse(scenario.robot, w.x, w.y, w.z, scenario.elbow)[1])
            for w in scenario.waypoints
        ]
        assert min(bends) < np.radians(12.0)


def test_the_below_case_passes_over_the_obstacle() -> None:
    for scenario in (s for s in STUDY if case_of(s) is Case.BELOW):
        assert scenario.obstacle is not None
        top = scenario.obstacle.height + scenario.obstacle.inflation
        assert min(w.z for w in scenario.waypoints) > top


def test_the_across_case_puts_the_obstacle_on_the_planned_path() -> None:
    for scenario in (s for s in STUDY if case_of(s) is Case.ACROSS):
        assert scenario.obstacle is not None
        assert min(_planned_clearances(scenario)) < 0.0


def test_waypoints_clear_is_the_rule_the_generator_keeps() -> None:
    scenario = STUDY[1]
    assert waypoints_clear(scenario)
    assert not waypoints_clear(scenario, room=1.0)  # no waypoint is a metre clear


@settings(max_examples=25)
@given(seed=st.integers(0, 2**32 - 1), case=st.sampled_from(list(Case)))
def test_every_draw_keeps_the_generator_rules(seed: int, case: Case) -> None:
    scenario = generate_scenario(np.random.default_rng(seed), case, "drawn")
    check_plan(scenario)
    assert waypoints_clear(scenario, WAYPOINT_CLEARANCE)
    assert 2 <= len(scenario.waypoints) <= 6
    points = [(w.x, w.y, w.z) for w in scenario.waypoints]
    assert all(
        np.linalg.norm(np.subtract(a, b)) >= MIN_SPACING for a, b in itertools.pairwise(points)
    )
    low, high = reach_radii(scenario.robot)
    assert all(low <= np.hypot(x, y) <= high for x, y, _ in points)
    obstacle = scenario.obstacle
    assert obstacle is not None
    top = obstacle.height + obstacle.inflation
    heights = _planned_heights(scenario)
    assert min(heights) > top + HEIGHT_GAP - 1e-9 or max(heights) < top - HEIGHT_GAP + 1e-9


def _planned_heights(scenario: Scenario) -> list[float]:
    plan = plan_of(scenario)
    times = np.linspace(scenario.waypoints[0].t, scenario.waypoints[-1].t, 400)
    return [plan.evaluate(float(t))[0][2] for t in times]


def _planned_clearances(scenario: Scenario) -> list[float]:
    assert scenario.obstacle is not None
    plan = plan_of(scenario)
    times = np.linspace(scenario.waypoints[0].t, scenario.waypoints[-1].t, 400)
    return [scenario.obstacle.clearance(*plan.evaluate(float(t))[0][:2]) for t in times]


@pytest.mark.parametrize("bad", [{"seed": -1, "index": 0}, {"seed": 0, "index": -1}])
def test_negative_seeds_and_indices_are_refused(bad: dict[str, int]) -> None:
    with pytest.raises(ValueError, match="must not be negative"):
        generate_scenario_at(**bad)
