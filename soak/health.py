"""The long-running processes' health: resident memory and open file handles, read from
``/proc`` every :data:`SAMPLE_PERIOD` for every start of every process, so that a leak shows
as growth within one start (a restart starts afresh)."""

from __future__ import annotations

import csv
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

SAMPLE_PERIOD = 2.0
"""s between samples."""
WARM_UP = 60.0
"""s after a start before its samples count: imports, sessions, first buffers and the first
runs (the controller's log of a run is allocated as it runs)."""


@dataclass(frozen=True, slots=True)
class Sample:
    at: float
    """s since the process started."""
    rss: int
    """bytes resident."""
    fds: int
    """open file handles."""


def sample(pid: int) -> tuple[int, int] | None:
    """(resident bytes, open file handles) of ``pid``; None if it has gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except (FileNotFoundError, ProcessLookupError):
        return None
    for line in status.splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024, fds
    return None


@dataclass(frozen=True, slots=True)
class Growth:
    """One start of one process, from its first sample after :data:`WARM_UP` to its last."""

    process: str
    start: int
    seconds: float
    rss_first: int
    rss_max: int
    fds_first: int
    fds_max: int

    @property
    def rss_growth(self) -> int:
        return self.rss_max - self.rss_first

    @property
    def fds_growth(self) -> int:
        return self.fds_max - self.fds_first


@dataclass
class Health:
    """Samples of every live process, by (name, start), taken in a thread of its own."""

    pids: Callable[[], dict[str, tuple[int, int]]]
    """The live processes: name -> (pid, which start)."""
    samples: dict[tuple[str, int], list[Sample]] = field(default_factory=dict)
    _began: dict[tuple[str, int], float] = field(default_factory=dict)
    _stop: threading.Event = field(default_factory=threading.Event)

    def run(self) -> None:
        while not self._stop.wait(SAMPLE_PERIOD):
            now = time.monotonic()
            for name, (pid, start) in self.pids().items():
                taken = sample(pid)
                if taken is None:
                    continue
                key = (name, start)
                began = self._began.setdefault(key, now)
                self.samples.setdefault(key, []).append(Sample(now - began, *taken))

    def stop(self) -> None:
        self._stop.set()

    def write_csv(self, path: Path) -> None:
        """Every sample (process, start, s since it started, resident bytes, file handles):
        a leak rises to the end; a backlog worked off leaves a high-water mark and stays."""
        with path.open("w", newline="") as stream:
            rows = csv.writer(stream)
            rows.writerow(["process", "start", "seconds", "rss_bytes", "open_files"])
            for (name, start), samples in sorted(self.samples.items()):
                rows.writerows([name, start, f"{s.at:.1f}", s.rss, s.fds] for s in samples)

    def growths(self) -> list[Growth]:
        """Every start observed past its warm-up, longest first."""
        found = []
        for (name, start), samples in self.samples.items():
            counted = [s for s in samples if s.at >= WARM_UP]
            if len(counted) < 2:
                continue
            found.append(
                Growth(
                    name,
                    start,
                    counted[-1].at - counted[0].at,
                    counted[0].rss,
                    max(s.rss for s in counted),
                    counted[0].fds,
                    max(s.fds for s in counted),
                )
            )
        return sorted(found, key=lambda growth: -growth.seconds)
