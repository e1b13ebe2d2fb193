"""The control law pinned tick by tick: the scalar simulation's per-tick logs hashed, and the
batch simulator's per-tick columns against the scalar law's on every fixture scenario.

The hashes were taken before the law was rewritten over one source for both drivers; a
change of behaviour, however small, changes them. They pin this platform's ``libm`` too: a
machine whose ``math.sin`` differs in a last bit would need them taken again.
"""

from __future__ import annotations

import hashlib
from functools import cache
from multiprocessing import get_context

import numpy as np
from support import NOT_LIBM_TOLERANCE, NUMPY_IS_LIBM
from test_batch import random_scenarios

from controller.runlog import RunLog
from protocol.scenario import Mode, Scenario, load_scenario
from sim.batch import trace_batch
from sim.generator import generate_scenario_at
from sim.simulation import simulate

PACKAGED = ("reference", "pass_left", "long_wall", "over_the_top", "no_obstacle", "endurance")
GENERATED = (
    *((0, index) for index in range(8)),
    # Scenarios that exercise the law's rarer parts: the loop, the height lead, the reach
    # and approach limits, the clear way, the plan waiting at a passed waypoint's time.
    (11, 4651),
    (13, 2173),
    (13, 248),
    (7, 3048),
    (0, 5519),
    (13, 3580),
    (1, 138),
    (0, 9476),
    (0, 5173),
    (1, 987),
    (0, 8669),
    (11, 4085),
)
WORKERS = 2
"""The machines have 2 cores, shared."""

PINNED = {
    "reference/fuzzy": "c3478a1fb9c1f99f",
    "reference/conventional": "f16ae9941a3531cc",
    "pass_left/fuzzy": "d76657abb9bf39d5",
    "pass_left/conventional": "897e8e085c9d5535",
    "long_wall/fuzzy": "e8f975a2600c9789",
    "long_wall/conventional": "1ecd925819e97e11",
    "over_the_top/fuzzy": "7732cc4defe4f0de",
    "over_the_top/conventional": "7732cc4defe4f0de",
    "no_obstacle/fuzzy": "7732cc4defe4f0de",
    "no_obstacle/conventional": "7732cc4defe4f0de",
    "endurance/fuzzy": "94ba4f9e9b02e8a8",
    "endurance/conventional": "ef94f989b6cb59f4",
    "gen-0-0-open/fuzzy": "4866404e659146db",
    "gen-0-0-open/conventional": "6eabda6c365a6935",
    "gen-0-1-across/fuzzy": "4a40762e754e47a7",
    "gen-0-1-across/conventional": "56edd0ee52367585",
    "gen-0-2-back_across/fuzzy": "de43039e7639b36d",
    "gen-0-2-back_across/conventional": "348e189e0ff359c6",
    "gen-0-3-doorstep/fuzzy": "c19e656e3c34c579",
    "gen-0-3-doorstep/conventional": "55f554b17abb2acd",
    "gen-0-4-boundary/fuzzy": "731313f7a2837e0f",
    "gen-0-4-boundary/conventional": "5aaa539986ba2129",
    "gen-0-5-stretched/fuzzy": "5d1cfd41d6ff94c5",
    "gen-0-5-stretched/conventional": "589745c911da68e5",
    "gen-0-6-below/fuzzy": "4c58dd60f6c16a68",
    "gen-0-6-below/conventional": "4c58dd60f6c16a68",
    "gen-0-7-open/fuzzy": "520e98963d693d9d",
    "gen-0-7-open/conventional": "520e98963d693d9d",
    "gen-11-4651-doorstep/fuzzy": "82a75a2d9dc86bf2",
    "gen-11-4651-doorstep/conventional": "0b36fd69fe82e888",
    "gen-13-2173-doorstep/fuzzy": "459f4e52a217590e",
    "gen-13-2173-doorstep/conventional": "257f05b05a47b8e5",
    "gen-13-248-doorstep/fuzzy": "4becaa39206887e4",
    "gen-13-248-doorstep/conventional": "2b43216f167057e7",
    "gen-7-3048-doorstep/fuzzy": "5d1fcf0412e1e9c6",
    "gen-7-3048-doorstep/conventional": "c4d3a40af02d8690",
    "gen-0-5519-doorstep/fuzzy": "f3c43f8baa6101cb",
    "gen-0-5519-doorstep/conventional": "bca784cf0cceda2a",
    "gen-13-3580-doorstep/fuzzy": "8776619809c71969",
    "gen-13-3580-doorstep/conventional": "2556c4327365242c",
    "gen-1-138-stretched/fuzzy": "fd19a5352074704f",
    "gen-1-138-stretched/conventional": "e72b0060e4f01ee1",
    "gen-0-9476-stretched/fuzzy": "5feae40c93856eeb",
    "gen-0-9476-stretched/conventional": "2378e923ded9f14c",
    "gen-0-5173-open/fuzzy": "413be59bf2e47ac9",
    "gen-0-5173-open/conventional": "f2be86a13fede76c",
    "gen-1-987-open/fuzzy": "4415e5e5e1a14cb7",
    "gen-1-987-open/conventional": "83a62e4eb5ec7783",
    "gen-0-8669-doorstep/fuzzy": "938d28510dc15ca2",
    "gen-0-8669-doorstep/conventional": "a3ee1b4039fcc091",
    "gen-11-4085-boundary/fuzzy": "5b3683ce4fe6c000",
    "gen-11-4085-boundary/conventional": "ecb48e03f754b52e",
    "random-11-0/fuzzy": "14e92511050804a6",
    "random-11-0/conventional": "14e92511050804a6",
    "random-11-1/fuzzy": "9edc4a9f082d9c6a",
    "random-11-1/conventional": "5bc2135e3ac24b3d",
    "random-11-2/fuzzy": "b45227dd0f0cdfb0",
    "random-11-2/conventional": "b45227dd0f0cdfb0",
    "random-11-3/fuzzy": "a20e2cc11e7d84ea",
    "random-11-3/conventional": "4d5a8e2606f285c5",
    "random-11-4/fuzzy": "673c36643d54c98f",
    "random-11-4/conventional": "673c36643d54c98f",
    "random-11-5/fuzzy": "eb852924b5aaa0a8",
    "random-11-5/conventional": "eb852924b5aaa0a8",
    "random-11-6/fuzzy": "ef9b7d2a20c06afc",
    "random-11-6/conventional": "ef9b7d2a20c06afc",
    "random-11-7/fuzzy": "6a1583899fd8b446",
    "random-11-7/conventional": "e13f21149f12d3d2",
    "random-11-8/fuzzy": "9625bfb4b6437af4",
    "random-11-8/conventional": "03430cd4e96142e8",
    "random-11-9/fuzzy": "7d064b2a8cea36f3",
    "random-11-9/conventional": "40621787293be23b",
    "random-11-10/fuzzy": "abb2584dd50831f8",
    "random-11-10/conventional": "2cfdfc115f376756",
    "random-11-11/fuzzy": "c91ecd6e44afdd94",
    "random-11-11/conventional": "e3d2063cfdeacda9",
    "random-11-12/fuzzy": "77edd4b3e42ccd28",
    "random-11-12/conventional": "8fcec0a5a6a7154f",
}
"""sha256 (first 16 hex digits) of each run's per-tick log, scenario/mode."""


