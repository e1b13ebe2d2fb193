"""Co-simulation benchmark: the codec, the real-time loop at 1 kHz, and lockstep speed.

Measures, in one run on this machine:

1. one encode and one decode of each cyclic frame (target: at most 5 us each);
2. plant and controller as two processes on the CAN-over-Zenoh transport, real time at
   1 kHz for 30 s (the ``endurance`` scenario): controller tick lateness p99 (target at most
   200 us), missed deadlines (under 0.5 %), joint state answering a command within one tick
   (99.9 %); once at normal priority and once under SCHED_FIFO (``--realtime-priority``);
3. lockstep on the reference scenario: simulated time over wall time (target at least 5x).

Run from the project root: ``python benchmarks/bench_cosim.py [--quick] [--json PATH]``.
"""

from __future__ import annotations

import argparse
import json
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from protocol.messages import COMMAND, STATE

TARGET_CODEC_US = 5.0
TARGET_LATENESS_US = 200.0
TARGET_MISSES = 0.005
TARGET_ANSWERED = 0.999
TARGET_LOCKSTEP = 5.0


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def codec_rows(repeats: int) -> list[list[str]]:
    rows = []
    cases = [(COMMAND, (1, 1.234, -5.5, 0.3)), (STATE[0], (3, -2.123456, 3.21))]
    for codec, values in cases:
        data = codec.encode(values, 5)
        for what, call in (
            ("encode", lambda c=codec, v=values: c.encode(v, 5)),
            ("decode", lambda c=codec, d=data: c.decode(d)),
        ):
            samples = []
            for _ in range(20):
                started = time.perf_counter_ns()
                for _ in range(repeats):
                    call()
                samples.append((time.perf_counter_ns() - started) / repeats / 1000)
            median = statistics.median(samples)
            rows.append(
                [
                    f"{codec.name} {what}",
                    f"{median:.2f} us",
                    f"<= {TARGET_CODEC_US:g} us",
                    verdict(median <= TARGET_CODEC_US),
                ]
            )
    return rows


def run_launcher(arguments: list[str], out: Path, timeout: float) -> dict[str, Any]:
    """Run scara-run with ``arguments`` on a fresh Zenoh port; return the controller's result."""
    command = [sys.executable, "-m", "controller.launch", *arguments, "--out", str(out)]
    command += ["--interface", "zenoh", "--channel", "bench"]
    command += ["--bus-option", f"port={free_port()}", "--bus-option", "lowlatency=true"]
    launcher = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        launcher.wait(timeout)
    except subprocess.TimeoutExpired:
        launcher.terminate()  # the launcher stops its two nodes on SIGTERM
        launcher.wait(30)
    result: dict[str, Any] = json.loads((out / "controller_result.json").read_text())
    return result


def realtime_rows(duration_scenario: str, priority: int | None, out: Path) -> list[list[str]]:
    arguments = [duration_scenario, "--clock", "realtime", "--rate", "1000"]
    label = "normal priority"
    if priority is not None:
        arguments += ["--realtime-priority", str(priority)]
        label = f"SCHED_FIFO {priority}"
    result = run_launcher(arguments, out, timeout=120)
    loop = result["loop"]
    loop["answered_within_tick_fraction"] = loop["answered_within_tick_fraction"] or 0.0
    return [
        [
            f"1 kHz real time, {label}: tick lateness p99 ({loop['loops']} ticks, "
            f"{result['wall_time_s']:.0f} s)",
            f"{loop['lateness_p99_us']:.0f} us (p50 {loop['lateness_p50_us']:.0f}, "
            f"max {loop['lateness_max_us']:.0f})",
            f"<= {TARGET_LATENESS_US:g} us",
            verdict(loop["lateness_p99_us"] <= TARGET_LATENESS_US),
        ],
        [
            f"1 kHz real time, {label}: missed deadlines",
            f"{100 * loop['deadline_miss_fraction']:.2f} % ({loop['deadline_misses']})",
            f"< {100 * TARGET_MISSES:g} %",
            verdict(loop["deadline_miss_fraction"] < TARGET_MISSES),
        ],
        [
            f"1 kHz real time, {label}: state answering a command within one tick",
            f"{100 * loop['answered_within_tick_fraction']:.2f} % (p50 "
            f"{loop['answer_delay_p50_us']:.0f} us, p99 {loop['answer_delay_p99_us']:.0f} us)",
            f">= {100 * TARGET_ANSWERED:g} %",
            verdict(loop["answered_within_tick_fraction"] >= TARGET_ANSWERED),
        ],
        [
            f"1 kHz real time, {label}: run",
            f"{'completed' if result['completed'] else 'NOT completed'}"
            + (f", faults {result['faults']}" if result["faults"] else ", no faults"),
            "completed",
            verdict(result["completed"] and not result["faults"]),
        ],
    ]


def lockstep_rows(runs: int, out: Path) -> list[list[str]]:
    factors = []
    for _ in range(runs):
        result = run_launcher(["reference", "--clock", "lockstep"], out, timeout=120)
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


def verdict(passed: bool) -> str:
    return "PASS" if passed else "FAIL"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Benchmark the CAN codec and the two-process co-simulation over Zenoh.",
    )
    parser.add_argument("--quick", action="store_true", help="the reference scenario at 1 kHz")
    parser.add_argument("--priority", type=int, default=50, help="SCHED_FIFO priority to try")
    parser.add_argument("--json", type=Path, help="also write the rows as JSON here")
    args = parser.parse_args(argv)
    scenario = "reference" if args.quick else "endurance"
    rows: list[list[str]] = []
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder)
        print("[1/3] codec", file=sys.stderr)
        rows += codec_rows(2000 if args.quick else 10000)
        print(f"[2/3] real time at 1 kHz on {scenario}, twice", file=sys.stderr)
        rows += realtime_rows(scenario, None, out)
        rows += realtime_rows(scenario, args.priority, out)
        print("[3/3] lockstep", file=sys.stderr)
        rows += lockstep_rows(1 if args.quick else 3, out)
    print("| measurement | result | target | |")
    print("|---|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
