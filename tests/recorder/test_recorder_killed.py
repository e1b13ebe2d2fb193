"""A ``scara-record`` process killed with SIGKILL at a random moment of a steady frame stream
loses at most its last :data:`~recorder.node.FLUSH_PERIOD` of frames, and ``scara-record
recover`` says what the file holds and what it could not keep, in numbers that match the
recovered file (read back with the ``mcap`` library)."""

from __future__ import annotations

import random
import re
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from support import ROOT, SLOWDOWN, Processes, Transport, frame, wait_until

from protocol.zenoh_can import ZenohBus
from recorder.mcap_can import FLUSH_PERIOD

pytestmark = pytest.mark.timeout(120)

SOURCE_ID = 0x321
SEQ = struct.Struct("<I")
RATE = 1000.0
"""frames/s of the test's source: a 1 kHz run's order of magnitude."""
HOP = 0.1
"""s a frame may take from the source to the recorder's writer on a loaded 2-core machine
(the router's hop, the recorder's threads, a stall of the machine), on top of the
recorder's own bound: times SLOWDOWN."""


class Source:
    """Sends frame ``i`` (data: ``i``) at ``i / RATE`` s on its own clock, in a thread; keeps
    the wall-clock time each frame was handed to the bus."""

    def __init__(self, bus: ZenohBus) -> None:
        self.bus = bus
        self.sent: list[float] = []
        self._running = True
        self._thread = threading.Thread(target=self._run, name="source", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        start = time.monotonic()
        while self._running:
            index = len(self.sent)
            delay = start + index / RATE - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            self.sent.append(time.time())
            self.bus.send(frame(SOURCE_ID, SEQ.pack(index) + bytes(4)))

    def stop(self) -> list[float]:
        self._running = False
        self._thread.join(5 * SLOWDOWN)
        self.bus.shutdown()
        return self.sent


def kept_sequence(path: Path) -> tuple[list[int], int]:
    """The source's sequence numbers in the recovered file, in file order, and the number of
    CAN frames it holds (``mcap``'s own reader)."""
    numbers, frames = [], 0
    with path.open("rb") as stream:
        for _, channel, message in make_reader(stream).iter_messages(log_time_order=False):
            if channel.message_encoding != "can-frame":
                continue
            frames += 1
            data = message.data
            if channel.metadata["id_in_data"] == "true":  # can/other: SocketCAN's can_id first
                frame_id, data = struct.unpack_from(">I", data)[0] & 0x1FFF_FFFF, data[4:]
            else:
                frame_id = int(channel.metadata["arbitration_id"])
            if frame_id == SOURCE_ID:
                numbers.append(SEQ.unpack_from(data)[0])
    return numbers, frames


def test_a_recorder_killed_at_any_moment_loses_at_most_its_last_flush_period(
    router: int, processes: Processes, tmp_path: Path
) -> None:
    transport = Transport("zenoh", f"kill{router}", {"port": router})
    file = tmp_path / "killed.mcap"
    recorder = processes.start("recorder.node", "--out", str(file), *transport.cli())
    bus = transport.open_bus()
    assert isinstance(bus, ZenohBus)
    wait_until(lambda: bus.has_receivers, 30.0, "the recorder's bus to subscribe")
    wait_until(lambda: "recording to" in recorder.output(), 30.0, "the recorder to start")
    seed = random.randrange(2**32)
    moment = random.Random(seed).uniform(0.5, 3.0)
    source = Source(bus)
    time.sleep(moment)
    killed = time.time()
    recorder.signal(signal.SIGKILL)
    sent = source.stop()
    assert recorder.wait(5.0) == -signal.SIGKILL, recorder.output()

    done = subprocess.run(
        [sys.executable, "-m", "recorder.node", "recover", str(file)],
        cwd=ROOT, capture_output=True, text=True, timeout=60 * SLOWDOWN,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    report = done.stdout
    numbers, frames = kept_sequence(file.with_suffix(".recovered.mcap"))
    context = f"seed {seed}, killed {moment:.3f} s in, {len(sent)} sent\n{report}"

    # what was kept is the start of the stream, and nothing older than the bound is missing
    assert numbers == list(range(len(numbers))), context
    bound = killed - (FLUSH_PERIOD + HOP) * SLOWDOWN
    due = sum(1 for at in sent if at <= bound)
    assert len(numbers) >= due, f"{due - len(numbers)} frames sent before the bound lost; {context}"

    # the report: what the file holds, what the recorder counted, never "nothing lost"
    assert "was cut short" in report and " 0 of " not in report, context
    kept = re.search(r"kept (\d+) CAN frames", report)
    assert kept is not None and int(kept[1]) == frames, context
    counted = re.search(r"(\d+) frames received, (\d+) dropped", report)
    assert counted is not None, context
    received, dropped = int(counted[1]), int(counted[2])
    assert dropped == 0 and received <= len(sent), context
    missing = max(0, received - frames)
    assert (f"{missing} of them not in the file" in report) == (missing > 0), context
    assert "cannot be counted" in report, context
