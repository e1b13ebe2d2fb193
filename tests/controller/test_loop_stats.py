"""The loop's statistics: the histogram's percentiles against numpy's on random data, within
the resolution its docstring states, in memory that does not grow with the number of values."""

from __future__ import annotations

import tracemalloc
from collections.abc import Callable

import numpy as np
import pytest

from controller.loop_stats import FLOOR, RESOLUTION, Histogram, LoopStats

PERCENTILES = (0.0, 0.1, 1.0, 25.0, 50.0, 90.0, 99.0, 99.9, 100.0)


def histogram_of(values: np.ndarray) -> Histogram:
    histogram = Histogram()
    for value in values.tolist():
        histogram.add(value)
    return histogram


@pytest.mark.parametrize(
    "draw",
    [
        lambda rng: rng.lognormal(np.log(50e-6), 1.0, 20_000),  # lateness-like, µs to ms
        lambda rng: 10.0 ** rng.uniform(-7.0, 3.0, 20_000),  # every decade from 0.1 µs to 1 ks
        lambda rng: rng.exponential(2e-3, 37),  # a few values: interpolation between bins
    ],
    ids=["lognormal", "decades", "few"],
)
@pytest.mark.parametrize("seed", range(3))
def test_percentiles_of_positive_values_are_within_the_resolution_of_numpys(
    draw: Callable[[np.random.Generator], np.ndarray], seed: int
) -> None:
    values = draw(np.random.default_rng(seed))
    histogram = histogram_of(values)
    for q in PERCENTILES:
        exact = float(np.percentile(values, q))
        assert histogram.percentile(q) == pytest.approx(exact, rel=RESOLUTION, abs=FLOOR), q
    assert histogram.percentile(0.0) == values.min()
    assert histogram.percentile(100.0) == values.max()


@pytest.mark.parametrize("seed", range(3))
def test_percentiles_of_values_of_both_signs_move_each_sample_by_under_the_resolution(
    seed: int,
) -> None:
    """Where the two samples around the rank have opposite signs, numpy's value may be near
    zero: the bound is then 1 % of the larger of the two."""
    values = np.random.default_rng(seed).normal(0.0, 1e-4, 5_001)
    values[:100] = 0.0  # exact zeros, and values under FLOOR, share the bin around zero
    values[100:200] *= 1e-4
    histogram = histogram_of(values)
    for q in (*PERCENTILES, 49.0, 51.0):
        exact = float(np.percentile(values, q))
        lower = abs(float(np.percentile(values, q, method="lower")))
        upper = abs(float(np.percentile(values, q, method="higher")))
        bound = RESOLUTION * max(lower, upper) + FLOOR
        assert abs(histogram.percentile(q) - exact) <= bound, q


def test_a_histogram_of_no_values_has_no_percentile() -> None:
    with pytest.raises(ValueError, match="no values"):
        Histogram().percentile(50.0)


def test_the_statistics_keep_a_fixed_memory_whatever_the_number_of_ticks() -> None:
    """A tick adds a lateness and an answer delay; memory after 1,000 ticks and after 100,000
    more is the same (a list of floats would have grown by over 6 MB)."""
    rng = np.random.default_rng(0)
    values = rng.lognormal(np.log(50e-6), 1.0, 101_000).tolist()
    tracemalloc.start()
    try:
        stats = LoopStats(period=0.002)
        for value in values[:1_000]:
            stats.lateness.add(value)
            stats.add_answer(value)
        after_first, _ = tracemalloc.get_traced_memory()
        for value in values[1_000:]:
            stats.lateness.add(value)
            stats.add_answer(value)
        after_all, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert stats.lateness.count == stats.answer_delay.count == len(values)
    assert after_all - after_first < 1_000, (after_first, after_all)


def test_the_summary_reports_the_runs_percentiles_exact_maxima_and_answers_within_a_tick() -> None:
    rng = np.random.default_rng(1)
    lateness = rng.lognormal(np.log(80e-6), 0.5, 2_000)
    delays = rng.lognormal(np.log(1.5e-3), 0.3, 1_500)
    stats = LoopStats(period=0.002, loops=2_000, ticks=1_600)
    for value in lateness.tolist():
        stats.lateness.add(value)
    for value in delays.tolist():
        stats.add_answer(value)
    summary = stats.summary()
    for key, values in (("lateness", lateness), ("answer_delay", delays)):
        for q in (50, 99):
            exact = float(np.percentile(values, q)) * 1e6
            assert summary[f"{key}_p{q}_us"] == pytest.approx(exact, rel=RESOLUTION), (key, q)
    assert summary["lateness_max_us"] == lateness.max() * 1e6
    assert summary["answered_within_tick_fraction"] == np.sum(delays <= 0.002) / 1_600


def test_the_summary_of_a_run_without_ticks_reports_zeros() -> None:
    summary = LoopStats(period=0.002).summary()
    assert summary["lateness_p50_us"] == summary["lateness_max_us"] == 0.0
    assert summary["answer_delay_p99_us"] == 0.0
    assert summary["answered_within_tick_fraction"] is None
