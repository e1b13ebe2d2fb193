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
    "reference/fuzzy": "c008fbef0a8ec575",
    "reference/conventional": "508f0db6e6e101b9",
    "pass_left/fuzzy": "7221ed1031764283",
    "pass_left/conventional": "8960f2cfb4ebaa79",
    "long_wall/fuzzy": "49199d1284b94b08",
    "long_wall/conventional": "e3e9edd1b8354a81",
    "over_the_top/fuzzy": "429f1b73b10dc967",
    "over_the_top/conventional": "429f1b73b10dc967",
    "no_obstacle/fuzzy": "429f1b73b10dc967",
    "no_obstacle/conventional": "429f1b73b10dc967",
    "endurance/fuzzy": "a0c3ea1bed7f7c59",
    "endurance/conventional": "a27b86261a7b72ff",
    "gen-0-0-open/fuzzy": "b3049fcda4a1cd83",
    "gen-0-0-open/conventional": "36ed40d541a50aa2",
    "gen-0-1-across/fuzzy": "e5279fea58718183",
    "gen-0-1-across/conventional": "d74759ef13bb8ed5",
    "gen-0-2-back_across/fuzzy": "0ae25230f7c0b932",
    "gen-0-2-back_across/conventional": "40403c53a92b86c0",
    "gen-0-3-doorstep/fuzzy": "710b0a2737e96a37",
    "gen-0-3-doorstep/conventional": "1d21bc1c1811e7a8",
    "gen-0-4-boundary/fuzzy": "6407e9f078cd493d",
    "gen-0-4-boundary/conventional": "714a714e044ce400",
    "gen-0-5-stretched/fuzzy": "a59272d137105c60",
    "gen-0-5-stretched/conventional": "0b2d8d8bf80be648",
    "gen-0-6-below/fuzzy": "90ac3696ce3a4de7",
    "gen-0-6-below/conventional": "90ac3696ce3a4de7",
    "gen-0-7-open/fuzzy": "46cf81df2b4eb97e",
    "gen-0-7-open/conventional": "46cf81df2b4eb97e",
    "gen-11-4651-doorstep/fuzzy": "e0f40740f0a4cbca",
    "gen-11-4651-doorstep/conventional": "1bdbe780ebdae919",
    "gen-13-2173-doorstep/fuzzy": "8d957751b5f01d4f",
    "gen-13-2173-doorstep/conventional": "c3736d9340337942",
    "gen-13-248-doorstep/fuzzy": "befda2cc9de60255",
    "gen-13-248-doorstep/conventional": "da409c3b1f5c6fc1",
    "gen-7-3048-doorstep/fuzzy": "866099be3e5442f5",
    "gen-7-3048-doorstep/conventional": "c188cfb9c2f1645f",
    "gen-0-5519-doorstep/fuzzy": "2c6860a7b2cb6b1d",
    "gen-0-5519-doorstep/conventional": "4ddb41119dc1a686",
    "gen-13-3580-doorstep/fuzzy": "df3f6401dc165b0a",
    "gen-13-3580-doorstep/conventional": "be245c3fc2574d9c",
    "gen-1-138-stretched/fuzzy": "06b10b71c506edd3",
    "gen-1-138-stretched/conventional": "2e49989a14df12a9",
    "gen-0-9476-stretched/fuzzy": "e746a94e2baf8557",
    "gen-0-9476-stretched/conventional": "e12d1552d3c0ec72",
    "gen-0-5173-open/fuzzy": "6383efdc316426fc",
    "gen-0-5173-open/conventional": "ef22678a7ad838ac",
    "gen-1-987-open/fuzzy": "680668f65e979943",
    "gen-1-987-open/conventional": "4eed24d128204b7c",
    "gen-0-8669-doorstep/fuzzy": "ee1c9638d69f73b9",
    "gen-0-8669-doorstep/conventional": "b0bf2fb921266eda",
    "gen-11-4085-boundary/fuzzy": "41ddba9228fde1a8",
    "gen-11-4085-boundary/conventional": "f2eb96ebecc40896",
    "random-11-0/fuzzy": "a81acbf9b79bddb9",
    "random-11-0/conventional": "a81acbf9b79bddb9",
    "random-11-1/fuzzy": "858182deed7a7f1e",
    "random-11-1/conventional": "7284914842d74565",
    "random-11-2/fuzzy": "82645d098f16cfd1",
    "random-11-2/conventional": "82645d098f16cfd1",
    "random-11-3/fuzzy": "001e3ad9012d42ed",
    "random-11-3/conventional": "5815951136a5b47e",
    "random-11-4/fuzzy": "5068088e00b46c2f",
    "random-11-4/conventional": "5068088e00b46c2f",
    "random-11-5/fuzzy": "e01dedc2e8d2988f",
    "random-11-5/conventional": "e01dedc2e8d2988f",
    "random-11-6/fuzzy": "e30468b04500bef0",
    "random-11-6/conventional": "e30468b04500bef0",
    "random-11-7/fuzzy": "645aef7358839c74",
    "random-11-7/conventional": "1288b8d727d11f5c",
    "random-11-8/fuzzy": "9625bfb4b6437af4",
    "random-11-8/conventional": "03430cd4e96142e8",
    "random-11-9/fuzzy": "f4f21fd9b36e95bf",
    "random-11-9/conventional": "40621787293be23b",
    "random-11-10/fuzzy": "28f2f91554931d86",
    "random-11-10/conventional": "80161c4b043a8901",
    "random-11-11/fuzzy": "eafdf35e928cf6b9",
    "random-11-11/conventional": "6694294883e65edc",
    "random-11-12/fuzzy": "da31356b7352f492",
    "random-11-12/conventional": "dacdccb5210506f6",
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
