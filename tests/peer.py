"""A CAN-over-Zenoh bus in an OS process of its own, for the transport tests.

Modes (the router's port is ``--port``, on 127.0.0.1):

``send``    sends ``--count`` frames, id 0x100, data = sequence number (uint32 LE) + 4 bytes,
            as fast as it can; ``--wait-receivers S`` first waits up to S seconds until a
            subscriber on the channel is known. Prints ``{"ready": true}`` once its bus is
            open, then ``{"sent": N}``.
``member``  one participant of a shared channel: every ``--period`` s it sends a frame
            carrying its number (``--index``), its run (``--run``, which restart of it this
            is) and a sequence number; it logs ``joined TIME`` once its bus is open, ``sent
            TIME SEQ`` per frame sent and ``got TIME INDEX RUN SEQ`` per frame received
            (flushed at once, so a member killed with SIGKILL leaves what it got).
"""

from __future__ import annotations

import argparse
import json
import struct
import sys
import time
from pathlib import Path

import can

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from protocol.zenoh_can import ZenohBus  # noqa: E402

DATA_ID = 0x100
MEMBER_ID = 0x200
SEQ = struct.Struct("<I")
MEMBER = struct.Struct("<BBI")


def frame(seq: int) -> can.Message:
    """The test frame carrying ``seq``; the rest of the data is a fixed marker."""
    return can.Message(
        arbitration_id=DATA_ID, is_extended_id=False, data=SEQ.pack(seq) + b"\xa5\x5a\xc3\x3c"
    )


def run_send(args: argparse.Namespace) -> int:
    bus = ZenohBus(args.channel, port=args.port, linger=args.linger)
    print(json.dumps({"ready": True}), flush=True)
    try:
        deadline = time.monotonic() + args.wait_receivers
        while args.wait_receivers and not bus.has_receivers:
            if time.monotonic() > deadline:
                print(json.dumps({"error": "no receiver appeared"}), flush=True)
                return 3
            time.sleep(0.005)
        for seq in range(args.count):
            bus.send(frame(seq))
    finally:
        bus.shutdown()
    print(json.dumps({"sent": args.count}), flush=True)
    return 0


def run_member(args: argparse.Namespace) -> int:
    bus = ZenohBus(args.channel, port=args.port, linger=0)
    seq = 0
    next_send = time.monotonic()
    with args.log.open("a", buffering=1) as log:
        log.write(f"joined {time.time():.6f}\n")
        while True:
            now = time.monotonic()
            if now >= next_send:
                data = MEMBER.pack(args.index, args.run, seq)
                bus.send(can.Message(arbitration_id=MEMBER_ID, data=data, is_extended_id=False))
                log.write(f"sent {time.time():.6f} {seq}\n")
                seq += 1
                next_send += args.period
            message = bus.recv(max(0.0, next_send - time.monotonic()))
            if message is not None and message.arbitration_id == MEMBER_ID:
                index, run, their_seq = MEMBER.unpack(bytes(message.data))
                log.write(f"got {message.timestamp:.6f} {index} {run} {their_seq}\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("mode", choices=["send", "member"])
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--channel", default="test")
    parser.add_argument("--count", type=int, default=5000)
    parser.add_argument("--wait-receivers", type=float, default=0.0)
    parser.add_argument("--linger", type=float, default=2.0)
    parser.add_argument("--index", type=int, default=0)
    parser.add_argument("--run", type=int, default=0)
    parser.add_argument("--period", type=float, default=0.01)
    parser.add_argument("--log", type=Path)
    args = parser.parse_args(argv)
    if args.mode == "send":
        return run_send(args)
    return run_member(args)


if __name__ == "__main__":
    sys.exit(main())