@cache
def fixture_scenarios() -> list[Scenario]:
    """The packaged scenarios, the generated ones above and the batch tests' random ones."""
    packaged = [load_scenario(name) for name in PACKAGED]
    generated = [generate_scenario_at(seed, index) for seed, index in GENERATED]
    return packaged + generated + random_scenarios(13, seed=11)


def _scalar_log(job: tuple[int, Mode]) -> np.ndarray:
    index, mode = job
    return simulate(fixture_scenarios()[index], mode).log.data


@cache
def scalar_logs() -> dict[tuple[str, Mode], np.ndarray]:
    """Every fixture scenario's per-tick log in both modes, from the scalar simulation."""
    scenarios = fixture_scenarios()
    jobs = [(index, mode) for index in range(len(scenarios)) for mode in Mode]
    with get_context("fork").Pool(WORKERS) as pool:
        logs = pool.map(_scalar_log, jobs, chunksize=2)
    return {
        (scenarios[index].name, mode): log for (index, mode), log in zip(jobs, logs, strict=True)
    }


def digest(log: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(log).tobytes()).hexdigest()[:16]


def test_the_scalar_laws_per_tick_logs_are_those_pinned() -> None:
    got = {f"{name}/{mode.value}": digest(log) for (name, mode), log in scalar_logs().items()}
    changed = {
        key: (value, PINNED.get(key)) for key, value in got.items() if PINNED.get(key) != value
    }
    assert not changed, f"per-tick logs changed (got, pinned): {changed}"
    assert set(got) == set(PINNED)


def test_the_batch_equals_the_scalar_law_tick_by_tick() -> None:
    """Every column the batch logs, on every tick of every fixture scenario in both modes:
    bit for bit where numpy's transcendental functions are libm's to the last bit (as on
    these machines); on a CPU where numpy's own atan2, acos or exp are an ulp off libm's
    (``test_batch``'s check allows that), to 1e-9."""
    scenarios = fixture_scenarios()
    modes = [mode for _ in scenarios for mode in Mode]
    traces = trace_batch([scenario for scenario in scenarios for _ in Mode], modes)
    logs = scalar_logs()
    for index, trace in enumerate(traces):
        name, mode = scenarios[index // 2].name, modes[index]
        log = RunLog.from_array(logs[(name, mode)])
        for column, values in trace.items():
            where = f"{name}/{mode.value}: {column}"
            if NUMPY_IS_LIBM:
                np.testing.assert_array_equal(values, log[column], err_msg=where)
            else:
                np.testing.assert_allclose(
                    values,
                    log[column],
                    rtol=NOT_LIBM_TOLERANCE,
                    atol=NOT_LIBM_TOLERANCE,
                    err_msg=where,
                )
