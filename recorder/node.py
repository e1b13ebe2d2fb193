"""``scara-record``: every frame on the bus, and the robot's state decoded from them, to one
MCAP file per run; ``scara-record recover`` rewrites a file cut short.

One more participant on the bus that only listens. The bus reader never waits for the disk:
frames go through a bounded queue (:data:`QUEUE_FRAMES`) to a writer thread, and a full queue
drops the frame and counts it. The writer ends a chunk and hands it to the OS at most
:data:`~recorder.mcap_can.FLUSH_PERIOD` after the chunk's first message, so that a recorder
killed at any moment loses no more than that of its last frames. The file holds:

- the raw frames (``recorder/mcap_can.py``: one channel per DBC message, log time = the bus
  timestamp in ns, the raw data bytes as the message), corrupt ones included;
- the decoded state of the frames that pass the E2E checks, as the bridge publishes it
  (``scara/joints``, ``scara/tcp``, ``scara/coordination``, ``scara/status``,
  ``scara/events``, and ``scara/scenario`` each time a task comes into force on the bus:
  ``recorder/tasks.py``): JSON with the same JSON Schemas as the bridge's keys; in
  ``status`` the ``bridge`` part holds the recorder's own counts;
- the arm in 3D as Foxglove draws it (``bridge/scene.py``): ``foxglove.SceneUpdate`` on
  ``scara/scene`` and ``foxglove.FrameTransforms`` on ``scara/tf`` (protobuf, with Foxglove's
  schemas), drawn from the decoded joint state and the task in force (the scenario given,
  until one comes on the bus), at most 30 Hz;
- the recorder's counts (``recorder/counts``: frames received and dropped so far) at the end
  of each chunk, which ``scara-record recover`` reads back from a file cut short;
- metadata ``recording`` (software version, command line, start, frames written and
  dropped), and the DBC and the scenario (if given) as attachments.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import logging
import queue
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import can
from foxglove import Schema
from foxglove.messages import FrameTransforms, SceneUpdate
from mcap.writer import Writer

from bridge.scene import SCENE_TOPIC, STATE_TOPIC_PREFIX, TF_TOPIC, ArmScene, Joints
from bridge.view import VIEWED, RobotView
from controller.task_rules import load_task
from protocol.bus import add_bus_arguments, enlarge_receive_buffer, open_bus_from_args
from protocol.cli import add_verbosity, configure_logging, number, quiet_on_closed_pipe
from protocol.codec import DBC_TEXT, alive_counter
from protocol.e2e import E2EMonitor
from protocol.errors import ScaraError
from protocol.keys import schema
from protocol.messages import (
    CONTROLLER_ANSWER,
    STATE_IDS,
    JointStateParts,
)
from protocol.node import stop_on_signals
from protocol.realtime import yield_to_the_nodes
from protocol.scenario import Scenario, scenario_document, task_document
from recorder.mcap_can import (
    FLUSH_PERIOD,
    FrameChannels,
    RecorderCounts,
    RecordingError,
    counts_channel,
    end_chunk,
    finish,
    flush,
    open_writer,
)
from recorder.recover import recover
from recorder.tasks import TASK_IDS, TaskInForce
from sim.report import LOG_FILE

log = logging.getLogger("scara.recorder")

QUEUE_FRAMES = 200_000
"""Frames the writer may fall behind by (50 s of a 1 kHz run) before frames are dropped."""
DECODED = ("joints", "tcp", "coordination", "status", "events", "scenario")
JOINTS_PERIOD = 0.01
"""s between decoded joint-state samples (100 Hz, the bridge's default rate); the raw
frames keep every one."""
STATE_PREFIX = STATE_TOPIC_PREFIX
RUN_FILES = {
    "controller.json": "application/json",
    "plant_sim.json": "application/json",
    LOG_FILE: "application/x-npz",
}
"""What the nodes write of a run (results, the controller's log): attached with ``--run``."""
STATE_ENCODING = "json"
LISTENED = {codec.frame_id for codec in (*VIEWED, CONTROLLER_ANSWER)}


class SceneChannels:
    """The arm in 3D on one writer (:class:`~bridge.scene.ArmScene`'s messages, by the bus
    timestamps), as protobuf with Foxglove's schemas."""

    def __init__(self, writer: Writer, robot: Any, task: Scenario | None) -> None:
        self.writer = writer
        self.scene = ArmScene(robot, task)
        self._scene_id = _protobuf_channel(writer, SCENE_TOPIC, SceneUpdate.get_schema())
        self._transforms_id = _protobuf_channel(writer, TF_TOPIC, FrameTransforms.get_schema())

    def on_joints(self, position: Joints, received: float) -> None:
        """The messages due at a decoded joint state, logged at its bus timestamp."""
        due = self.scene.on_joints(position, received)
        stamp = int(received * 1e9)
        if due.transforms is not None:
            self.writer.add_message(self._transforms_id, stamp, due.transforms.encode(), stamp)
        if due.scene is not None:
            self.writer.add_message(self._scene_id, stamp, due.scene.encode(), stamp)

    def on_event(self, event: str) -> None:
        self.scene.on_event(event)

    def set_task(self, task: Scenario) -> None:
        self.scene.set_task(task)


def _protobuf_channel(writer: Writer, topic: str, schema: Schema) -> int:
    schema_id = writer.register_schema(schema.name, schema.encoding, schema.data)
    return writer.register_channel(topic, "protobuf", schema_id)


class StateChannels:
    """The decoded-state channels of one writer: JSON with the bridge's schemas, and the
    scene drawn from them."""

    def __init__(self, writer: Writer, robot: Any, task: Scenario | None = None) -> None:
        self.writer = writer
        self.view = RobotView(robot)
        self.scene = SceneChannels(writer, robot, task)
        self.tasks = TaskInForce(task or Scenario("recorder", (), None, robot=robot))
        self.monitor = E2EMonitor()
        self._parts = JointStateParts()
        self._seq = dict.fromkeys(DECODED, 0)
        self._next_joints = 0.0
        self._ids = {
            name: writer.register_channel(
                STATE_PREFIX + name,
                STATE_ENCODING,
                writer.register_schema(name, "jsonschema", json.dumps(schema(name)).encode()),
            )
            for name in DECODED
        }

    def feed(self, message: can.Message, counts: Callable[[], dict[str, Any]]) -> None:
        """Decode ``message`` (if it is valid) and write what it changes."""
        if message.arbitration_id in STATE_IDS and not self._joints_due(message):
            return
        if message.arbitration_id in TASK_IDS:
            self._in_force(self.tasks.on_transfer_frame(message), message.timestamp)
            return
        accepted = self.monitor.accept(message, LISTENED)
        if accepted is None:
            return
        codec, counter, record = accepted
        received = message.timestamp
        if codec is CONTROLLER_ANSWER:
            self._in_force(self.tasks.on_answer(record), received)
            return
        if codec.frame_id in STATE_IDS:
            complete = self._parts.add(STATE_IDS.index(codec.frame_id), counter, record)
            if complete is not None:
                self._next_joints = max(self._next_joints + JOINTS_PERIOD, received)
                self.view.on_joint_state(complete[0], complete[1], received)
                self._write("joints", self.view.joints_payload(), received)
                self._write("tcp", self.view.tcp_payload(), received)
                self.scene.on_joints(complete[0], received)
            return
        for name, detail in self.view.on_frame(codec, record, received):
            self.scene.on_event(name)
            self._write("events", {"t": received, "event": name, "detail": detail}, received)
        if codec.name == "ControllerCoordination":
            self._write("coordination", self.view.coordination_payload(), received)
        elif codec.name in ("ControllerStatus", "PlantStatus"):
            self._write("status", self.view.status_payload(received, counts()), received)

    def _in_force(self, task: Scenario | None, received: float) -> None:
        """A task came into force: drawn from now on, and written as the bridge says it."""
        if task is not None:
            self.scene.set_task(task)
            self._write("scenario", task_document(task), received)

    def _joints_due(self, message: can.Message) -> bool:
        """A joint-state frame is decoded only when a sample is due (:data:`JOINTS_PERIOD`);
        the others only keep its alive counter followed (the raw frames have them all)."""
        if message.timestamp >= self._next_joints:
            return True
        if len(message.data) > 1 and not (message.is_error_frame or message.is_remote_frame):
            self.monitor.check(
                message.arbitration_id, alive_counter(message.data), message.timestamp
            )
        return False

    def _write(self, name: str, payload: dict[str, Any] | None, received: float) -> None:
        if payload is None:
            return
        numbered = payload if name == "scenario" else payload | {"seq": self._seq[name]}
        data = json.dumps(numbered).encode()
        stamp = int(received * 1e9)
        self.writer.add_message(self._ids[name], stamp, data, stamp, self._seq[name])
        self._seq[name] += 1


class Recorder:
    """Bus reader (the caller's thread, :meth:`run`) and file writer (a thread of its own)."""

    def __init__(
        self,
        bus: can.BusABC,
        path: Path,
        robot: Any,
        command_line: Sequence[str],
        task: Scenario | None = None,
    ) -> None:
        self.bus = bus
        self.path = path
        self.running = True
        self.dropped = 0
        self.received = 0
        self._queue: queue.Queue[can.Message | None] = queue.Queue(QUEUE_FRAMES)
        self._stream = path.open("wb")
        self._writer = open_writer(self._stream)
        self._frames = FrameChannels(self._writer)
        self._state = StateChannels(self._writer, robot, task)
        self._counts = counts_channel(self._writer)
        flush(self._writer)  # the header on disk: killed before its first chunk, still MCAP
        self._started = time.time()
        self._command_line = list(command_line)
        self._thread = threading.Thread(target=self._write_loop, name="mcap-writer")
        self._thread.start()

    def run(self, duration: float | None = None) -> None:
        """Read the bus until stopped (or for ``duration`` s)."""
        end = None if duration is None else time.monotonic() + duration
        while self.running and (end is None or time.monotonic() < end):
            message = self.bus.recv(0.1)
            if message is None:
                continue
            self.received += 1
            try:
                self._queue.put_nowait(message)
            except queue.Full:
                self.dropped += 1

    def counts(self) -> dict[str, Any]:
        """The recorder's counts, in the place of the bridge's in ``status``."""
        return {
            "frames": self._frames.written,
            "bad_frames": self._state.monitor.counts.bad,
            "published": {},
            "dropped": {"frames": self.dropped},
            "rates_hz": {},
        }

    def _write_loop(self) -> None:
        """Write what the reader queues; end the chunk and flush it once its first message is
        :data:`FLUSH_PERIOD` old, whether frames keep coming or stop."""
        flush_at: float | None = None
        while True:
            try:
                wait = None if flush_at is None else max(0.0, flush_at - time.monotonic())
                message = self._queue.get(timeout=wait)
            except queue.Empty:  # the chunk is due and nothing more came
                self._flush()
                flush_at = None
                continue
            if message is None:
                return
            self._frames.write(message)
            self._state.feed(message, self.counts)
            if flush_at is None:
                flush_at = time.monotonic() + FLUSH_PERIOD
            elif time.monotonic() >= flush_at:
                self._flush()
                flush_at = None

    def _flush(self) -> None:
        """End the chunk with the counts so far, and hand it to the OS."""
        end_chunk(
            self._writer, self._counts, RecorderCounts(self.received, self.dropped), time.time_ns()
        )

    def stop(self) -> None:
        """End :meth:`run` (from a signal handler)."""
        self.running = False

    def close(
        self, scenario: Scenario | None, scenario_file: Path | None, run: Path | None = None
    ) -> None:
        """Write what is queued, the metadata and attachments (and the results and log of
        the run in ``run``, if there are), and the index; close."""
        self._queue.put(None)
        self._thread.join()
        self._flush()
        writer = self._writer
        now = time.time_ns()
        writer.add_attachment(now, now, "scara.dbc", "text/plain", DBC_TEXT.encode())
        if scenario is not None:
            document = json.dumps(scenario_document(scenario)).encode()
            writer.add_attachment(now, now, "scenario.json", "application/json", document)
        if scenario_file is not None and scenario_file.is_file():
            writer.add_attachment(
                now, now, scenario_file.name, "application/toml", scenario_file.read_bytes()
            )
        for name, media_type in RUN_FILES.items():
            path = None if run is None else run / name
            if path is not None and path.is_file():
                writer.add_attachment(now, now, name, media_type, path.read_bytes())
        writer.add_metadata(
            "recording",
            {
                "software": f"scara-fuzzy {importlib.metadata.version('scara-fuzzy')}",
                "command_line": json.dumps(self._command_line),
                "started": f"{self._started:.6f}",
                "frames_received": str(self.received),
                "frames_written": str(self._frames.written),
                "frames_dropped": str(self.dropped),
            },
        )
        finish(writer)
        self._stream.close()


# --- the command ---------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-record",
        description="Record every CAN frame, and the robot's state decoded from them, to one "
        "MCAP file. 'scara-record recover FILE' rewrites a file cut short (kill -9) as a "
        "valid, indexed MCAP.",
    )
    parser.add_argument(
        "--out", type=Path, default=Path("out/run/run.mcap"), help="file (default %(default)s)"
    )
    parser.add_argument(
        "--scenario",
        help="scenario file or name of the run: its robot decodes the state, and it is "
        "attached to the file",
    )
    parser.add_argument(
        "--duration", type=number(0.0, low_open=True), metavar="S", help="stop after S s"
    )
    parser.add_argument(
        "--run",
        type=Path,
        metavar="DIR",
        help="the nodes' --out folder: at the end, attach the run's results and log",
    )
    add_bus_arguments(parser)
    add_verbosity(parser)
    return parser


def build_recover_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-record recover",
        description="Rewrite an MCAP file cut short (its writer killed) as a valid, indexed "
        "MCAP with every complete chunk, and report what it kept and what it could not: the "
        "cut bytes, and the frames the recorder had counted that are not in the file.",
    )
    parser.add_argument("file", type=Path, help="the damaged recording")
    parser.add_argument(
        "--out", type=Path, help="where to write (default: FILE with .recovered.mcap)"
    )
    add_verbosity(parser)
    return parser


