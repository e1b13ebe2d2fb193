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
    "reference/fuzzy": "4889dd3ba3868d6b",
    "reference/conventional": "2269cea314f949ed",
    "pass_left/fuzzy": "9d75111e890955ab",
    "pass_left/conventional": "37f749b17519abac",
    "long_wall/fuzzy": "a9243ad4cd863ae2",
    "long_wall/conventional": "d735bd8a4ee24073",
    "over_the_top/fuzzy": "51f32c65238a3154",
    "over_the_top/conventional": "51f32c65238a3154",
    "no_obstacle/fuzzy": "51f32c65238a3154",
    "no_obstacle/conventional": "51f32c65238a3154",
    "endurance/fuzzy": "d1d727d519a13517",
    "endurance/conventional": "058ccee29f27f2eb",
    "gen-0-0-open/fuzzy": "241897900b687738",
    "gen-0-0-open/conventional": "af812fabe6538d48",
    "gen-0-1-across/fuzzy": "d521ef0e1255143c",
    "gen-0-1-across/conventional": "5bea362ed5777845",
    "gen-0-2-back_across/fuzzy": "643d05235099ec5d",
    "gen-0-2-back_across/conventional": "884b0e31e2b882ea",
    "gen-0-3-doorstep/fuzzy": "3dd47918c7c6a6db",
    "gen-0-3-doorstep/conventional": "d9ace1fcceb95f5b",
    "gen-0-4-boundary/fuzzy": "6dc320ff359dd822",
    "gen-0-4-boundary/conventional": "dc58f7a20b4e1ca3",
    "gen-0-5-stretched/fuzzy": "030a8c251d019fdb",
    "gen-0-5-stretched/conventional": "d3b3eb9d3eb5d972",
    "gen-0-6-below/fuzzy": "0558a1c8c3a34b22",
    "gen-0-6-below/conventional": "0558a1c8c3a34b22",
    "gen-0-7-open/fuzzy": "bb07ac49216a55cb",
    "gen-0-7-open/conventional": "bb07ac49216a55cb",
    "gen-11-4651-doorstep/fuzzy": "e1c295a7f5ef9595",
    "gen-11-4651-doorstep/conventional": "2e534f107c35fc1c",
    "gen-13-2173-doorstep/fuzzy": "4f1efb2d248f30b2",
    "gen-13-2173-doorstep/conventional": "df162932dd0572b4",
    "gen-13-248-doorstep/fuzzy": "009023d58c14c2ec",
    "gen-13-248-doorstep/conventional": "09a0b7486b5ea092",
    "gen-7-3048-doorstep/fuzzy": "8099961bf9755d72",
    "gen-7-3048-doorstep/conventional": "7167e7436ca6071d",
    "gen-0-5519-doorstep/fuzzy": "874ec98010a4bb1a",
    "gen-0-5519-doorstep/conventional": "f0935bd763e042c1",
    "gen-13-3580-doorstep/fuzzy": "8602ed730fcf7c95",
    "gen-13-3580-doorstep/conventional": "c5eaf857dc597ae8",
    "gen-1-138-stretched/fuzzy": "08228a4413c60445",
    "gen-1-138-stretched/conventional": "5fde531dce2bf806",
    "gen-0-9476-stretched/fuzzy": "edeaaee5a79a2e4b",
    "gen-0-9476-stretched/conventional": "29ef0fe7c77a01fa",
    "gen-0-5173-open/fuzzy": "20441eccf6ab4090",
    "gen-0-5173-open/conventional": "3e961924d633a0e4",
    "gen-1-987-open/fuzzy": "2645541cb0d209b0",
    "gen-1-987-open/conventional": "c01f06b7f3535798",
    "gen-0-8669-doorstep/fuzzy": "53ba86fe70948612",
    "gen-0-8669-doorstep/conventional": "195851a0097a1346",
    "gen-11-4085-boundary/fuzzy": "92707a34db931f91",
    "gen-11-4085-boundary/conventional": "237a4130074c92ba",
    "random-11-0/fuzzy": "c04348b8ae3b5de8",
    "random-11-0/conventional": "c04348b8ae3b5de8",
    "random-11-1/fuzzy": "5d5cb9e5913312d8",
    "random-11-1/conventional": "f6d12796c600b2b0",
    "random-11-2/fuzzy": "d9d05747b75649cc",
    "random-11-2/conventional": "d9d05747b75649cc",
    "random-11-3/fuzzy": "c8cb347b3bd67dde",
    "random-11-3/conventional": "b324e24cf1834f02",
    "random-11-4/fuzzy": "d9e4ddda6dd1fcfc",
    "random-11-4/conventional": "d9e4ddda6dd1fcfc",
    "random-11-5/fuzzy": "041c13fe11c63b84",
    "random-11-5/conventional": "041c13fe11c63b84",
    "random-11-6/fuzzy": "6d150478494476cc",
    "random-11-6/conventional": "6d150478494476cc",
    "random-11-7/fuzzy": "b8abdb2982be8079",
    "random-11-7/conventional": "8948c876bd51c191",
    "random-11-8/fuzzy": "c3bcef64a131437f",
    "random-11-8/conventional": "dd810e5e032dff48",
    "random-11-9/fuzzy": "a114bef51675112a",
    "random-11-9/conventional": "f73c4a854e3cde0d",
    "random-11-10/fuzzy": "0e226f2cfd442c80",
    "random-11-10/conventional": "ca203ff44fbded05",
    "random-11-11/fuzzy": "7c8c17bb068cfaae",
    "random-11-11/conventional": "f51fd21519bba131",
    "random-11-12/fuzzy": "201b01e8c32e38cd",
    "random-11-12/conventional": "c43b33ff6d77ef31",
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
