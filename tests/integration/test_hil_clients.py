"""The ``hil`` tier's outside clients: the nodes on SocketCAN ``vcan0`` as a user's Linux host
has it, seen and prodded by tools that are not ours, Debian's can-utils and cantools' command
line (``hil_clients.py``).

- ``candump -L`` captures a lockstep run; ``cantools decode`` with the project's DBC decodes
  every frame of it, the commands it decodes are those the controller logged, and the
  recorder's MCAP holds the very frames candump saw.
- ``cansend`` puts bad frames on the bus during a run: each is counted by the plant, none
  acted on, and the run stays bit-identical to the in-process simulation.
- ``canplayer`` replays the controller's side of the capture into a plant alone, which moves
  exactly as it did in the run.
- ``cangen`` floods the bus with unrelated IDs during a lockstep run, which completes with
  the same measures.

Runs in CI inside ``tools/vcan-vm`` (``.ci/run``); on a host with vcan0, ``python -m pytest
-m hil``.
"""

from __future__ import annotations

import json
import signal
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest
from cosim import (
    CONTROLLER_IDS,
    assert_bit_identical,
    brief,
    decode,
    finish_clean,
    launch,
    node_args,
)
from hil_clients import (
    Candump,
    Captured,
    background,
    can_util,
    cansend,
    cantools_decode,
    write_capture,
)
from support import (
    SLOWDOWN,
    Observer,
    Processes,
    Transport,
    hil_marks,
    wait_while_growing,
)

from protocol.e2e import RESYNC_AFTER
from protocol.messages import COMMAND, PLANT_STATUS, STATE_IDS, STEP, on_the_wire_command
from protocol.scenario import Mode
from recorder.mcap_can import MCAPReader
from sim.report import read_run

pytestmark = hil_marks()

VCAN = Transport("socketcan", "vcan0")
HEARD = 60.0
"""s a node may take to start and be heard on the bus (an emulated VM imports slowly)."""
FLOOD_GAP_MS = 0.2
"""ms between the frames of each cangen flood: 5000 frames/s each, two floods, more than a CAN
bus at full load carries (about 8000 frames/s at 1 Mbit/s). In the emulated VM, where python
runs SLOWDOWN times slower, the gap is stretched as much: at a tenth of this, faster than the
emulated nodes could read, the queue before the plant's answer grew until the controller gave
the plant up (CI)."""
FOREIGN_ID = 0x7E8
"""A standard ID the DBC does not define (an OBD-II answer: another system's traffic)."""


@dataclass(frozen=True, slots=True)
class CapturedRun:
    capture: Path
    frames: list[Captured]
    out: Path
    result: dict[str, Any]


@pytest.fixture(scope="module")
def captured_run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[CapturedRun]:
    """A lockstep run of the reference scenario (fuzzy) with ``candump -L vcan0`` capturing."""
    folder = tmp_path_factory.mktemp("captured")
    processes = Processes(folder)
    try:
        with Candump(folder / "capture.log") as candump:
            code, result = launch(processes, VCAN, folder / "run", "lockstep")
            frames = candump.stop()
        assert code == 0, f"{brief(result)}\n{processes.outputs()}"
        yield CapturedRun(folder / "capture.log", frames, folder / "run", result)
    finally:
        processes.close()


def test_cantools_decodes_every_captured_frame_and_the_commands_are_those_logged(
    captured_run: CapturedRun,
) -> None:
    decoded = cantools_decode(captured_run.capture)
    assert len(decoded) == len(captured_run.frames)
    # Each StepSync names the command the plant steps under; retries repeat its rates.
    latest: dict[int, tuple[float, float, float]] = {}
    stepped: dict[int, tuple[float, float, float]] = {}
    for frame in decoded:
        if frame.message == COMMAND.name:
            rates = tuple(frame.signals[name] for name in ("Theta1Rate", "Theta2Rate", "D3Rate"))
            latest[int(frame.signals["Counter"])] = rates  # type: ignore[assignment]
        elif frame.message == STEP.name and frame.signals["Tick"] > 0:
            stepped.setdefault(
                int(frame.signals["Tick"]), latest[int(frame.signals["CommandCounter"])]
            )
    log = read_run(captured_run.out).log
    logged = log.columns("command_theta1", "command_theta2", "command_d3")
    assert sorted(stepped) == list(range(1, len(logged) + 1))
    for tick, rates in stepped.items():  # StepSync n carries the command of control step n-1
        expected = on_the_wire_command(tuple(float(r) for r in logged[tick - 1]))  # type: ignore[arg-type]
        assert rates == pytest.approx(expected, abs=1e-12), tick


