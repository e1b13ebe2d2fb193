"""python-can's own tools as outside clients of the CAN-over-Zenoh transport: ``can.logger``
records what a bus sends, ``can.player`` replays a file onto the bus, and the curses
``can.viewer`` (in a real tmux terminal) shows the plant's frames."""

from __future__ import annotations

import shutil
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest
from support import ROOT, SLOWDOWN, native_stacks, wait_until

from protocol.zenoh_can import ZenohBus

SEQ = struct.Struct("<I")
DATA_ID = 0x100

pytestmark = pytest.mark.timeout(90)


@pytest.fixture
def bus(router: int) -> Iterator[ZenohBus]:
    opened = ZenohBus("tools", port=router)
    yield opened
    opened.shutdown()


def tool(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # a group of its own, for native_stacks
    )


@pytest.mark.parametrize("suffix", [".log", ".asc"])
def test_can_logger_records_what_the_bus_sends(
    bus: ZenohBus, router: int, tmp_path: Path, suffix: str
) -> None:
    log_file = tmp_path / f"recorded{suffix}"
    logger = tool(
        "can.logger", "-i", "zenoh", "-c", "tools", "--bus-kwargs", f"port={router}",
        "-f", str(log_file),
    )  # fmt: skip
    try:
        wait_until(lambda: bus.has_receivers or logger.poll() is not None, 20, "can.logger")
        assert logger.poll() is None, logger.communicate()[1]
        sent = [
            can.Message(arbitration_id=0x200 + i, is_extended_id=False, data=SEQ.pack(i))
            for i in range(200)
        ]
        for msg in sent:
            bus.send(msg)
        # the logger receives as it goes, writes the file on SIGINT and drops what it has not
        # taken from its bus by then
        time.sleep(1.0 * SLOWDOWN)
        logger.send_signal(signal.SIGINT)
        try:
            _, err = logger.communicate(timeout=20 * SLOWDOWN)
        except subprocess.TimeoutExpired:
            raise AssertionError(
                f"can.logger ignored SIGINT\n{native_stacks(logger.pid)}"
            ) from None
    finally:
        if logger.poll() is None:
            logger.kill()
            logger.communicate(timeout=10 * SLOWDOWN)
    assert logger.returncode == 0, err
    with can.LogReader(log_file) as reader:
        logged = list(reader)
    assert [(m.arbitration_id, bytes(m.data)) for m in logged] == [
        (m.arbitration_id, bytes(m.data)) for m in sent
    ]
    stamps = [m.timestamp for m in logged]
    assert stamps == sorted(stamps)  # receive times, in order


@pytest.mark.parametrize("suffix", [".blf", ".asc"])
def test_can_player_replays_a_file_onto_the_bus(
    bus: ZenohBus, router: int, tmp_path: Path, suffix: str
) -> None:
    count = 2000
    recording = tmp_path / f"replay{suffix}"
    t0 = 1_700_000_000.0
    with can.Logger(recording) as writer:
        for i in range(count):
            writer.on_message_received(
                can.Message(
                    timestamp=t0 + i * 1e-5,
                    arbitration_id=DATA_ID,
                    is_extended_id=False,
                    data=SEQ.pack(i) + b"\xa5\x5a\xc3\x3c",
                    channel=0,
                )
            )
    # --bus-kwargs takes one or more words: end it with "--" before the file name.
    player = tool(
        "can.player", "-i", "zenoh", "-c", "tools", "-g", "0", "--bus-kwargs", f"port={router}",
        "--", str(recording),
    )  # fmt: skip
    got: list[can.Message] = []
    deadline = time.monotonic() + 30 * SLOWDOWN
    while len(got) < count and time.monotonic() < deadline:
        message = bus.recv(0.5)
        if message is not None:
            got.append(message)
    _, err = player.communicate(timeout=30 * SLOWDOWN)
    assert player.returncode == 0, err
    assert [int(SEQ.unpack_from(m.data)[0]) for m in got] == list(range(count))
    assert all(m.arbitration_id == DATA_ID and not m.is_extended_id for m in got)


@pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux is not installed")
def test_can_viewer_shows_the_plants_frames(router: int) -> None:
    session = f"viewer-{router}"
    viewer = f"{sys.executable} -m can.viewer -i zenoh -c scara --bus-kwargs port={router}"
    subprocess.run(
        ["tmux", "new-session", "-d", "-s", session, "-x", "160", "-y", "40", viewer], check=True
    )
    try:
        probe = ZenohBus("scara", port=router)  # sees the viewer's bus subscribe
        try:
            wait_until(lambda: probe.has_receivers, 30.0, "can.viewer's bus to subscribe")
        finally:
            probe.shutdown()
        plant = [sys.executable, "-m", "plant_sim.node", "--duration", "3"]
        subprocess.run(
            [*plant, "--bus-option", f"port={router}"],
            check=True, timeout=30 * SLOWDOWN, capture_output=True,
        )  # fmt: skip
        screen = subprocess.run(
            ["tmux", "capture-pane", "-t", session, "-p"], capture_output=True, text=True
        ).stdout
    finally:
        subprocess.run(["tmux", "kill-session", "-t", session], capture_output=True)
    rows = {line.split()[3]: line.split() for line in screen.splitlines() if "0x" in line}
    assert {"0x110", "0x111", "0x112", "0x701"} <= set(rows), screen
    assert int(rows["0x110"][0]) > 1000  # about 500 Hz for 3 s, idle-state frames
    assert rows["0x110"][4] == "7"  # DLC of JointState1