def main_recover(argv: Sequence[str]) -> int:
    args = build_recover_parser().parse_args(argv)
    configure_logging(args.verbose)
    out = args.out or args.file.with_suffix(".recovered.mcap")
    try:
        report = recover(args.file, out)
    except RecordingError as error:
        print(f"scara-record recover: {error}", file=sys.stderr)
        return 2
    except OSError as error:
        print(f"scara-record recover: {out}: {error.strerror}", file=sys.stderr)
        return 2
    print(report.summary(out))
    return 0


@quiet_on_closed_pipe
def main(argv: Sequence[str] | None = None) -> int:
    arguments = list(sys.argv[1:] if argv is None else argv)
    if arguments[:1] == ["recover"]:
        return main_recover(arguments[1:])
    args = build_parser().parse_args(arguments)
    configure_logging(args.verbose)
    yield_to_the_nodes()
    try:
        scenario = load_task(args.scenario) if args.scenario else None
        bus = open_bus_from_args(args)
        enlarge_receive_buffer(bus)
    except (ScaraError, can.CanError, ValueError, OSError) as error:
        print(f"scara-record: {error}", file=sys.stderr)
        return 2
    robot = (scenario or Scenario("recorder", (), None)).robot
    try:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        recorder = Recorder(bus, args.out, robot, ["scara-record", *arguments], scenario)
    except OSError as error:
        bus.shutdown()
        print(f"scara-record: {args.out}: {error.strerror}", file=sys.stderr)
        return 2

    stop_on_signals(recorder.stop)
    print(f"scara-record: recording to {args.out} (Ctrl-C to stop)", file=sys.stderr, flush=True)
    try:
        recorder.run(args.duration)
    finally:
        scenario_file = Path(args.scenario) if args.scenario else None
        recorder.close(scenario, scenario_file, args.run)
        bus.shutdown()
    print(
        f"scara-record: {recorder.received} frames, {recorder.dropped} dropped, in {args.out}",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
