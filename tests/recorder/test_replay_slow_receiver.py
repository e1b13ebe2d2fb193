"""``scara-replay --as-fast-as-possible`` to a deliberately slow receiver in a process of its
own, stopped for a while mid-replay (a busy machine): every frame (``--to can``) or sample
(``--to zenoh``) arrives, and the replay says who confirmed it; never "all sent" with whole
batches lost on the way (closing a Zenoh session drops what is still in flight)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from support import ROOT, SLOWDOWN, wait_until

from protocol.keys import DEFAULT_ROBOT, state_key
from recorder.mcap_can import finish, open_writer
from recorder.replay import deliver_frames

pytestmark = pytest.mark.timeout(300)

RECEIVER = Path(__file__).with_name("slow_receiver.py")
FRAMES = 20_000
"""Frames replayed, in batches of 256: sent in well under a second."""
SAMPLES = 50_000
"""Decoded-state samples replayed, one put each."""
STALL = 3.0
"""s the receiver stops (SIGSTOP) mid-replay: longer than the 2 s a bus lingers at shutdown
for its receivers, shorter than the 5 s after which Zenoh closes a link blocked that long."""


class Receiver:
    """``slow_receiver.py`` as a process of its own; the last count it printed."""

    def __init__(self, *args: str) -> None:
        self.popen = subprocess.Popen(
            [sys.executable, str(RECEIVER), *args],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            start_new_session=True,
        )  # fmt: skip
        self.count = 0
        self.ready = threading.Event()
        self.lines: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.lines.append(line)
            if line.startswith("ready"):
                self.ready.set()
            elif line.startswith("got "):
                self.count = int(line.split()[1])

    def close(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.popen.pid, signal.SIGKILL)
        self.popen.wait(10)


@contextlib.contextmanager
def receiver(*args: str) -> Iterator[Receiver]:
    started = Receiver(*args)
    try:
        wait_until(started.ready.is_set, 30.0, "the slow receiver to subscribe")
        yield started
    finally:
        started.close()


def replay_through_a_stall(got: Receiver, *args: str) -> subprocess.CompletedProcess[str]:
    """``scara-replay ARGS --as-fast-as-possible``, its receiver stopped for :data:`STALL` s
    once the first frames have come (the replay is then done sending, its frames in flight)."""
    started = subprocess.Popen(
        [sys.executable, "-m", "recorder.replay", *args, "--as-fast-as-possible"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        wait_until(lambda: got.count > 0, 30.0, "the first frames to arrive")
        os.kill(got.popen.pid, signal.SIGSTOP)
        time.sleep(STALL)
        os.kill(got.popen.pid, signal.SIGCONT)
        out, err = started.communicate(timeout=240 * SLOWDOWN)
    finally:
        if started.poll() is None:
            started.kill()
            started.wait()
    return subprocess.CompletedProcess(started.args, started.returncode, out, err)


def all_arrived(done: subprocess.CompletedProcess[str], got: Receiver, total: int, by: str) -> None:
    """The replay confirmed that ``by`` took everything, and everything arrived. (It cannot
    count what a receiver missed, so confirming is the only way it may say "sent".)"""
    assert done.returncode == 0, done.stderr
    assert f"{total} " in done.stderr and f"sent, taken by {by}" in done.stderr, done.stderr
    wait_until(lambda: got.count >= total, 30.0, f"all {total} to arrive ({got.lines[-3:]})")
    assert got.count == total, done.stderr


def test_a_replay_as_fast_as_possible_reaches_a_slow_can_receiver_whole(
    router: int, tmp_path: Path
) -> None:
    file = tmp_path / "many.mcap"
    with can.Logger(file) as writer:
        for index in range(FRAMES):
            writer.on_message_received(
                can.Message(
                    timestamp=1_800_000_000.0 + index * 1e-4,
                    arbitration_id=0x123,
                    data=index.to_bytes(4, "little") + bytes(4),
                    is_extended_id=False,
                )
            )
    channel = f"slow{router}"
    bus = ["--interface", "zenoh", "--channel", channel, "--bus-option", f"port={router}"]
    with receiver(
        "can", "--port", str(router), "--channel", channel, "--per-frame", "40e-6",
        "--pause", "1e-5",
    ) as got:  # fmt: skip
        done = replay_through_a_stall(got, str(file), *bus)
        all_arrived(done, got, FRAMES, "the 1 bus listening")


def test_a_replay_onto_the_zenoh_keys_reaches_a_slow_subscriber_whole(
    router: int, tmp_path: Path
) -> None:
    file = tmp_path / "state.mcap"
    with file.open("wb") as stream:
        writer = open_writer(stream)
        channel = writer.register_channel("scara/tcp", "json", 0)
        for index in range(SAMPLES):
            stamp = 1_800_000_000_000_000_000 + index * 10_000_000
            payload = {"t": stamp / 1e9, "seq": index, "x": 0.3, "y": 0.0, "z": 0.2}
            writer.add_message(channel, stamp, json.dumps(payload).encode(), stamp)
        finish(writer)
    key = state_key(DEFAULT_ROBOT, "tcp")
    with receiver("zenoh", "--port", str(router), "--key", key, "--per-frame", "2e-5") as got:
        done = replay_through_a_stall(got, str(file), "--to", "zenoh", "--zenoh-port", str(router))
        all_arrived(done, got, SAMPLES, "the router")


class StalledBus:
    """A bus whose receivers never confirm: its flush barrier runs out its timeout."""

    def flush(self, timeout: float) -> int:
        time.sleep(timeout)
        return 0


def test_a_replay_that_cannot_confirm_delivery_says_so() -> None:
    delivery = deliver_frames(StalledBus(), 0.05)  # type: ignore[arg-type]
    assert delivery is not None and not delivery.confirmed
    assert delivery.summary().startswith("NOT confirmed taken by the 0 buses listening within")
    with can.Bus(interface="virtual", channel="confirm") as bus:  # no barrier: sent is sent
        assert deliver_frames(bus, 1.0) is None
