"""How the controller's loop kept time during one run: counters, and the quantiles of the
ticks' lateness and of the plant's answer delay from fixed-size histograms, so that a service
that runs for days holds the same few kilobytes whatever the number of ticks."""

from __future__ import annotations

import math
from array import array
from dataclasses import dataclass, field

import numpy as np

RESOLUTION = 0.01
"""Relative resolution of :class:`Histogram`: a bin's centre is within 1 % of its values."""
FLOOR = 1e-7
"""s: values closer to zero than this (0.1 µs) share one bin, centred on zero."""
CEILING = 1e4
"""s: values larger in magnitude than this share the outermost bin of their sign."""
_RATIO = (1.0 + RESOLUTION) ** 2
"""One bin's upper edge over its lower edge: the centre, lower edge x (1 + RESOLUTION), is
within RESOLUTION of every value in the bin."""
_BINS = math.ceil(math.log(CEILING / FLOOR) / math.log(_RATIO))
"""Bins of each sign between FLOOR and CEILING."""
_LOG_RATIO = math.log(_RATIO)
_CENTRES = FLOOR * (1.0 + RESOLUTION) * _RATIO ** np.arange(_BINS)
_VALUES = np.concatenate((-_CENTRES[::-1], [0.0], _CENTRES))
"""Each bin's value, in order: the negative bins (largest magnitude first), zero, the positive."""


class Histogram:
    """Quantiles of a stream of values (seconds) in fixed memory, 2,547 counts (20 kB),
    whatever the number of values: log-spaced bins of the magnitude, one set for each sign.

    Resolution: :meth:`percentile` is numpy's ``percentile`` (its default: linear
    interpolation between the two samples around the rank) as if each sample had been moved
    by less than 1 % of its magnitude, or by less than 0.1 µs if it is under 0.1 µs. So it is
    within 1 % relative (+ 0.1 µs) of numpy's where those two samples have the same sign, as
    lateness and answer delays have. That holds up to 10,000 s (beyond, values share the
    outermost bin). The smallest and the largest value are exact, and no percentile lies
    outside them.
    """

    __slots__ = ("_counts", "count", "max", "min")

    def __init__(self) -> None:
        self._counts = array("q", bytes(8 * len(_VALUES)))  # int64: fast to add to in Python
        self.count = 0
        self.max = -math.inf
        self.min = math.inf

    def add(self, value: float) -> None:
        self.count += 1
        self.max = max(self.max, value)
        self.min = min(self.min, value)
        magnitude = abs(value)
        index = _BINS  # zero's
        if magnitude >= FLOOR:
            offset = 1 + min(int(math.log(min(magnitude, CEILING) / FLOOR) / _LOG_RATIO), _BINS - 1)
            index += offset if value > 0.0 else -offset
        self._counts[index] += 1

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile (0-100) of the values added (at least one)."""
        if not self.count:
            raise ValueError("percentile of no values")
        rank = (self.count - 1) * q / 100.0
        below = math.floor(rank)
        low, high = self._order_statistics(below, min(below + 1, self.count - 1))
        return low + (rank - below) * (high - low)

    def _order_statistics(self, *ranks: int) -> list[float]:
        """The values of the given ranks (0: the smallest) in sorted order: the smallest and
        the largest exact, the others their bin's value (within the two)."""
        bins = np.searchsorted(np.cumsum(np.frombuffer(self._counts, np.int64)), ranks, "right")
        last = self.count - 1
        return [
            self.min if rank == 0 else self.max if rank == last
            else min(max(float(_VALUES[index]), self.min), self.max)
            for rank, index in zip(ranks, bins, strict=True)
        ]  # fmt: skip


@dataclass(slots=True)
class LoopStats:
    """How the loop kept time, what the wire did, and how often the controller held, since
    the run started (``period``: the control period, s)."""

    period: float
    loops: int = 0
    ticks: int = 0
    deadline_misses: int = 0
    overruns: int = 0
    lockstep_retries: int = 0
    holds: int = 0
    hold_time: float = 0.0
    longest_hold: float = 0.0
    lateness: Histogram = field(default_factory=Histogram)
    """s from each tick's deadline to when it started."""
    answer_delay: Histogram = field(default_factory=Histogram)
    """s from a command sent to the joint state answering it."""
    answered_within_tick: int = 0

    def add_answer(self, delay: float) -> None:
        """The plant answered a command ``delay`` s after it was sent."""
        self.answer_delay.add(delay)
        if delay <= self.period:
            self.answered_within_tick += 1

    def summary(self) -> dict[str, float | int | None]:
        # Real time only (loops counts its ticks): lockstep has no "within a tick".
        within = self.answered_within_tick / self.ticks if self.loops and self.ticks else None
        return {
            "loops": self.loops,
            "ticks": self.ticks,
            "deadline_misses": self.deadline_misses,
            "deadline_miss_fraction": self.deadline_misses / max(self.loops, 1),
            "overruns": self.overruns,
            "lockstep_retries": self.lockstep_retries,
            "holds": self.holds,
            "hold_time_s": self.hold_time,
            "longest_hold_s": self.longest_hold,
            "lateness_p50_us": _microseconds(self.lateness, 50),
            "lateness_p99_us": _microseconds(self.lateness, 99),
            "lateness_max_us": self.lateness.max * 1e6 if self.lateness.count else 0.0,
            "answered_within_tick_fraction": within,
            "answer_delay_p50_us": _microseconds(self.answer_delay, 50),
            "answer_delay_p99_us": _microseconds(self.answer_delay, 99),
        }


def _microseconds(histogram: Histogram, q: float) -> float:
    """The ``q``-th percentile in µs; 0 with no values."""
    return histogram.percentile(q) * 1e6 if histogram.count else 0.0
