"""The issue's claim on generated scenarios, with the scalar simulation: in fuzzy mode every
waypoint is passed within tolerance, with no collision and no stop (the whole study is slow: a
few minutes; the scenarios it once failed are not)."""

from __future__ import annotations

import math
from functools import cache
from multiprocessing import get_context

import pytest

from protocol.scenario import Mode
from sim.generator import generate_scenario_at, waypoints_clear
from sim.measures import WAYPOINT_TOLERANCE, Measures
from sim.simulation import simulate

SEED = 2026
COUNT = 210
WORKERS = 2
"""The machines have 2 cores, shared."""


def _run(index: int) -> tuple[str, bool, Measures]:
    scenario = generate_scenario_at(SEED, index, Mode.FUZZY)
    return scenario.name, waypoints_clear(scenario), simulate(scenario).measures


@cache
def _study() -> tuple[tuple[str, bool, Measures], ...]:
    with get_context("fork").Pool(WORKERS) as pool:
        return tuple(pool.map(_run, range(COUNT), chunksize=5))


@pytest.mark.slow
def test_fuzzy_keeps_every_waypoint_without_collision() -> None:
    results = _study()
    assert all(clear for _, clear, _ in results)  # the condition holds for all
    collided = [name for name, _, m in results if not m.collision_free]
    missed = [name for name, _, m in results if m.max_waypoint_miss > WAYPOINT_TOLERANCE]
    unfinished = [name for name, _, m in results if math.isnan(m.completion_time)]
    assert (collided, missed, unfinished) == ([], [], [])


@pytest.mark.slow
def test_fuzzy_never_stops() -> None:
    assert [name for name, _, m in _study() if m.stops] == []


