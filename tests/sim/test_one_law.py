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
    "reference/fuzzy": "8592ed68718bdba0",
    "reference/conventional": "94b7adee4003d3d5",
    "pass_left/fuzzy": "f1648f54d1cccb71",
    "pass_left/conventional": "2f598cebeeb55927",
    "long_wall/fuzzy": "6bc6102e783e91e7",
    "long_wall/conventional": "5d899f66b222f1fc",
    "over_the_top/fuzzy": "ea27823be9dcdbc4",
    "over_the_top/conventional": "ea27823be9dcdbc4",
    "no_obstacle/fuzzy": "ea27823be9dcdbc4",
    "no_obstacle/conventional": "ea27823be9dcdbc4",
    "endurance/fuzzy": "fb3ed0d351bb8fdf",
    "endurance/conventional": "a2036b0bd984e496",
    "gen-0-0-open/fuzzy": "bd0534b030d7fab2",
    "gen-0-0-open/conventional": "0fe3482ae740a2c4",
    "gen-0-1-across/fuzzy": "2074c3bb837b34b2",
    "gen-0-1-across/conventional": "0912613a9dd0cdf7",
    "gen-0-2-back_across/fuzzy": "10e72f3918602e8a",
    "gen-0-2-back_across/conventional": "0c1b74af816dbd14",
    "gen-0-3-doorstep/fuzzy": "1830b35e112d3c48",
    "gen-0-3-doorstep/conventional": "7ebe77955620ef05",
    "gen-0-4-boundary/fuzzy": "f2b99da80da29b54",
    "gen-0-4-boundary/conventional": "a7198ef70eeaaca2",
    "gen-0-5-stretched/fuzzy": "76f0ce6bc08c2757",
    "gen-0-5-stretched/conventional": "137be0bb07870e22",
    "gen-0-6-below/fuzzy": "cff518d1c4299454",
    "gen-0-6-below/conventional": "cff518d1c4299454",
    "gen-0-7-open/fuzzy": "4c327a40c179a1fb",
    "gen-0-7-open/conventional": "4c327a40c179a1fb",
    "gen-11-4651-doorstep/fuzzy": "3cf80ad6a856add9",
    "gen-11-4651-doorstep/conventional": "c4b23cda235a1988",
    "gen-13-2173-doorstep/fuzzy": "997d3bdb0b991514",
    "gen-13-2173-doorstep/conventional": "eff6a0f70a53f0c4",
    "gen-13-248-doorstep/fuzzy": "1ef33d9e5557fc75",
    "gen-13-248-doorstep/conventional": "13983632eb3480ff",
    "gen-7-3048-doorstep/fuzzy": "f7c1b2ff984dd2fe",
    "gen-7-3048-doorstep/conventional": "783b760399a2cde9",
    "gen-0-5519-doorstep/fuzzy": "d62e4673c0930521",
    "gen-0-5519-doorstep/conventional": "de0609fc10d7d204",
    "gen-13-3580-doorstep/fuzzy": "4d5027ddba9f920f",
    "gen-13-3580-doorstep/conventional": "49c4fd5d9e156870",
    "gen-1-138-stretched/fuzzy": "2cd8f2ca67bacb0c",
    "gen-1-138-stretched/conventional": "dfbc987290eb7f8f",
    "gen-0-9476-stretched/fuzzy": "df3099687736075a",
    "gen-0-9476-stretched/conventional": "09bfac1794989395",
    "gen-0-5173-open/fuzzy": "b10cdf46883ca37e",
    "gen-0-5173-open/conventional": "a6fa14ca989e0b8a",
    "gen-1-987-open/fuzzy": "75a4fa720d809f8a",
    "gen-1-987-open/conventional": "47ae8e719408dcc2",
    "gen-0-8669-doorstep/fuzzy": "2f655d7e2523255f",
    "gen-0-8669-doorstep/conventional": "a845e89369c7ff0d",
    "gen-11-4085-boundary/fuzzy": "e5f57bb02d3f92df",
    "gen-11-4085-boundary/conventional": "0cab6de09d9eaab3",
    "random-11-0/fuzzy": "d01196d26abb5443",
    "random-11-0/conventional": "d01196d26abb5443",
    "random-11-1/fuzzy": "7d4c1d712c6eb60e",
    "random-11-1/conventional": "a63a619fed925335",
    "random-11-2/fuzzy": "9fd6478401500a0b",
    "random-11-2/conventional": "9fd6478401500a0b",
    "random-11-3/fuzzy": "4c818ea568b67ace",
    "random-11-3/conventional": "1e3879127b45a796",
    "random-11-4/fuzzy": "e4d004bbd344a96e",
    "random-11-4/conventional": "e4d004bbd344a96e",
    "random-11-5/fuzzy": "56be7232e0ef653a",
    "random-11-5/conventional": "56be7232e0ef653a",
    "random-11-6/fuzzy": "050e749b00f86606",
    "random-11-6/conventional": "050e749b00f86606",
    "random-11-7/fuzzy": "5b167ca1966bdf7a",
    "random-11-7/conventional": "df5a6131eafa10b1",
    "random-11-8/fuzzy": "0846644688b92a5b",
    "random-11-8/conventional": "2b8e5ce099d9f09b",
    "random-11-9/fuzzy": "beed99ee1579f517",
    "random-11-9/conventional": "19d282f921282f5e",
    "random-11-10/fuzzy": "d904d254b3002844",
    "random-11-10/conventional": "10fc5bef35421a56",
    "random-11-11/fuzzy": "c0bd9106236c26bb",
    "random-11-11/conventional": "425f2931f794b3ec",
    "random-11-12/fuzzy": "446d4a72110a52d1",
    "random-11-12/conventional": "e44a6510a5921333",
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
