"""Co-simulation benchmark: the codec (now and at an earlier revision, side by side), lockstep
speed, and real time at 1 kHz.

Measures, in one run on this machine:

1. one encode and one decode of each cyclic frame (target: at most 5 us each), and the same
   with the codec of ``--before REV`` (read from git, run on the same DBC) for comparison;
2. lockstep on the reference scenario over CAN-over-Zenoh: simulated time over wall time
   (target at least 5x);
3. real time at 1 kHz for 30 s (the ``endurance`` scenario), normal priority: tick lateness,
   missed deadlines, answers within a tick, holds (reported; the 500 Hz targets are
   ``bench_link.py``'s).

Run from the project root: ``python benchmarks/bench_cosim.py [--quick] [--before REV]
[--json PATH]``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # the tests' helpers: tests.support
from protocol import codec as current_codec  # noqa: E402
from tests.support import free_port  # noqa: E402

TARGET_CODEC_US = 5.0
TARGET_LOCKSTEP = 5.0
CASES = (
    ("JointVelocityCommand", (1, 1.234, -5.5, 0.3)),
    ("JointState1", (3, -2.123456, 3.21)),
)


def codec_at(revision: str) -> ModuleType:
    """``protocol/codec.py`` as it was at ``revision``, loaded beside the current one."""
    source = subprocess.run(
        ["git", "show", f"{revision}:protocol/codec.py"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    spec = importlib.util.spec_from_loader(f"codec_{revision}", loader=None)
    assert spec is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    exec(compile(source, f"{revision}:protocol/codec.py", "exec"), module.__dict__)
    return module


def time_call(call: Callable[[], object], repeats: int) -> float:
    """Median over 20 batches of the time of one call, in us."""
    samples = []
    for _ in range(20):
        started = time.perf_counter_ns()
        for _ in range(repeats):
            call()
        samples.append((time.perf_counter_ns() - started) / repeats / 1000)
    return statistics.median(samples)


def codec_rows(repeats: int, before: str | None) -> list[list[str]]:
    versions: list[tuple[str, Any]] = [("now", current_codec.WIRE)]
    if before:
        versions.append((before, codec_at(before).WIRE))
    rows = []
    for name, values in CASES:
        for what in ("encode", "decode"):
            cells = []
            for _label, wire in versions:
                message = wire[name]
                data = message.encode(values, 5)
                call: Callable[[], object] = (
                    (lambda m=message, v=values: m.encode(v, 5))
                    if what == "encode"
                    else (lambda m=message, d=data: m.decode(d))
                )
                cells.append(time_call(call, repeats))
            shown = f"{cells[0]:.2f} us" + (f" (at {before}: {cells[1]:.2f} us)" if before else "")
            rows.append(
                [
                    f"{name} {what}",
                    shown,
                    f"<= {TARGET_CODEC_US:g} us",
                    verdict(cells[0] <= TARGET_CODEC_US),
                ]
            )
    return rows


def run_launcher(arguments: list[str], out: Path, timeout: float) -> dict[str, Any]:
    """Run scara-run with ``arguments`` on a fresh Zenoh port; return the controller's result."""
    command = [sys.executable, "-m", "sim.launch", *arguments, "--out", str(out)]
    command += ["--interface", "zenoh", "--channel", "bench", "--bus-option", f"port={free_port()}"]
    launcher = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        launcher.wait(timeout)
    except subprocess.TimeoutExpired:
        launcher.terminate()  # the launcher stops its nodes and router on SIGTERM
        launcher.wait(30)
    result: dict[str, Any] = json.loads((out / "controller.json").read_text())
    return result


def lockstep_rows(runs: int, out: Path) -> list[list[str]]:
    factors = []
    for _ in range(runs):
        result = run_launcher(["reference", "--clock", "lockstep"], out, timeout=180)
        factors.append(result["realtime_factor"])
    median = statistics.median(factors)
    return [
        [
            f"lockstep, reference scenario: simulated / wall time ({runs} runs)",
            f"{median:.1f}x (runs: {', '.join(f'{f:.1f}' for f in factors)})",
            f">= {TARGET_LOCKSTEP:g}x",
            verdict(median >= TARGET_LOCKSTEP),
        ]
    ]


def realtime_rows(out: Path) -> list[list[str]]:
    arguments = ["endurance", "--clock", "realtime", "--rate", "1000"]
    result = run_launcher(arguments, out, timeout=120)
    loop = result["loop"]
    within = loop["answered_within_tick_fraction"] or 0.0
    return [
        [
            f"1 kHz, 30 s, normal priority: lateness p99 / missed deadlines "
            f"({loop['loops']} ticks)",
            f"{loop['lateness_p99_us']:.0f} us / {100 * loop['deadline_miss_fraction']:.2f} %",
            "reported",
            "",
        ],
        [
            "1 kHz: answered within a tick; round trip p50 / p99",
            f"{100 * within:.2f} %; {loop['answer_delay_p50_us']:.0f} / "
            f"{loop['answer_delay_p99_us']:.0f} us",
            "reported",
            "",
        ],
        [
            "1 kHz: the run",
            ("completed" if result["completed"] else "NOT completed")
            + f", faults {result['faults'] or 'none'}, holds {loop['holds']} "
            f"(longest {1e3 * loop['longest_hold_s']:.1f} ms)",
            "reported",
            "",
        ],
    ]


def verdict(passed: bool) -> str:
    return "PASS" if passed else "FAIL"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument("--quick", action="store_true", help="shorter; no 1 kHz run")
    parser.add_argument("--before", metavar="REV", help="also time the codec of this git revision")
    parser.add_argument("--json", type=Path, help="also write the rows as JSON here")
    args = parser.parse_args(argv)
    rows: list[list[str]] = []
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder)
        print("[1/3] codec", file=sys.stderr)
        rows += codec_rows(2000 if args.quick else 10000, args.before)
        print("[2/3] lockstep", file=sys.stderr)
        rows += lockstep_rows(1 if args.quick else 3, out)
        if not args.quick:
            print("[3/3] real time at 1 kHz on endurance", file=sys.stderr)
            rows += realtime_rows(out)
    print("| measurement | result | target | |")
    print("|---|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
