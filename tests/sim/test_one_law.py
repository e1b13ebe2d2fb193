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
    "reference/fuzzy": "f4553024a54594ba",
    "reference/conventional": "287cbdec38d9efe4",
    "pass_left/fuzzy": "b11f13ac4b6a7658",
    "pass_left/conventional": "75cf8a6dee10e8de",
    "long_wall/fuzzy": "44a2301e4814caf9",
    "long_wall/conventional": "8d60000d3d88a40b",
    "over_the_top/fuzzy": "12e30e49d60e4e24",
    "over_the_top/conventional": "12e30e49d60e4e24",
    "no_obstacle/fuzzy": "12e30e49d60e4e24",
    "no_obstacle/conventional": "12e30e49d60e4e24",
    "endurance/fuzzy": "242cc2c57abce36c",
    "endurance/conventional": "5f6d3db0cd2506d3",
    "gen-0-0-open/fuzzy": "211d2967fe5c3cfd",
    "gen-0-0-open/conventional": "e31db392d1d381c2",
    "gen-0-1-across/fuzzy": "5e7f47f1156f1e3c",
    "gen-0-1-across/conventional": "08b0ef7febed4f13",
    "gen-0-2-back_across/fuzzy": "1d61a3d7c0512837",
    "gen-0-2-back_across/conventional": "ed3b823b51d339b6",
    "gen-0-3-doorstep/fuzzy": "6945a473177410f9",
    "gen-0-3-doorstep/conventional": "48ba024236d275c3",
    "gen-0-4-boundary/fuzzy": "00200e0eb409c903",
    "gen-0-4-boundary/conventional": "eea40269eadbd0a8",
    "gen-0-5-stretched/fuzzy": "9958e149ba216e70",
    "gen-0-5-stretched/conventional": "102626fbe4437907",
    "gen-0-6-below/fuzzy": "54739e926c4b9a92",
    "gen-0-6-below/conventional": "54739e926c4b9a92",
    "gen-0-7-open/fuzzy": "ab8ba928ec8063bc",
    "gen-0-7-open/conventional": "ab8ba928ec8063bc",
    "gen-11-4651-doorstep/fuzzy": "90a6750d269ff9ba",
    "gen-11-4651-doorstep/conventional": "4d3e54c0230e663d",
    "gen-13-2173-doorstep/fuzzy": "8cac720adb3b7673",
    "gen-13-2173-doorstep/conventional": "9ec1ad65270166e7",
    "gen-13-248-doorstep/fuzzy": "d9ffa9471a1cba83",
    "gen-13-248-doorstep/conventional": "9c2c484214fa7502",
    "gen-7-3048-doorstep/fuzzy": "0c07aaa3dc890708",
    "gen-7-3048-doorstep/conventional": "a268a485f92f3a34",
    "gen-0-5519-doorstep/fuzzy": "8cfb84313c251b59",
    "gen-0-5519-doorstep/conventional": "e66e9302c9e380e5",
    "gen-13-3580-doorstep/fuzzy": "07cc70f07462dfb7",
    "gen-13-3580-doorstep/conventional": "49ec6af746737234",
    "gen-1-138-stretched/fuzzy": "d66119e2dcad77c7",
    "gen-1-138-stretched/conventional": "a956b1fef21f196d",
    "gen-0-9476-stretched/fuzzy": "6d9ef7e2b5a71ab3",
    "gen-0-9476-stretched/conventional": "a2638a2d42fec46c",
    "gen-0-5173-open/fuzzy": "1a1fa99afefb7c63",
    "gen-0-5173-open/conventional": "fd9674db1b0fd0fe",
    "gen-1-987-open/fuzzy": "e46905712324c57e",
    "gen-1-987-open/conventional": "1872090859f1dd1b",
    "gen-0-8669-doorstep/fuzzy": "737ae9884c5e3f26",
    "gen-0-8669-doorstep/conventional": "87984f4b612a95fc",
    "gen-11-4085-boundary/fuzzy": "d6b091cd17683d4e",
    "gen-11-4085-boundary/conventional": "cefcd94e6fb67315",
    "random-11-0/fuzzy": "7d5116d92efa20f9",
    "random-11-0/conventional": "7d5116d92efa20f9",
    "random-11-1/fuzzy": "b8ef621767c7c871",
    "random-11-1/conventional": "c2bf9c4c8bd7a7cc",
    "random-11-2/fuzzy": "e3e01d64619bee3b",
    "random-11-2/conventional": "e3e01d64619bee3b",
    "random-11-3/fuzzy": "e35c4fa171712658",
    "random-11-3/conventional": "0cf8b046bcba481a",
    "random-11-4/fuzzy": "830407ec450c9ba3",
    "random-11-4/conventional": "830407ec450c9ba3",
    "random-11-5/fuzzy": "4f2caccd4215cfe5",
    "random-11-5/conventional": "4f2caccd4215cfe5",
    "random-11-6/fuzzy": "ffc274fad850ed92",
    "random-11-6/conventional": "ffc274fad850ed92",
    "random-11-7/fuzzy": "2d5c0dfaba63c889",
    "random-11-7/conventional": "13e9e4ea68fc517d",
    "random-11-8/fuzzy": "863f5e0ce4d6ffae",
    "random-11-8/conventional": "0ce5156cdc2b3409",
    "random-11-9/fuzzy": "c2faa6e712be48de",
    "random-11-9/conventional": "ec2cf0527269774a",
    "random-11-10/fuzzy": "9fc9bcef0547c7e4",
    "random-11-10/conventional": "8e472bdea19ad49b",
    "random-11-11/fuzzy": "a9c333514370267e",
    "random-11-11/conventional": "d779a0627703b232",
    "random-11-12/fuzzy": "13fc728d04a9021c",
    "random-11-12/conventional": "88cde30e46660b8f",
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
