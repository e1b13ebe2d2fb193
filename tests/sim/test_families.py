"""The generator's families beyond the mix: each reproducible, each scenario one a user could
have written, each made to test what it is named for; the mix as it was; the held-out part
refused unless asked for by name."""

from __future__ import annotations

import itertools
import json
import math
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from controller.planner import check_plan
from controller.task_rules import check_task
from protocol.errors import ConfigError, NoWayRoundError
from protocol.kinematics import reach_radii
from protocol.scenario import (
    Scenario,
    Waypoint,
    parse_scenario,
    scenario_document,
    task_document,
)
from sim.compare import main
from sim.edges import Edge
from sim.generator import (
    FAMILIES,
    HELD_OUT_SEEDS,
    MIN_SPACING,
    WAYPOINT_CLEARANCE,
    Family,
    Kind,
    generate_scenario_at,
    generate_scenarios,
    waypoints_clear,
)
from sim.passability import FreeSpace, Verdict
from sim.study.jobs import generate_chunk
from sim.study.pool import Processes

NEW = [family for family in Family if family not in (Family.MIX, Family.HELD_OUT)]
EDGES = {Family(edge.value) for edge in Edge}
"""Half of their tasks break a rule by design (``tests/sim/test_edges.py``)."""
PASSABLE = [family for family in NEW if family is not Family.WIDE and family not in EDGES]
"""The families whose every segment has a way round (wide offers some that have none)."""
COUNT = 6
"""Scenarios of each family checked (the user family's three kinds twice)."""


@cache
def drawn(family: Family, seed: int = 4) -> tuple[Scenario, ...]:
    return tuple(generate_scenarios(COUNT, seed, family=family))


def default_settle_time() -> float:
    """What a scenario file that gives none runs for after its last waypoint."""
    points = [{"t": t, "x": 0.4, "y": y, "z": 0.3} for t, y in ((0.0, 0.0), (1.0, 0.1))]
    return parse_scenario({"waypoints": points}).settle_time


def segments(scenario: Scenario) -> list[tuple[Waypoint, Waypoint]]:
    return list(itertools.pairwise(scenario.waypoints))


def speed(first: Waypoint, second: Waypoint) -> float:
    distance = math.dist((first.x, first.y, first.z), (second.x, second.y, second.z))
    return distance / (second.t - first.t)


def crossed(scenario: Scenario) -> int:
    """How many segments' straight lines pass through the inflated obstacle (sampled)."""
    obstacle = scenario.obstacle
    assert obstacle is not None
    shares = np.linspace(0.0, 1.0, 400)
    return sum(
        any(
            obstacle.contains(a.x + s * (b.x - a.x), a.y + s * (b.y - a.y)) for s in shares.tolist()
        )
        for a, b in segments(scenario)
    )


def reaches_out_to(scenario: Scenario) -> float:
    """The farthest any point of the inflated section is from the base axis (finely sampled)."""
    obstacle = scenario.obstacle
    assert obstacle is not None
    a, b = obstacle.semi_axes
    t = np.linspace(0.0, 2.0 * math.pi, 20_000)
    cos, sin = math.cos(obstacle.yaw), math.sin(obstacle.yaw)
    x = obstacle.x + cos * a * np.cos(t) - sin * b * np.sin(t)
    y = obstacle.y + sin * a * np.cos(t) + cos * b * np.sin(t)
    return float(np.hypot(x, y).max())


def test_the_mix_is_what_it_was() -> None:
    """Scenarios 0-13 of seed 0 (each case twice) as the code before the families gave them."""
    before = json.loads((Path(__file__).parent / "mix_seed0.json").read_text())
    now = [task_document(generate_scenario_at(0, index)) for index in range(len(before))]
    assert now == before
    assert generate_scenario_at(0, 3, family=Family.MIX) == generate_scenario_at(0, 3)


@pytest.mark.parametrize("family", NEW, ids=lambda f: f.value)
def test_a_family_is_reproducible_scenario_by_scenario(family: Family) -> None:
    study = drawn(family)
    assert generate_scenario_at(4, 5, family=family) == study[5]
    assert generate_scenarios(2, seed=5, family=family) != list(study[:2])
    names = [
        f"{family.value}-4-{index}-{FAMILIES[family][index % len(FAMILIES[family])].case.value}"
        for index in range(COUNT)
    ]
    sides = ("-inside", "-outside") if family in EDGES else ("",)
    for scenario, name in zip(study, names, strict=True):  # an edge task says its rule's side
        assert scenario.name in {name + side for side in sides}