def test_the_recording_holds_the_frames_candump_saw_over_its_span(
    captured_run: CapturedRun,
) -> None:
    """The recorder on vcan0 missed nothing and added nothing: from its first frame to its
    last, the same frames as candump's, each with the same kernel receive time. (Frames of
    two senders that arrive together may reach two sockets in either order: each socket is
    fed by the CPU that sent the frame, so the order is not compared across senders.)"""
    with MCAPReader(captured_run.out / "run.mcap") as reader:
        recorded = list(reader)
    start, end = recorded[0].timestamp - 1e-5, recorded[-1].timestamp + 1e-5
    window = [f for f in captured_run.frames if start <= f.timestamp <= end]

    def by_frame(pairs: list[tuple[int, bytes, float]]) -> dict[tuple[int, bytes], list[float]]:
        times: dict[tuple[int, bytes], list[float]] = {}
        for frame_id, data, stamp in pairs:
            times.setdefault((frame_id, data), []).append(stamp)
        return times

    seen = by_frame([(f.frame_id, f.data, f.timestamp) for f in window])
    kept = by_frame([(m.arbitration_id, bytes(m.data), m.timestamp) for m in recorded])
    assert len(recorded) == len(window)
    assert seen.keys() == kept.keys()
    for key, stamps in seen.items():
        assert len(kept[key]) == len(stamps), key
        gaps = [abs(a - b) for a, b in zip(sorted(stamps), sorted(kept[key]), strict=True)]
        assert max(gaps) < 1e-5, (key, max(gaps))


def test_canplayer_replays_the_controller_side_into_a_plant_that_moves_as_in_the_run(
    captured_run: CapturedRun, processes: Processes, observer_on: Any, tmp_path: Path
) -> None:
    """canplayer replays at the capture's pace and never waits for the plant, which has no
    second chance at a frame: one StepSync lost and it never steps again (every later one
    names a tick it has not reached). So the plant must not lose a frame to a full receive
    queue while it is not scheduled (it asks for a large one in lockstep; the kernel's count
    of what it dropped, ``receive_drops``, is in its result), and the wait for its last
    answers lasts while it is still catching up."""
    replay = tmp_path / "controller_side.log"
    write_capture(replay, [f for f in captured_run.frames if f.frame_id in CONTROLLER_IDS])
    observer = observer_on(VCAN)
    plant = processes.start(
        "plant_sim.node", *node_args(VCAN, "lockstep", tmp_path / "replay"), name="plant"
    )
    heard = observer.wait_for(lambda m: m.arbitration_id == PLANT_STATUS.frame_id, HEARD)
    assert heard is not None, processes.outputs()
    span = captured_run.frames[-1].timestamp - captured_run.frames[0].timestamp
    played = subprocess.run(
        [can_util("canplayer"), "-I", str(replay)],
        capture_output=True, text=True, timeout=span + 40 * SLOWDOWN,
    )  # fmt: skip
    assert played.returncode == 0, played.stderr
    expected = trajectory(original_frames(captured_run))
    wait_while_growing(
        lambda: len(trajectory(observer.frames())),
        len(expected),
        5.0,
        "the plant's answers to the replayed frames",
    )
    assert plant.interrupt(30) == 0, plant.output()
    result = json.loads((tmp_path / "replay" / "plant_sim.json").read_text())
    received = {key: result[key] for key in ("e2e", "receive_drops", "stats")}
    assert result["receive_drops"] == 0, (
        f"the kernel dropped {result['receive_drops']} frames of the replay (None: it did not "
        f"say) for want of room in the plant's receive queue: canplayer does not wait for the "
        f"plant; {received}"
    )
    assert trajectory(observer.frames()) == expected, received
    assert len(expected) > len(read_run(captured_run.out).log.data) / 2


def original_frames(run: CapturedRun) -> list[can.Message]:
    """The frames candump captured during the run, as python-can messages."""
    return [
        can.Message(arbitration_id=f.frame_id, data=f.data, is_extended_id=False)
        for f in run.frames
    ]


def trajectory(frames: list[can.Message]) -> list[tuple[int, float, float]]:
    """The plant's joint states in a list of frames: (frame ID, position, velocity), each
    state once (an answer repeated for a retried step is the same state)."""
    states: list[tuple[int, float, float]] = []
    last: dict[int, tuple[int, float, float]] = {}
    for message in frames:
        if message.arbitration_id not in STATE_IDS:
            continue
        decoded = decode(message)
        assert decoded is not None, message
        state = (message.arbitration_id, decoded[2].Position, decoded[2].Velocity)
        if last.get(message.arbitration_id) != state:
            states.append(state)
            last[message.arbitration_id] = state
    return states


