"""The soak's health samples (``soak/health.py``): memory and file handles from ``/proc``, and
the growth of each start past its warm-up; and the watch's time back after a disturbance."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import pytest

from soak.drive import Watch
from soak.health import WARM_UP, Health, Sample, sample


def test_a_live_process_is_sampled_and_a_gone_one_is_not() -> None:
    taken = sample(os.getpid())
    assert taken is not None and taken[0] > 10 * 2**20 and taken[1] >= 3
    assert sample(2**22 + 12345) is None  # above any pid_max


def test_growth_counts_from_the_first_sample_past_the_warm_up() -> None:
    health = Health(dict)
    health.samples[("bridge", 0)] = [
        Sample(1.0, 10, 5),  # warming up: not counted
        Sample(WARM_UP, 50, 8),
        Sample(WARM_UP + 30, 70, 9),
        Sample(WARM_UP + 60, 60, 8),
    ]
    health.samples[("plant", 2)] = [Sample(WARM_UP + 1, 40, 4)]  # one sample: no growth yet
    (growth,) = health.growths()
    assert (growth.process, growth.start, growth.seconds) == ("bridge", 0, 60)
    assert (growth.rss_growth, growth.fds_growth) == (20, 1)


def test_every_sample_is_written_to_csv(tmp_path: Path) -> None:
    health = Health(dict)
    health.samples[("recorder", 1)] = [Sample(2.0, 100, 9), Sample(4.0, 120, 9)]
    health.samples[("bridge", 0)] = [Sample(2.0, 80, 21)]
    health.write_csv(tmp_path / "health.csv")
    with (tmp_path / "health.csv").open() as stream:
        rows = list(csv.DictReader(stream))
    assert [(r["process"], r["start"], r["seconds"], r["rss_bytes"]) for r in rows] == [
        ("bridge", "0", "2.0", "80"),
        ("recorder", "1", "2.0", "100"),
        ("recorder", "1", "4.0", "120"),
    ]


def test_a_system_is_back_once_it_stays_up() -> None:
    """A fault that shows only after the disturbance ended counts in its time back."""
    watch = Watch(operator=None)  # type: ignore[arg-type]
    looks = [(0.0, True), (0.1, True), (0.2, False), (0.3, False), (0.4, True)]
    looks += [(0.4 + 0.1 * k, True) for k in range(1, 15)]
    watch.ups.extend(looks)
    assert watch.back_after(0.05) == pytest.approx(0.35)
    watch.ups.append((2.0, False))
    assert watch.back_after(1.95) is None  # never up again for long enough
