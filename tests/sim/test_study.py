"""The issue's claim on generated scenarios, with the scalar simulation: in fuzzy mode every
waypoint is passed within tolerance, with no collision and no stop (slow: a few minutes)."""

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
@pytest.mark.xfail(
    strict=True,
    reason="gen-2026-164-doorstep stops once: the arm, ahead of the plan, crawls past the "
    "waypoint unvisited and must turn back to it (docs/study.md, 'What is left')",
)
def test_fuzzy_never_stops() -> None:
    assert [name for name, _, m in _study() if m.stops] == []