@pytest.mark.parametrize("family", PASSABLE, ids=lambda f: f.value)
def test_a_familys_scenarios_pass_the_checks_and_keep_the_generators_rules(
    family: Family,
) -> None:
    for scenario in drawn(family):
        reread = parse_scenario(scenario_document(scenario), default_name=scenario.name)
        check_plan(reread)
        assert reread.waypoints == scenario.waypoints
        assert waypoints_clear(scenario, WAYPOINT_CLEARANCE)
        assert all(
            math.dist((a.x, a.y, a.z), (b.x, b.y, b.z)) >= MIN_SPACING
            for a, b in segments(scenario)
        )
        assert scenario.settle_time == default_settle_time() == 1.0
        space = FreeSpace(scenario)
        ways = [space.verdict(i) for i in range(len(scenario.waypoints) - 1)]
        assert ways == [Verdict.WAY] * len(ways)


def test_inner_has_the_obstacles_edge_near_the_inner_limit() -> None:
    for scenario in drawn(Family.INNER):
        assert scenario.obstacle is not None
        inner = reach_radii(scenario.robot)[0]
        assert abs(scenario.obstacle.clearance(0.0, 0.0) - inner) <= 0.03
        assert crossed(scenario) >= 1


def test_outer_has_the_obstacles_edge_near_the_full_reach() -> None:
    for scenario in drawn(Family.OUTER):
        outer = reach_radii(scenario.robot)[1]
        assert abs(outer - reaches_out_to(scenario)) <= 0.03 + 1e-6
        assert crossed(scenario) >= 1


def test_fast_has_a_segment_faster_than_users_wrote() -> None:
    for scenario in drawn(Family.FAST):
        speeds = [speed(*pair) for pair in segments(scenario)]
        assert max(speeds) > 0.35
        assert max(speeds) <= 0.4 + 1e-3  # rounding to 0.1 mm and 1 ms


def test_multi_has_the_obstacle_across_two_segments_or_more() -> None:
    for scenario in drawn(Family.MULTI):
        assert crossed(scenario) >= 2


def test_user_writes_as_the_users_did() -> None:
    study = drawn(Family.USER)
    assert [s.name.rsplit("-", 1)[1] for s in study[:3]] == ["across", "doorstep", "back_across"]
    for scenario in study:
        assert 3 <= len(scenario.waypoints) <= 6
        assert all(speed(*pair) <= 0.35 + 1e-3 for pair in segments(scenario))
        assert crossed(scenario) >= 1 or scenario.name.endswith("doorstep")


def test_the_held_out_part_is_refused_unless_asked_for() -> None:
    with pytest.raises(ConfigError, match="held out"):
        generate_scenario_at(0, 0, family=Family.HELD_OUT)
    with pytest.raises(ConfigError, match="held out"):
        generate_scenario_at(HELD_OUT_SEEDS, 0, family=Family.INNER)
    with pytest.raises(ConfigError, match="held out"):
        generate_chunk(HELD_OUT_SEEDS + 7, [0])
    for argv in (["--family", "held_out"], ["--family", "user", "--seed", str(HELD_OUT_SEEDS)]):
        with pytest.raises(SystemExit) as refused:
            main([*argv, "-n", "1", "-q"])
        assert refused.value.code == 2


def test_the_held_out_part_generates_when_asked_for() -> None:
    """Generated only, never simulated: each of its kinds once, through the checks."""
    recipes = FAMILIES[Family.HELD_OUT]
    assert {recipe.case for recipe in recipes} >= set(Kind)
    for index in range(len(recipes)):
        scenario = generate_scenario_at(0, index, family=Family.HELD_OUT, held_out=True)
        check_plan(scenario)
        assert scenario.name.startswith("held_out-0-")


def test_a_chunk_is_of_its_family() -> None:
    assert generate_chunk(4, [1, 2], Family.MULTI) == [
        (1, drawn(Family.MULTI)[1], None),
        (2, drawn(Family.MULTI)[2], None),
    ]


def test_wide_offers_tasks_with_no_way_round_and_worker_processes_return_the_refusals() -> None:
    """The study generates on worker processes; a refusal comes back to the parent whole (a
    NoWayRoundError once stopped the pool: it could not be rebuilt from its arguments)."""
    indices = list(range(10))
    expected: dict[int, str] = {}
    for index in indices:
        try:
            check_task(generate_scenario_at(0, index, family=Family.WIDE))
        except NoWayRoundError as error:
            expected[index] = str(error)
    assert 0 < len(expected) < len(indices)
    executor = Processes(2, lambda _: None)
    try:
        chunks = list(
            executor.map(
                generate_chunk, [(0, indices[:5], Family.WIDE), (0, indices[5:], Family.WIDE)]
            )
        )
    finally:
        executor.close()
    refused = {
        index: refusal for chunk in chunks for index, _, refusal in chunk if refusal is not None
    }
    assert all(isinstance(refusal, NoWayRoundError) for refusal in refused.values())
    assert {index: str(refusal) for index, refusal in refused.items()} == expected
