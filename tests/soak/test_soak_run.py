"""A minute of soak through real processes on 127.0.0.1 (``scara-soak --minutes 1``): every
invariant holds on its recordings, every disturbance is recovered from, and tasks complete.
A failure prints the report, which names the seed and the moment of each violation."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from support import ROOT, SLOWDOWN, real_time_needed

SEED = 73
"""Its minute: pauses of the bridge, the controller and the recorder, the recorder, the keys' router
and the controller killed, a flood, an obstacle set in a run, commands from the read-only user."""
START_AND_CHECK = 240.0
"""s beyond the minute for starting the stack, stopping it and checking the recordings on a
loaded 2-core machine."""


@pytest.mark.slow
@pytest.mark.timeout(60 + START_AND_CHECK + 60)
def test_a_minute_of_soak_breaks_no_invariant(tmp_path: Path) -> None:
    real_time_needed()
    out = tmp_path / "soak"
    command = [sys.executable, "-m", "soak.cli", "--minutes", "1", "--seed", str(SEED)]
    done = subprocess.run(
        [*command, "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=(60 + START_AND_CHECK) * SLOWDOWN,
    )
    report = json.loads((out / "report.json").read_text())
    shown = f"{done.stdout}\n{done.stderr[-3000:]}"
    assert sum(report["invariants"].values()) == 0, shown
    assert all(d["back_s"] is not None for d in report["disturbances"]), shown
    assert report["tasks"]["completed"] >= 1, shown
    assert done.returncode == 0, shown
