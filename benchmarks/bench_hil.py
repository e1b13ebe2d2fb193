"""The link on one transport, for the comparison of SocketCAN vcan0 (in ``tools/vcan-vm``, or
on a Linux host that has it) with CAN over Zenoh on the host: lockstep speed, then the
controller's tick lateness, missed deadlines, command-to-state round trip and holds over
real-time runs of the reference scenario (500 Hz).

Run from the project root: ``python benchmarks/bench_hil.py --transport zenoh`` on the host,
``tools/vcan-vm -- .venv/bin/python benchmarks/bench_hil.py --transport vcan0`` in the VM.
Prints one Markdown table row per measure; ``--json`` also writes the numbers.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from bench_link import RATE_HZ, router, summarise

ROOT = Path(__file__).resolve().parent.parent


def run(transport: list[str], clock: str, out: Path) -> dict[str, Any]:
    """One reference run through ``scara-run`` (no recording): the controller's result."""
    command = [
        sys.executable, "-m", "sim.launch", "reference", "--clock", clock, "--no-record",
        "--rate", f"{RATE_HZ:g}", "--out", str(out), *transport,
    ]  # fmt: skip
    subprocess.run(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    result: dict[str, Any] = json.loads((out / "controller.json").read_text())
    return result


@contextmanager
def bus(name: str) -> Iterator[list[str]]:
    """The launcher's flags for transport ``name`` (with a router for Zenoh)."""
    if name == "vcan0":
        yield ["--interface", "socketcan", "--channel", "vcan0"]
    else:
        with router() as port:
            yield [
                "--interface",
                "zenoh",
                "--channel",
                f"hil{port}",
                "--bus-option",
                f"port={port}",
            ]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument("--transport", choices=["vcan0", "zenoh"], required=True)
    parser.add_argument("--runs", type=int, default=3, help="real-time runs (default 3)")
    parser.add_argument("--json", type=Path, help="also write the numbers as JSON here")
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error(f"argument --runs: must be at least 1, got {args.runs}")
    with bus(args.transport) as transport, tempfile.TemporaryDirectory() as folder:
        print(f"{args.transport}: one lockstep run...", file=sys.stderr)
        lockstep = run(transport, "lockstep", Path(folder) / "lockstep")
        ticks, wall = lockstep["loop"]["ticks"], lockstep["wall_time_s"]
        realtime = []
        for index in range(args.runs):
            print(f"{args.transport}: real-time run {index + 1}/{args.runs}...", file=sys.stderr)
            realtime.append(summarise(run(transport, "realtime", Path(folder) / f"rt{index}")))
    rows = {
        "lockstep: ticks per second (completed)": (
            f"{ticks / wall:.0f} ({'yes' if lockstep['completed'] else 'NO'})"
        ),
        "lockstep: retries per tick": f"{lockstep['loop']['lockstep_retries'] / ticks:.2f}",
        "real time: runs completed": f"{sum(r['completed'] for r in realtime)} of {args.runs}",
        "real time: tick lateness p99, median of runs": (
            f"{statistics.median(r['lateness_p99_us'] for r in realtime):.0f} us"
        ),
        "real time: missed deadlines, worst run": (
            f"{100 * max(r['misses'] for r in realtime):.2f} %"
        ),
        "real time: round trip p50 / p99, median of runs": (
            f"{statistics.median(r['rtt_p50_us'] for r in realtime):.0f} / "
            f"{statistics.median(r['rtt_p99_us'] for r in realtime):.0f} us"
        ),
        "real time: answered within a tick, worst run": (
            f"{100 * min(r['within_tick'] for r in realtime):.2f} %"
        ),
        "real time: holds, worst run (longest)": (
            f"{max(r['holds'] for r in realtime)} "
            f"({max(r['longest_hold_ms'] for r in realtime):.1f} ms)"
        ),
    }
    print(f"| measure | {args.transport} |\n|---|---:|")
    for label, value in rows.items():
        print(f"| {label} | {value} |")
    if args.json:
        numbers = {"lockstep_ticks_per_s": ticks / wall, "realtime": realtime}
        args.json.write_text(json.dumps(numbers, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
