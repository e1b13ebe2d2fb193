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
    "reference/fuzzy": "1c49e5b3a747b456",
    "reference/conventional": "dc2de1fd6630c731",
    "pass_left/fuzzy": "8751b7fc5026378f",
    "pass_left/conventional": "1dfcebfe35a495a0",
    "long_wall/fuzzy": "e8f975a2600c9789",
    "long_wall/conventional": "1ecd925819e97e11",
    "over_the_top/fuzzy": "7ecbee0dea1d840b",
    "over_the_top/conventional": "7ecbee0dea1d840b",
    "no_obstacle/fuzzy": "7ecbee0dea1d840b",
    "no_obstacle/conventional": "7ecbee0dea1d840b",
    "endurance/fuzzy": "a612d26de455de3c",
    "endurance/conventional": "ef94f989b6cb59f4",
    "gen-0-0-open/fuzzy": "4866404e659146db",
    "gen-0-0-open/conventional": "6eabda6c365a6935",
    "gen-0-1-across/fuzzy": "4a40762e754e47a7",
    "gen-0-1-across/conventional": "dfbc7234efcb0951",
    "gen-0-2-back_across/fuzzy": "f47789f69a2fd64b",
    "gen-0-2-back_across/conventional": "164b39a3cbc56be4",
    "gen-0-3-doorstep/fuzzy": "d7eabe9b9a92befb",
    "gen-0-3-doorstep/conventional": "1b58da6fa9df383c",
    "gen-0-4-boundary/fuzzy": "77474974b51f764e",
    "gen-0-4-boundary/conventional": "d4fa52ef4a0aeb7c",
    "gen-0-5-stretched/fuzzy": "5aaee3cf11bb3299",
    "gen-0-5-stretched/conventional": "fe387d757a94db2f",
    "gen-0-6-below/fuzzy": "4c58dd60f6c16a68",
    "gen-0-6-below/conventional": "4c58dd60f6c16a68",
    "gen-0-7-open/fuzzy": "083b24eb5a19215b",
    "gen-0-7-open/conventional": "083b24eb5a19215b",
    "gen-11-4651-doorstep/fuzzy": "0e9b7f894c35d07f",
    "gen-11-4651-doorstep/conventional": "21b1f4fc37cca791",
    "gen-13-2173-doorstep/fuzzy": "db2bb07bdae9ba00",
    "gen-13-2173-doorstep/conventional": "63c5132205be192f",
    "gen-13-248-doorstep/fuzzy": "7fdf1191aeacc20e",
    "gen-13-248-doorstep/conventional": "69369580978b3902",
    "gen-7-3048-doorstep/fuzzy": "53a7062eb04639a9",
    "gen-7-3048-doorstep/conventional": "18d6df5c7ea7a0a1",
    "gen-0-5519-doorstep/fuzzy": "ef94d5b7a9223982",
    "gen-0-5519-doorstep/conventional": "3fcd4e8f398ea878",
    "gen-13-3580-doorstep/fuzzy": "21f20d23f32f5d62",
    "gen-13-3580-doorstep/conventional": "cc1bde7a16052254",
    "gen-1-138-stretched/fuzzy": "7508f9f2255bcb0f",
    "gen-1-138-stretched/conventional": "d205439555d384e4",
    "gen-0-9476-stretched/fuzzy": "902adbab2df03f12",
    "gen-0-9476-stretched/conventional": "b4cdfd9b351c65dc",
    "gen-0-5173-open/fuzzy": "fcdba719d7002b7a",
    "gen-0-5173-open/conventional": "758c3988d73c4102",
    "gen-1-987-open/fuzzy": "b3169063f8f7b470",
    "gen-1-987-open/conventional": "9b4c85e8318621ac",
    "gen-0-8669-doorstep/fuzzy": "6745e7cef9acdf2b",
    "gen-0-8669-doorstep/conventional": "8803045798b212fa",
    "gen-11-4085-boundary/fuzzy": "6d14895384aa9044",
    "gen-11-4085-boundary/conventional": "2a38380efe7d0de0",
    "random-11-0/fuzzy": "b9b17d5ad927ef8c",
    "random-11-0/conventional": "b9b17d5ad927ef8c",
    "random-11-1/fuzzy": "f1f29747bb232a70",
    "random-11-1/conventional": "d99b9383a3dbf482",
    "random-11-2/fuzzy": "97288d66ce01fefa",
    "random-11-2/conventional": "97288d66ce01fefa",
    "random-11-3/fuzzy": "605d6eb7421dd1ac",
    "random-11-3/conventional": "e4143b8851fda6ae",
    "random-11-4/fuzzy": "8647a0b426f65665",
    "random-11-4/conventional": "8647a0b426f65665",
    "random-11-5/fuzzy": "d9ee13559289b818",
    "random-11-5/conventional": "d9ee13559289b818",
    "random-11-6/fuzzy": "dd085761646e4e8b",
    "random-11-6/conventional": "dd085761646e4e8b",
    "random-11-7/fuzzy": "41e19944701579b7",
    "random-11-7/conventional": "8e4c0b8cb29bd6e1",
    "random-11-8/fuzzy": "9625bfb4b6437af4",
    "random-11-8/conventional": "03430cd4e96142e8",
    "random-11-9/fuzzy": "7d064b2a8cea36f3",
    "random-11-9/conventional": "40621787293be23b",
    "random-11-10/fuzzy": "e1e6271da6c50162",
    "random-11-10/conventional": "3c684a2e3de50771",
    "random-11-11/fuzzy": "0188872bb4541a88",
    "random-11-11/conventional": "dd760822fb86dc63",
    "random-11-12/fuzzy": "c028bc8c31c8d6ba",
    "random-11-12/conventional": "4b106da7a8da04ad",
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