def test_bad_frames_from_cansend_are_counted_by_the_plant_and_none_is_acted_on(
    processes: Processes, observer_on: Any, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    observer = observer_on(VCAN)
    plant = processes.start("plant_sim.node", *node_args(VCAN, "lockstep", out), name="plant")
    assert observer.wait_for(lambda m: m.arbitration_id == PLANT_STATUS.frame_id, HEARD)
    controller = processes.start(
        "controller.cli", *node_args(VCAN, "lockstep", out), name="controller"
    )
    stepping = observer.wait_for(
        lambda m: m.arbitration_id == STEP.frame_id and step_tick(m) >= 100, 4 * HEARD
    )
    assert stepping is not None, processes.outputs()
    # The controller paused, its last command is the one the plant judges counters against.
    controller.signal(signal.SIGSTOP)
    try:
        # For its frames in flight to arrive; not stretched by SLOWDOWN: the injected frames
        # must follow its last command within RESYNC_AFTER, as a product bound (checked below).
        time.sleep(0.05)
        last = [m for m in observer.frames() if m.arbitration_id == COMMAND.frame_id][-1]
        decoded = decode(last)
        assert decoded is not None
        counter = decoded[1]
        wild = COMMAND.Record(Enable=1, Theta1Rate=1.0, Theta2Rate=-1.0, D3Rate=0.05)
        following = COMMAND.encode(wild, (counter + 1) % 16)
        flipped = bytearray(following)
        flipped[4] ^= 0x01
        injected = [
            ("repeated counter", COMMAND.frame_id, COMMAND.encode(wild, counter)),
            ("stale counter", COMMAND.frame_id, COMMAND.encode(wild, (counter - 2) % 16)),
            ("corrupt CRC", COMMAND.frame_id, bytes(flipped)),
            ("wrong DLC", COMMAND.frame_id, following[:-1]),
            ("unknown ID", FOREIGN_ID, following),
        ]
        cansend([(frame_id, data) for _, frame_id, data in injected])
        seen = wait_for_all(observer, [(frame_id, data) for _, frame_id, data in injected])
    finally:
        controller.signal(signal.SIGCONT)
    # Judged against the controller's last counter, not as a sender starting over.
    assert max(m.timestamp for m in seen[:2]) - last.timestamp < RESYNC_AFTER, (last, seen)
    result = finish_clean(processes, controller, plant, out)
    plant_e2e = result["plant"]["e2e"]
    assert (plant_e2e["repeated"], plant_e2e["stale"], plant_e2e["corrupt"]) == (1, 1, 2)
    assert plant_e2e["unknown"] == 1
    sent = sum(
        1 for m in observer.frames()
        if m.arbitration_id == COMMAND.frame_id
        and bytes(m.data) not in {data for _, _, data in injected}
    )  # fmt: skip
    assert result["plant"]["stats"]["commands_applied"] == sent
    assert_bit_identical(result, out, Mode.FUZZY)


def step_tick(message: can.Message) -> int:
    decoded = decode(message)
    return -1 if decoded is None else int(decoded[2].Tick)


def wait_for_all(observer: Observer, frames: list[tuple[int, bytes]]) -> list[can.Message]:
    """The observer's copies of ``frames`` (each is unique on the bus)."""
    found = []
    for frame_id, data in frames:
        message = observer.wait_for(
            lambda m, i=frame_id, d=data: (m.arbitration_id, bytes(m.data)) == (i, d), HEARD
        )
        assert message is not None, f"{frame_id:03X}#{data.hex()} never seen on the bus"
        found.append(message)
    return found


def test_a_flood_of_unrelated_frames_from_cangen_leaves_a_lockstep_run_unchanged(
    processes: Processes, tmp_path: Path
) -> None:
    cangen = can_util("cangen")
    out = tmp_path / "run"
    gap = f"{FLOOD_GAP_MS * SLOWDOWN:g}"
    # -i: a write the kernel refuses for want of buffer (ENOBUFS) is skipped, not the end of
    # the flood (cangen's own advice for load tests)
    standard = [cangen, "vcan0", "-i", "-g", gap, "-I", f"{FOREIGN_ID:X}", "-L", "8", "-D", "r"]
    extended = [cangen, "vcan0", "-i", "-g", gap, "-e"]
    with background(standard) as first, background(extended) as second:
        time.sleep(1.0)
        started = time.monotonic()
        code, result = launch(processes, VCAN, out, "lockstep")
        seconds = time.monotonic() - started
        for flood in (first, second):  # on from before the run to after it
            assert flood.poll() is None, flood.stderr.read() if flood.stderr else flood.args
    assert code == 0, f"{brief(result)}\n{processes.outputs()}"
    assert_bit_identical(result, out, Mode.FUZZY)
    unknown = result["plant"]["e2e"]["unknown"]
    assert unknown > seconds * 100, (unknown, seconds)  # the flood was on while it ran
    print(f"plant passed over {unknown} foreign frames in {seconds:.1f} s")
