"""Process timing (``protocol.realtime``): precise wake-ups are asked for, and inherited by the
threads started afterwards (as the transport's are). Run in a child process: the test runner's
own scheduling stays as it is."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from support import ROOT, SLOWDOWN

PROBE = """
import ctypes, json, sys, threading
from protocol.realtime import tune_process
applied = tune_process(plain=sys.argv[1] == "plain")
libc = ctypes.CDLL(None)
seen = []
thread = threading.Thread(target=lambda: seen.append(libc.prctl(30, 0, 0, 0, 0)))
thread.start(); thread.join()
print(json.dumps({"applied": applied, "main": libc.prctl(30, 0, 0, 0, 0), "thread": seen[0]}))
"""


def probe(mode: str) -> dict[str, object]:
    done = subprocess.run(
        [sys.executable, "-c", PROBE, mode],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60 * SLOWDOWN,
    )
    assert done.returncode == 0, done.stderr
    result: dict[str, object] = json.loads(done.stdout)
    return result


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl is Linux's")
def test_timer_slack_is_1_ns_in_the_process_and_its_later_threads() -> None:
    tuned = probe("tuned")
    assert "timer slack 1 ns" in tuned["applied"]  # type: ignore[operator]
    assert tuned["main"] == 1 and tuned["thread"] == 1
    plain = probe("plain")
    assert plain["applied"] == [] and plain["main"] == 50_000  # the kernel's default
