"""A second OS process on the CAN-over-Zenoh bus, for tests and measurements.

Modes (all on 127.0.0.1; the port is the bus's well-known port):

``send``        sends ``--count`` frames, id 0x100, data = sequence number (uint32 LE) + 4 bytes,
                at ``--rate`` Hz (0: as fast as possible); ``--wait-receivers S`` first waits up
                to S seconds until a subscriber on the channel is known (the sender-first case).
``recv``        receives until ``--count`` sequence frames arrived or ``--timeout`` passed;
                prints a JSON summary (count, in order, frames/s).
``latency``     receives here while a ``send`` child sends at ``--rate`` Hz for ``--seconds``;
                prints one-way latency percentiles (receive time minus the sender's stamp;
                same clock, both processes on this machine).
``throughput``  as ``latency`` but the child sends ``--count`` frames as fast as it can.

Run from the project root, e.g.
``/work/venv/bin/python tests/zenoh_peer.py latency --port 17461 --rate 1000 --seconds 10``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import struct
import subprocess
import sys
import time
from pathlib import Path

import can

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from protocol.zenoh_can import ZenohBus  # noqa: E402

DATA_ID = 0x100
SEQ = struct.Struct("<I")


def frame(seq: int) -> can.Message:
    """The test frame carrying ``seq``; the rest of the data is a fixed marker."""
    return can.Message(
        arbitration_id=DATA_ID, is_extended_id=False, data=SEQ.pack(seq) + b"\xa5\x5a\xc3\x3c"
    )


def sequence_of(msg: can.Message) -> int | None:
    """The sequence number of a test frame, None for anything else."""
    if msg.arbitration_id != DATA_ID or len(msg.data) != 8:
        return None
    return int(SEQ.unpack_from(msg.data)[0])


def open_bus(args: argparse.Namespace) -> ZenohBus:
    extra = {} if args.linger is None else {"linger": args.linger}
    return ZenohBus(args.channel, port=args.port, express=bool(args.express), **extra)


def run_send(args: argparse.Namespace) -> int:
    bus = open_bus(args)
    print(json.dumps({"ready": bus.role}), flush=True)
    try:
        if args.wait_receivers > 0:
            deadline = time.monotonic() + args.wait_receivers
            while not bus.has_receivers:
                if time.monotonic() > deadline:
                    print(json.dumps({"error": "no receiver appeared"}), flush=True)
                    return 3
                time.sleep(0.005)
        period = 1.0 / args.rate if args.rate > 0 else 0.0
        start = time.monotonic()
        for seq in range(args.count):
            if period:
                delay = start + seq * period - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            msg = frame(seq)
            msg.timestamp = time.time()
            bus.send(msg)
        elapsed = time.monotonic() - start
    finally:
        bus.shutdown()
    print(json.dumps({"sent": args.count, "seconds": round(elapsed, 4)}), flush=True)
    return 0


def receive(bus: ZenohBus, count: int, timeout: float) -> dict[str, object]:
    """Collect sequence frames; latency samples are receive time minus the sender's stamp."""
    deadline = time.monotonic() + timeout
    seqs: list[int] = []
    latencies: list[float] = []
    first = last = 0.0
    while len(seqs) < count:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        msg = bus.recv(min(left, 0.5))
        if msg is None:
            continue
        seq = sequence_of(msg)
        if seq is None:
            continue
        now = time.time()
        latencies.append(now - msg.timestamp)
        last = time.monotonic()
        if not seqs:
            first = last
        seqs.append(seq)
    return {
        "count": len(seqs),
        "in_order": seqs == list(range(len(seqs))),
        "first": seqs[0] if seqs else None,
        "frames_per_s": round((len(seqs) - 1) / (last - first)) if len(seqs) > 1 else None,
        "latencies": latencies,
    }


def run_recv(args: argparse.Namespace) -> int:
    bus = open_bus(args)
    print(json.dumps({"ready": bus.role}), flush=True)
    try:
        summary = receive(bus, args.count, args.timeout)
    finally:
        bus.shutdown()
    summary.pop("latencies")
    print(json.dumps(summary), flush=True)
    return 0


def percentiles(values: list[float]) -> dict[str, float]:
    """p50, p99, p99.9 and max, in microseconds."""
    ordered = sorted(values)

    def at(q: float) -> float:
        return round(ordered[min(len(ordered) - 1, int(q * len(ordered)))] * 1e6, 1)

    return {
        "p50_us": at(0.50),
        "p99_us": at(0.99),
        "p99.9_us": at(0.999),
        "max_us": round(ordered[-1] * 1e6, 1),
        "mean_us": round(statistics.fmean(ordered) * 1e6, 1),
    }


def run_measure(args: argparse.Namespace, rate: float, count: int) -> int:
    bus = open_bus(args)
    child = subprocess.Popen(
        [
            sys.executable,
            __file__,
            "send",
            "--port",
            str(args.port),
            "--channel",
            args.channel,
            "--count",
            str(count),
            "--rate",
            str(rate),
            "--express",
            str(args.express),
            "--wait-receivers",
            "10",
            *([] if args.linger is None else ["--linger", str(args.linger)]),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        summary = receive(bus, count, args.timeout)
        out, _ = child.communicate(timeout=30)
    finally:
        if child.poll() is None:
            child.kill()
        bus.shutdown()
    latencies = summary.pop("latencies")
    assert isinstance(latencies, list)
    skip = min(len(latencies) // 100, 100)  # drop the start-up frames
    result = {
        "mode": args.mode,
        "rate_hz": rate,
        "express": bool(args.express),
        **summary,
        **(percentiles(latencies[skip:]) if latencies[skip:] else {}),
        "sender": json.loads(out.strip().splitlines()[-1]) if out.strip() else None,
    }
    print(json.dumps(result), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("mode", choices=["send", "recv", "latency", "throughput"])
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--channel", default="test")
    parser.add_argument("--count", type=int, default=5000)
    parser.add_argument("--rate", type=float, default=0.0)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--timeout", type=float, default=60.0)
    parser.add_argument("--wait-receivers", type=float, default=0.0)
    parser.add_argument("--express", type=int, default=0)
    parser.add_argument("--linger", type=float, default=None, help="bus default if not given")
    args = parser.parse_args(argv)
    if args.mode == "send":
        return run_send(args)
    if args.mode == "recv":
        return run_recv(args)
    if args.mode == "latency":
        rate = args.rate or 1000.0
        return run_measure(args, rate, int(rate * args.seconds))
    return run_measure(args, 0.0, args.count)


if __name__ == "__main__":
    sys.exit(main())
