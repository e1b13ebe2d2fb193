"""Real-time link benchmark: the reference scenario at 500 Hz over CAN-over-Zenoh, at normal
priority, with plant, controller and two passive listeners on the bus, over several runs;
beside it, the floor: a bare two-process ping-pong on the same transport (one frame out,
three back, like a command and its joint state).

Prints a Markdown table: per run and in all, the controller's tick lateness p99, missed
deadlines, joint states answering a command within one tick, the command-to-state round
trip p50/p99, holds, and whether the run completed.

Run from the project root: ``python benchmarks/bench_link.py [--runs 10] [--load N]
[--plain-scheduling] [--json PATH]``. ``--load N`` adds N busy processes (a noisy
neighbour on a shared machine); ``--plain-scheduling`` runs the nodes without the precise
wake-ups of ``protocol/realtime.py``, to show what they bring.
"""

from __future__ import annotations

import argparse
import json
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can
import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # the tests' helpers: tests.support
from protocol.realtime import tune_process  # noqa: E402
from protocol.zenoh_can import ZenohBus  # noqa: E402
from protocol.zenoh_can.config import router_reachable  # noqa: E402
from tests.support import free_port  # noqa: E402

RATE_HZ = 500.0
TARGET_LATENESS_US = 200.0
TARGET_MISSES = 0.005
TARGET_ANSWERED = 0.995
PING = 0x100
SEQ = struct.Struct("<I")

LISTENER = """
import sys, can
bus = can.Bus(interface="zenoh", channel=sys.argv[1], port=int(sys.argv[2]))
print("ready", flush=True)
try:
    while True:
        bus.recv(1.0)
except KeyboardInterrupt:
    bus.shutdown()
"""

HOG = "while True: pass"


