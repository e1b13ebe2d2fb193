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
    "long_wall/fuzzy": "e869b47b01967764",
    "long_wall/conventional": "543ba24775a613fc",
    "over_the_top/fuzzy": "ea27823be9dcdbc4",
    "over_the_top/conventional": "ea27823be9dcdbc4",
    "no_obstacle/fuzzy": "ea27823be9dcdbc4",
    "no_obstacle/conventional": "ea27823be9dcdbc4",
    "endurance/fuzzy": "4d028e89f3446b74",
    "endurance/conventional": "a2036b0bd984e496",
    "gen-0-0-open/fuzzy": "bd0534b030d7fab2",
    "gen-0-0-open/conventional": "0fe3482ae740a2c4",
    "gen-0-1-across/fuzzy": "2074c3bb837b34b2",
    "gen-0-1-across/conventional": "0912613a9dd0cdf7",
    "gen-0-2-back_across/fuzzy": "c421d8315c1f9fb9",
    "gen-0-2-back_across/conventional": "870a72eaf160abc8",
    "gen-0-3-doorstep/fuzzy": "1830b35e112d3c48",
    "gen-0-3-doorstep/conventional": "659ab061b91f45d5",
    "gen-0-4-boundary/fuzzy": "a8f76808edac00c1",
    "gen-0-4-boundary/conventional": "0c1e0759c0da7e85",
    "gen-0-5-stretched/fuzzy": "f5514828eb37f90e",
    "gen-0-5-stretched/conventional": "137be0bb07870e22",
    "gen-0-6-below/fuzzy": "cff518d1c4299454",
    "gen-0-6-below/conventional": "cff518d1c4299454",
    "gen-0-7-open/fuzzy": "2f2a95240404b54c",
    "gen-0-7-open/conventional": "2f2a95240404b54c",
    "gen-11-4651-doorstep/fuzzy": "374c7517bf0add8a",
    "gen-11-4651-doorstep/conventional": "9e6b3b59387846b6",
    "gen-13-2173-doorstep/fuzzy": "e8ded8cfe8c4375f",
    "gen-13-2173-doorstep/conventional": "84ab34324091d096",
    "gen-13-248-doorstep/fuzzy": "ee8c6b65acd89613",
    "gen-13-248-doorstep/conventional": "7c6d00a44898d3dc",
    "gen-7-3048-doorstep/fuzzy": "36c6d36a1570205f",
    "gen-7-3048-doorstep/conventional": "4e7edf89f144c3c8",
    "gen-0-5519-doorstep/fuzzy": "d62e4673c0930521",
    "gen-0-5519-doorstep/conventional": "de0609fc10d7d204",
    "gen-13-3580-doorstep/fuzzy": "4d5027ddba9f920f",
    "gen-13-3580-doorstep/conventional": "49c4fd5d9e156870",
    "gen-1-138-stretched/fuzzy": "2cd8f2ca67bacb0c",
    "gen-1-138-stretched/conventional": "dfbc987290eb7f8f",
    "gen-0-9476-stretched/fuzzy": "8aebea7edd04c20a",
    "gen-0-9476-stretched/conventional": "0a8624d85b4bb825",
    "gen-0-5173-open/fuzzy": "e9b1687c669f9b3d",
    "gen-0-5173-open/conventional": "f3151b291b1ec314",
    "gen-1-987-open/fuzzy": "75a4fa720d809f8a",
    "gen-1-987-open/conventional": "c77d7a3095411280",
    "gen-0-8669-doorstep/fuzzy": "20f886d2a4805091",
    "gen-0-8669-doorstep/conventional": "11f571018a7f2615",
    "gen-11-4085-boundary/fuzzy": "f93bb615a9a41339",
    "gen-11-4085-boundary/conventional": "762de9539dc9df4a",
    "random-11-0/fuzzy": "d01196d26abb5443",
    "random-11-0/conventional": "d01196d26abb5443",
    "random-11-1/fuzzy": "b994cb6f058746d5",
    "random-11-1/conventional": "4aea8de77def5c01",
    "random-11-2/fuzzy": "1f9d14685fa96d58",
    "random-11-2/conventional": "1f9d14685fa96d58",
    "random-11-3/fuzzy": "9ccc88ce2628a687",
    "random-11-3/conventional": "4a2cdb97167569e7",
    "random-11-4/fuzzy": "e4d004bbd344a96e",
    "random-11-4/conventional": "e4d004bbd344a96e",
    "random-11-5/fuzzy": "4cda121287d30f1c",
    "random-11-5/conventional": "4cda121287d30f1c",
    "random-11-6/fuzzy": "050e749b00f86606",
    "random-11-6/conventional": "050e749b00f86606",
    "random-11-7/fuzzy": "5b167ca1966bdf7a",
    "random-11-7/conventional": "df5a6131eafa10b1",
    "random-11-8/fuzzy": "0846644688b92a5b",
    "random-11-8/conventional": "2b8e5ce099d9f09b",
    "random-11-9/fuzzy": "beed99ee1579f517",
    "random-11-9/conventional": "19d282f921282f5e",
    "random-11-10/fuzzy": "96353eb710fe9d3c",
    "random-11-10/conventional": "b19d5c85157abc97",
    "random-11-11/fuzzy": "85ee8d060de3c9ac",
    "random-11-11/conventional": "d31af582d8620ff9",
    "random-11-12/fuzzy": "446d4a72110a52d1",
    "random-11-12/conventional": "1c07c3c72f63e950",
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