HARD_CASES = [
    pytest.param(seed, index, id=f"gen-{seed}-{index}")
    for seed, index, _was in (
        (0, 288, "collided: k_C fell to 0 beside a thin obstacle, the arm looping round"),
        (0, 339, "stopped: overshot the waypoint the plan waited at, turned back"),
        (0, 528, "stopped: beside the waypoint, ahead of the plan"),
        (0, 556, "never finished: the plan waited longer than the run's settling time"),
        (0, 701, "missed by 2.9 mm: the plan moved on from an arm beside the waypoint"),
        (0, 710, "stopped three times at a doorstep waypoint"),
        (0, 745, "stopped: beside the waypoint, ahead of the plan"),
        (0, 871, "stopped: beside the waypoint, ahead of the plan"),
        (0, 918, "stopped: overshot the waypoint while the plan waited, then crawled"),
        (0, 945, "never finished: AO circled an obstacle beyond the last waypoint"),
        (2026, 164, "stopped: crawled past the waypoint unvisited"),
        (2026, 211, "stopped: beside the waypoint, ahead of the plan"),
        (2026, 556, "missed by 2.6 mm: stalled 4 mm beside the waypoint, ahead of the plan"),
        (2026, 653, "never finished: AO circled an obstacle beyond the last waypoint"),
        (2026, 836, "missed by 2.4 mm: the reference stood past the waypoint it waited for"),
        (2026, 840, "never finished: AO circled an obstacle beyond the last waypoint"),
        (2026, 934, "stopped, and missed by 2.1 mm"),
        # Before the approach limit (ControlLaw._approach_limited); found on 10,000 of seed 0.
        (0, 5173, "collided 1.0 mm: PT's and AO's turn rates cancelled, heading at the obstacle"),
        (0, 5547, "collided: the same, at a doorstep"),
        (0, 7252, "collided 3.9 mm: the same"),
        (0, 8422, "collided 3.9 mm: the same"),
        (0, 8999, "collided: the same, near the boundary"),
        (1, 987, "collided 2.0 mm: the same; then never finished, AO's long way round"),
        # Before AO chose its side afresh at each waypoint passed (ControlLaw._mark_reached):
        # the side chosen on an earlier segment took the arm the long way round.
        (0, 1312, "never finished: circled the obstacle to a last waypoint at its doorstep"),
        (0, 5511, "never finished: the plan waited 3.3 s for the long way round"),
        (0, 5734, "never finished: the plan waited 3.6 s for the long way round"),
        (0, 8459, "never finished: circled the obstacle to a last waypoint at its doorstep"),
        # Before PASSED was 1.9 mm (1.5): passed 1.6 to 1.8 mm off, slid back, stopped.
        (1, 488, "stopped: passed 1.8 mm off near the stretched arm, slid back"),
        (2026, 271, "stopped: passed 1.6 mm off (1.7 mm below) near the stretched arm"),
        (0, 2425, "stopped: passed 1.6 mm off at a doorstep, slid back"),
        (0, 4672, "stopped: passed 3.8 mm off, ahead of the plan, slid back and turned"),
        # Before the reach limit (ControlLaw._reach_limited): carried to full stretch 2 mm
        # beyond a waypoint near it, slid back, stopped.
        (1, 138, "stopped: passed 2.0 mm off at full stretch, slid back"),
        (0, 9476, "stopped: passed 2.1 mm off at full stretch (the elbow flipped), slid back"),
        # Before AO gave way wherever the obstacle is beyond p_j on every segment, not only
        # the last (ControlLaw._at_waypoint).
        (0, 8669, "never finished: AO went round an obstacle beyond an inner waypoint, 3.5 s"),
        # Before the height loop led an arm ahead of the plan (ControlLaw._height_lead).
        (0, 5519, "stopped twice: over the waypoint in the plane, 11 mm above it, came down"),
        # Before the plan waited at a passed waypoint's time until the arm had been to it
        # (ControlLaw._wanted_rate); found on 10,000 of seed 11, never run before.
        (11, 4085, "missed by 2.02 mm: the plan crept on while the final approach came in"),
        # Before the height led near the waypoint from a few millimetres ahead
        # (ControlLaw._height_lead); found on seeds 13, 17, 19, 23 and 29, each never run
        # before.
        (13, 3580, "stopped twice: over the waypoint in the plane, 3.7 mm below, held there"),
        (17, 5736, "stopped twice: reached a planned rest 0.13 s early, waited over it"),
        (23, 3281, "stopped: on the waypoint in the plane 0.14 s early, 1.75 mm above it"),
        (19, 7115, "stopped: on the waypoint in the plane 0.26 s early, 1.3 mm below it"),
        (29, 136, "stopped: on the waypoint in the plane 0.22 s early, 1.65 mm below it"),
        (23, 2691, "stopped: came onto it from beyond, 1.3 mm above; the loop helps it more"),
        # Before the final approach looped round a waypoint it would have come onto against
        # the plan (ControlLaw._final_approach); found on seeds 7, 11 and 13, each never run
        # before.
        (11, 4651, "stopped: came onto the waypoint from beyond it, turned round on it"),
        (13, 2173, "stopped: the same"),
        (13, 248, "stopped: the same where the plan itself turns 160 degrees"),
        (7, 3048, "stopped: passed 2.08 mm off, overshot by 3 mm and was slid back"),
        # Seed 19, never run before this change: three more of that kind.
        (19, 696, "stopped: came onto the waypoint from beyond it, turned round on it"),
        (19, 8214, "stopped: the same"),
        (19, 8816, "stopped: the same (not counted by the batch: measures' block bug)"),
        # Seeds 23 and 29, never run before this change: three more.
        (23, 5295, "stopped: came onto the waypoint from beyond it, turned round on it"),
        (29, 1914, "stopped: the same"),
        (29, 5204, "stopped twice: the same"),
    )
]


@pytest.mark.parametrize(("seed", "index"), HARD_CASES)
def test_fuzzy_holds_on_the_scenarios_it_once_failed(seed: int, index: int) -> None:
    """Each failed a must-hold before one of the changes of docs/study.md (the final
    approach, the clear way, the approach limit, AO's side chosen afresh, PASSED, the reach
    limit, the height lead, the plan waiting until the waypoint is done, the loop): all are
    reachable, 20 mm clear of the inflated obstacle."""
    scenario = generate_scenario_at(seed, index, Mode.FUZZY)
    assert waypoints_clear(scenario)
    measures = simulate(scenario).measures
    assert measures.collision_free, measures.min_clearance
    assert measures.stops == 0
    assert measures.max_waypoint_miss <= WAYPOINT_TOLERANCE
    assert not math.isnan(measures.completion_time)
