"""A deliberately slow receiver in an OS process of its own, for the replay tests.

``can``    a python-can bus on the ``zenoh`` interface whose Zenoh thread needs ``--per-frame``
           s per frame it is handed (a busy process: it stops reading its link, so the
           router's queue and then the sender's fill) and whose reader sleeps ``--pause`` s
           between ``recv`` calls.
``zenoh``  a Zenoh subscriber of ``--key`` whose callback needs ``--per-frame`` s per sample.

It prints ``ready`` once subscribed, then ``got N`` each time its count changes (at most every
0.1 s), until SIGTERM.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import zenoh  # noqa: E402

from bridge.session import ZenohEndpoint  # noqa: E402
from protocol.zenoh_can import ZenohBus  # noqa: E402
from protocol.zenoh_can.frame import HEADER  # noqa: E402

FRAME_SIZE = HEADER.size + 8
"""Bytes of one classic 8-byte frame on the wire: the tests replay only those."""


class SlowBus(ZenohBus):
    """Its Zenoh thread spends ``per_frame`` s on each frame of a sample before queuing it."""

    def __init__(self, *args: Any, per_frame: float, **kwargs: Any) -> None:
        self.per_frame = per_frame
        super().__init__(*args, **kwargs)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        time.sleep(self.per_frame * (len(sample.payload.to_bytes()) // FRAME_SIZE))
        super()._on_sample(sample)


def report(count: list[int], stop: threading.Event) -> None:
    shown = -1
    while not stop.wait(0.1):
        if count[0] != shown:
            shown = count[0]
            print(f"got {shown}", flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("mode", choices=["can", "zenoh"])
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--channel", default="slow")
    parser.add_argument("--key", default="scara/demo/tcp")
    parser.add_argument("--per-frame", type=float, default=0.0)
    parser.add_argument("--pause", type=float, default=0.0)
    args = parser.parse_args()
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    count = [0]
    if args.mode == "can":
        bus = SlowBus(args.channel, port=args.port, per_frame=args.per_frame, linger=0)
        print("ready", flush=True)
        threading.Thread(target=report, args=(count, stop), daemon=True).start()
        while not stop.is_set():
            if bus.recv(0.1) is not None:
                count[0] += 1
                time.sleep(args.pause)
        bus.shutdown()
        return 0

    def on_sample(sample: zenoh.Sample) -> None:
        time.sleep(args.per_frame)
        count[0] += 1

    session = ZenohEndpoint("127.0.0.1", args.port).open()
    subscriber = session.declare_subscriber(args.key, on_sample)
    print("ready", flush=True)
    report(count, stop)
    subscriber.undeclare()  # type: ignore[no-untyped-call]
    session.close()  # type: ignore[no-untyped-call]
    return 0


if __name__ == "__main__":
    sys.exit(main())