@contextmanager
def background(commands: list[list[str]]) -> Iterator[list[subprocess.Popen[bytes]]]:
    """Start ``commands``; interrupt (then kill) them at the end."""
    started = [
        subprocess.Popen(c, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        for c in commands
    ]
    try:
        yield started
    finally:
        for process in started:
            process.send_signal(2)
        for process in started:
            try:
                process.wait(5)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


@contextmanager
def router() -> Iterator[int]:
    port = free_port()
    command = [sys.executable, "-m", "protocol.zenoh_can.router", "--port", str(port)]
    with background([command]):
        deadline = time.monotonic() + 15
        while not router_reachable("127.0.0.1", port):
            if time.monotonic() > deadline:
                raise SystemExit("the router did not come up")
            time.sleep(0.05)
        yield port


def pong(port: int, seconds: float, plain: bool) -> None:
    """The floor's far end: answers each ping with three frames at once."""
    tune_process(plain=plain)
    bus = ZenohBus("floor", port=port)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        message = bus.recv(0.1)
        if message is not None and message.arbitration_id == PING:
            bus.send_many(  # as the plant answers: three frames sent together
                [
                    can.Message(arbitration_id=0x110 + offset, data=message.data[:7])
                    for offset in range(3)
                ]
            )
    bus.shutdown()


def ping(port: int, seconds: float, plain: bool) -> dict[str, float]:
    """The floor's near end: a ping every tick at absolute deadlines (sleeping), round trips
    from the bus's receive time of the third answer."""
    tune_process(plain=plain)
    bus = ZenohBus("floor", port=port)
    while not bus.has_receivers:
        time.sleep(0.01)
    time.sleep(0.5)
    period = 1.0 / RATE_HZ
    sent: dict[int, float] = {}
    trips: list[float] = []
    deadline = time.monotonic()
    ticks = int(seconds * RATE_HZ)
    for tick in range(ticks):
        deadline += period
        remaining = deadline - time.monotonic()
        if remaining > 0:
            time.sleep(remaining)
        while (message := bus.recv(0.0)) is not None:
            if message.arbitration_id == 0x112:
                answered = sent.pop(int(SEQ.unpack_from(message.data)[0]), None)
                if answered is not None:
                    trips.append(message.timestamp - answered)
        sent[tick] = time.time()
        bus.send(
            can.Message(arbitration_id=PING, data=SEQ.pack(tick) + bytes(4), is_extended_id=False)
        )
    bus.shutdown()
    round_trips = np.asarray(trips)
    return {
        "rtt_p50_us": float(np.percentile(round_trips, 50) * 1e6),
        "rtt_p99_us": float(np.percentile(round_trips, 99) * 1e6),
        "within_tick": float(np.sum(round_trips <= period)) / ticks,
    }


def floor(port: int, seconds: float, plain: bool) -> dict[str, float]:
    """Ping and pong, each in a process of its own (this one stays untuned: the nodes it
    starts would inherit its scheduling)."""
    flag = ["--plain-scheduling"] if plain else []
    me = [sys.executable, str(Path(__file__)), *flag]
    with background([[*me, "--pong", str(port), str(seconds + 10)]]):
        done = subprocess.run(
            [*me, "--ping", str(port), str(seconds)], cwd=ROOT, capture_output=True, text=True
        )
    if done.returncode != 0:
        raise SystemExit(f"the ping-pong failed: {done.stderr}")
    result: dict[str, float] = json.loads(done.stdout)
    return result


def run_once(port: int, out: Path, plain: bool) -> dict[str, Any]:
    channel = f"bench{port}"
    listeners = [[sys.executable, "-c", LISTENER, channel, str(port)] for _ in range(2)]
    with background(listeners) as started:
        for process in started:
            assert process.stdout is not None
            process.stdout.readline()  # "ready"
        command = [
            sys.executable, "-m", "sim.launch", "reference", "--clock", "realtime",
            "--rate", f"{RATE_HZ:g}", "--out", str(out), "--interface", "zenoh",
            "--channel", channel, "--bus-option", f"port={port}",
        ] + (["--plain-scheduling"] if plain else [])  # fmt: skip
        subprocess.run(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    result: dict[str, Any] = json.loads((out / "controller.json").read_text())
    return result


def summarise(result: dict[str, Any]) -> dict[str, Any]:
    loop = result["loop"]
    return {
        "completed": bool(result["completed"] and not result["faults"]),
        "lateness_p99_us": loop["lateness_p99_us"],
        "misses": loop["deadline_miss_fraction"],
        "within_tick": loop["answered_within_tick_fraction"] or 0.0,
        "rtt_p50_us": loop["answer_delay_p50_us"],
        "rtt_p99_us": loop["answer_delay_p99_us"],
        "holds": loop["holds"],
        "longest_hold_ms": 1e3 * loop["longest_hold_s"],
    }


def verdict(passed: bool) -> str:
    return "PASS" if passed else "FAIL"


def table(runs: list[dict[str, Any]], floor_result: dict[str, float]) -> str:
    lines = [
        "| run | completed | lateness p99 (us) | missed deadlines | answered within a tick "
        "| round trip p50 / p99 (us) | holds (longest ms) |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for index, run in enumerate(runs, 1):
        lines.append(
            f"| {index} | {'yes' if run['completed'] else 'NO'} | {run['lateness_p99_us']:.0f} "
            f"| {100 * run['misses']:.2f} % | {100 * run['within_tick']:.2f} % "
            f"| {run['rtt_p50_us']:.0f} / {run['rtt_p99_us']:.0f} "
            f"| {run['holds']} ({run['longest_hold_ms']:.1f}) |"
        )
    worst_late = max(run["lateness_p99_us"] for run in runs)
    worst_miss = max(run["misses"] for run in runs)
    worst_within = min(run["within_tick"] for run in runs)
    completed = sum(run["completed"] for run in runs)
    lines += [
        "",
        "| measure (all runs) | result | target | |",
        "|---|---|---|---|",
        f"| runs completed | {completed} of {len(runs)} | all "
        f"| {verdict(completed == len(runs))} |",
        f"| controller tick lateness p99, worst run (median) | {worst_late:.0f} us "
        f"({statistics.median(r['lateness_p99_us'] for r in runs):.0f}) "
        f"| <= {TARGET_LATENESS_US:g} us | {verdict(worst_late <= TARGET_LATENESS_US)} |",
        f"| missed deadlines, worst run | {100 * worst_miss:.2f} % | < {100 * TARGET_MISSES:g} % "
        f"| {verdict(worst_miss < TARGET_MISSES)} |",
        f"| joint state answering within one tick, worst run | {100 * worst_within:.2f} % "
        f"| >= {100 * TARGET_ANSWERED:g} % | {verdict(worst_within >= TARGET_ANSWERED)} |",
        f"| command-to-state round trip p50 / p99, median over runs "
        f"| {statistics.median(r['rtt_p50_us'] for r in runs):.0f} / "
        f"{statistics.median(r['rtt_p99_us'] for r in runs):.0f} us | reported | |",
        f"| the floor: bare two-process ping-pong, p50 / p99 (within a tick) "
        f"| {floor_result['rtt_p50_us']:.0f} / {floor_result['rtt_p99_us']:.0f} us "
        f"({100 * floor_result['within_tick']:.2f} %) | reported | |",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument("--runs", type=int, default=10, help="reference runs (default 10)")
    parser.add_argument("--load", type=int, default=0, help="busy processes beside the nodes")
    parser.add_argument("--plain-scheduling", action="store_true", help="nodes without tuning")
    parser.add_argument("--floor-seconds", type=float, default=10.0)
    parser.add_argument("--json", type=Path, help="also write the numbers as JSON here")
    parser.add_argument("--pong", nargs=2, help=argparse.SUPPRESS)
    parser.add_argument("--ping", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.pong:
        pong(int(args.pong[0]), float(args.pong[1]), args.plain_scheduling)
        return 0
    if args.ping:
        print(json.dumps(ping(int(args.ping[0]), float(args.ping[1]), args.plain_scheduling)))
        return 0
    hogs = [[sys.executable, "-c", HOG] for _ in range(args.load)]
    with background(hogs), router() as port, tempfile.TemporaryDirectory() as folder:
        print(f"[1/2] the floor: ping-pong for {args.floor_seconds:g} s", file=sys.stderr)
        floor_result = floor(port, args.floor_seconds, args.plain_scheduling)
        runs = []
        for index in tqdm(range(args.runs), desc="[2/2] reference runs", file=sys.stderr):
            out = Path(folder) / f"run{index}"
            runs.append(summarise(run_once(port, out, args.plain_scheduling)))
    print(table(runs, floor_result))
    if args.json:
        args.json.write_text(json.dumps({"floor": floor_result, "runs": runs}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
