"""``scara-record``, ``scara-replay`` and python-can's own logger and player on ``.mcap``,
with real processes on CAN-over-Zenoh through a router on 127.0.0.1, and the files read
back with the ``mcap`` library."""

from __future__ import annotations

import itertools
import json
import math
import shutil
import signal
import statistics
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import can
import jsonschema
import pytest
from mcap.reader import make_reader
from support import (
    ROOT,
    SLOWDOWN,
    Observer,
    Processes,
    Transport,
    quill_in_world,
    read_foxglove,
    wait_until,
)

from bridge.scene import SCENE_TOPIC, TF_PERIOD, TF_TOPIC, TRAIL_STEP
from bridge.session import ZenohEndpoint
from protocol.keys import DEFAULT_ROBOT, schema
from protocol.kinematics import forward
from protocol.messages import STATE
from protocol.scenario import load_scenario
from protocol.zenoh_can import ZenohBus
from recorder.mcap_can import COUNTS_SCHEMA, COUNTS_TOPIC, finish, open_writer
from sim.report import read_run
from sim.simulation import simulate

pytestmark = pytest.mark.timeout(180)


@pytest.fixture
def transport(router: int) -> Transport:
    """CAN over Zenoh through the test's router (python-can's tools are given its port)."""
    return Transport("zenoh", f"rec{router}", {"port": router})


def by_id(messages: list[can.Message]) -> dict[int, list[bytes]]:
    """Each frame ID's data, in the order received: each sender's frames keep their order."""
    found: dict[int, list[bytes]] = defaultdict(list)
    for message in messages:
        found[message.arbitration_id].append(bytes(message.data))
    return dict(found)


def mcap_contents(
    path: Path,
) -> tuple[list[can.Message], dict[str, list[Any]], dict[str, list[tuple[int, Any]]], Any]:
    """The frames, the decoded JSON channels, the Foxglove protobuf channels (log time and
    message, read with their own schemas and Foxglove's published ones) and the reader's
    summary, with mcap's own reader."""
    frames: list[can.Message] = []
    decoded: dict[str, list[Any]] = defaultdict(list)
    foxglove: dict[str, list[tuple[int, Any]]] = defaultdict(list)
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            if channel.message_encoding == "protobuf":
                assert schema is not None and schema.encoding == "protobuf", channel.topic
                read = read_foxglove(schema.name, schema.data, message.data)
                foxglove[channel.topic].append((message.log_time, read))
            elif channel.message_encoding == "can-frame":
                frames.append(
                    can.Message(
                        timestamp=message.log_time / 1e9,
                        arbitration_id=int(channel.metadata["arbitration_id"]),
                        data=message.data,
                    )
                )
            else:
                decoded[channel.topic].append(json.loads(message.data))
        attachments = {a.name: a.data for a in reader.iter_attachments()}
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    return frames, dict(decoded), dict(foxglove), (summary, attachments, metadata)


def check_scene(foxglove: dict[str, list[tuple[int, Any]]], joints: list[dict[str, Any]]) -> None:
    """The reference run in 3D: transforms at 30 Hz that put the quill where the recorded
    joints put the tool; scenes with the scenario's obstacle and waypoints and the path the
    tool travelled, ending near the last waypoint."""
    scenario = load_scenario("reference")
    transforms, scenes = foxglove[TF_TOPIC], foxglove[SCENE_TOPIC]
    span = (transforms[-1][0] - transforms[0][0]) / 1e9
    # 30 Hz at most (fewer where the decoded joint states paused: lockstep, a loaded machine)
    assert 50 < len(transforms) <= span / TF_PERIOD + 1
    by_time = {int(sample["t"] * 1e9): sample["position"] for sample in joints}  # as logged
    for log_time, message in transforms:
        position = by_time[log_time]  # a transform is drawn from a recorded joint state
        assert quill_in_world(message) == pytest.approx(forward(scenario.robot, *position))
    entities = {entity.id: entity for entity in scenes[-1][1].entities}
    real = entities["obstacle"].cylinders[0]
    assert scenario.obstacle is not None
    assert (real.pose.position.x, real.pose.position.y) == (
        scenario.obstacle.x,
        scenario.obstacle.y,
    )
    assert len(entities["waypoints"].spheres) == len(scenario.waypoints)
    travelled = entities["travelled"].lines[0].points
    last = scenario.waypoints[-1]
    assert len(travelled) > 50
    end = (travelled[-1].x, travelled[-1].y, travelled[-1].z)
    # a point every TRAIL_STEP of the tool's, and the arm settles within 1 mm of the waypoint
    assert math.dist(end, (last.x, last.y, last.z)) < TRAIL_STEP + 0.002


def launch(
    transport: Transport, out: Path, clock: str, *extra: str
) -> subprocess.CompletedProcess[str]:
    command = [
        sys.executable, "-m", "sim.launch", "reference", "--clock", clock, "--out", str(out),
        *transport.cli(), *extra,
    ]  # fmt: skip
    return subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=150 * SLOWDOWN)


@pytest.mark.parametrize("clock", ["lockstep", "realtime"])
def test_a_run_is_recorded_whole_frames_state_results_and_log(
    transport: Transport, observer_on: Any, tmp_path: Path, clock: str
) -> None:
    observer: Observer = observer_on(transport)
    out = tmp_path / "run"
    done = launch(transport, out, clock)
    assert done.returncode == 0, done.stderr
    frames, decoded, foxglove, (summary, attachments, metadata) = mcap_contents(out / "run.mcap")
    wait_until(
        lambda: len(observer.frames()) >= len(frames), 5.0, "the listener to hear what was recorded"
    )
    seen = observer.frames()

    # every frame on the bus while the nodes ran, each sender's in order, times in order
    assert by_id(frames) == by_id(seen)
    assert all(a.timestamp <= b.timestamp for a, b in itertools.pairwise(frames))
    recording = metadata["recording"]
    assert int(recording["frames_dropped"]) == 0
    assert int(recording["frames_written"]) == len(frames)
    assert summary.chunk_indexes and summary.statistics.message_count == len(frames) + sum(
        len(samples) for samples in (*decoded.values(), *foxglove.values())
    )
    check_scene(foxglove, decoded["scara/joints"])

    # the decoded state fits the bridge's schemas, the recorder's counts theirs; the run's
    # events are there in order
    for topic, samples in decoded.items():
        validator = jsonschema.Draft202012Validator(
            COUNTS_SCHEMA if topic == COUNTS_TOPIC else schema(topic.removeprefix("scara/"))
        )
        for sample in samples:
            validator.validate(sample)
    events = [e["event"] for e in decoded["scara/events"]]
    assert events[0] == "run_started" and events[-1] == "run_finished", events
    assert [e["detail"]["index"] for e in decoded["scara/events"] if "index" in e["detail"]] == [
        0, 1, 2, 3,
    ]  # fmt: skip

    # one run, one file: the results and the log; the measures from it equal the live ones
    for name in ("controller.json", "plant_sim.json", "controller_log.npz", "scara.dbc"):
        assert name in attachments, name
    assert attachments["controller.json"] == (out / "controller.json").read_bytes()
    unpacked = tmp_path / "from_mcap"
    unpacked.mkdir()
    for name in ("controller.json", "plant_sim.json", "controller_log.npz"):
        (unpacked / name).write_bytes(attachments[name])
    assert not (out / "controller_log.npz").exists()  # the recording holds the run's log
    from_file = read_run(unpacked)
    assert from_file.measures == read_run(out).measures
    if clock == "lockstep":  # lockstep is exact: the recorded log is the simulation's
        simulated = simulate(load_scenario("reference"))
        assert from_file.log.data.tobytes() == simulated.log.data.tobytes()
        assert from_file.measures == simulated.measures
    assert json.loads(recording["command_line"])[0] == "scara-record"

    # scara-plot prints what scara-run printed live, and draws the figure
    plot = subprocess.run(
        [sys.executable, "-m", "recorder.plot", str(out / "run.mcap")],
        cwd=ROOT, capture_output=True, text=True, timeout=120 * SLOWDOWN,
    )  # fmt: skip
    assert plot.returncode == 0, plot.stderr
    assert plot.stdout.startswith(done.stdout.strip()), (plot.stdout, done.stdout)
    assert (out / "run.png").stat().st_size > 10_000

    # regression replay: the same law gives the same commands; a changed gain does not
    regression = [sys.executable, "-m", "recorder.replay", str(out / "run.mcap"), "--regress"]
    same = subprocess.run(
        regression, cwd=ROOT, capture_output=True, text=True, timeout=120 * SLOWDOWN
    )
    if clock == "realtime":
        assert same.returncode == 2 and "--clock lockstep" in same.stderr, same.stderr
        return
    assert same.returncode == 0, same.stdout + same.stderr
    ticks = json.loads(attachments["controller.json"])["loop"]["ticks"]
    assert same.stdout.startswith(f"{ticks} of {ticks} commands identical"), same.stdout
    changed = tmp_path / "changed_gain.toml"
    changed.write_text(
        (ROOT / "scenarios" / "reference.toml").read_text()
        + "\n[controller]\nheading_gain = 16.0\n"
    )
    differs = subprocess.run(
        [*regression, "--scenario", str(changed)],
        cwd=ROOT, capture_output=True, text=True, timeout=120 * SLOWDOWN,
    )  # fmt: skip
    assert differs.returncode == 1, differs.stdout + differs.stderr
    assert "first divergence: tick " in differs.stdout and "JointVelocityCommand." in differs.stdout


def test_a_recorder_killed_mid_run_is_recovered_and_reports_the_loss(
    transport: Transport, observer_on: Any, processes: Processes, tmp_path: Path
) -> None:
    observer: Observer = observer_on(transport)
    file = tmp_path / "killed.mcap"
    recorder = processes.start("recorder.node", "--out", str(file), *transport.cli())
    wait_until(lambda: "recording to" in recorder.output(), 30.0, "the recorder to start")
    plant = processes.start("plant_sim.node", "endurance", *transport.cli(), name="plant")
    controller = processes.start(
        "controller.cli", "endurance", *transport.cli(), "--max-wall-time", "60", name="c"
    )
    wait_until(lambda: file.stat().st_size > 600_000, 60.0, "a few chunks on disk")
    recorder.signal(signal.SIGKILL)
    recorder.wait(5.0)
    controller.interrupt()
    plant.interrupt()

    done = subprocess.run(
        [sys.executable, "-m", "recorder.node", "recover", str(file)],
        cwd=ROOT, capture_output=True, text=True, timeout=60 * SLOWDOWN,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "was cut short" in done.stdout and "cannot be counted" in done.stdout, done.stdout
    frames, _, _, (summary, _, _) = mcap_contents(file.with_suffix(".recovered.mcap"))
    assert summary.chunk_indexes and len(frames) > 1000
    seen = by_id(observer.frames())
    for frame_id, data in by_id(frames).items():  # what was kept is the start of each stream
        assert seen[frame_id][: len(data)] == data, hex(frame_id)


def test_python_can_logger_and_player_use_mcap(
    transport: Transport, observer_on: Any, processes: Processes, tmp_path: Path
) -> None:
    file = tmp_path / "x.mcap"
    bus_kwargs = ["--bus-kwargs", f"port={transport.options['port']}"]
    where = ["-i", "zenoh", "-c", transport.channel, *bus_kwargs, "--"]
    logger = processes.start("can.logger", *where[:-1], "-f", str(file), name="logger")
    bus = transport.open_bus()
    assert isinstance(bus, ZenohBus)
    source = Observer(bus)
    # python-can's logger prints nothing when it is ready; its bus's subscription shows
    wait_until(lambda: bus.has_receivers, 30.0, "can.logger's bus to subscribe")
    sent = []
    for index in range(300):
        sent.append(index.to_bytes(2, "little"))
        source.send(0x123, sent[-1])
        time.sleep(0.005)
    source.close()  # its flush: the logger's bus has taken every frame
    time.sleep(0.5 * SLOWDOWN)  # for the logger to write them: it drops what is left on SIGINT
    assert logger.interrupt() in (0, 1, -2), logger.output()  # python-can exits 1 on SIGINT
    with can.LogReader(file) as reader:
        logged = [m for m in reader if m.arbitration_id == 0x123]
    assert [bytes(m.data) for m in logged] == sent

    observer: Observer = observer_on(transport)
    player = subprocess.run(
        [sys.executable, "-m", "can.player", *where, str(file)],
        cwd=ROOT, capture_output=True, text=True, timeout=60 * SLOWDOWN,
    )  # fmt: skip
    assert player.returncode == 0, player.stderr

    def played_frames() -> list[can.Message]:
        return [m for m in observer.frames() if m.arbitration_id == 0x123]

    wait_until(lambda: len(played_frames()) >= len(sent), 5.0, "the played frames")
    played = played_frames()
    assert [bytes(m.data) for m in played] == sent
    recorded_gaps = [b.timestamp - a.timestamp for a, b in itertools.pairwise(logged)]
    played_gaps = [b.timestamp - a.timestamp for a, b in itertools.pairwise(played)]
    # the recorded spacing (about 5 ms): python-can's player sleeps per frame, so compare
    # the typical gap and the whole span, not each gap on a shared machine (nor more exactly
    # than the machine keeps time)
    slack = statistics.median(played_gaps) - statistics.median(recorded_gaps)
    assert abs(slack) < 1e-3 * SLOWDOWN
    assert abs(sum(played_gaps) - sum(recorded_gaps)) < 0.25 * SLOWDOWN * sum(recorded_gaps)


def test_scara_replay_sends_a_recording_at_its_pace_faster_or_in_part(
    transport: Transport, observer_on: Any, tmp_path: Path
) -> None:
    file = tmp_path / "source.mcap"
    start = 1_800_000_000.0
    frames = [
        can.Message(
            timestamp=start + 0.004 * i,
            arbitration_id=0x110 + i % 3,
            data=bytes([i % 256]) * 7,
            is_extended_id=False,
        )
        for i in range(500)
    ]  # 2 s
    with can.Logger(file) as writer:
        for frame in frames:
            writer.on_message_received(frame)
    observer: Observer = observer_on(transport)

    def replay(expected: int, *extra: str) -> tuple[list[can.Message], float]:
        """The frames heard from a replay once ``expected`` have come, and their span."""
        before = time.time()
        done = subprocess.run(
            [sys.executable, "-m", "recorder.replay", str(file), *transport.cli(), *extra],
            cwd=ROOT, capture_output=True, text=True, timeout=60 * SLOWDOWN,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr

        def heard() -> list[can.Message]:
            return [m for m in observer.frames() if m.timestamp >= before]

        wait_until(lambda: len(heard()) >= expected, 5.0, "the replayed frames")
        got = heard()
        return got, got[-1].timestamp - got[0].timestamp

    late = 0.4 * SLOWDOWN  # the most a loaded machine may add to a replay's span
    paced, span = replay(len(frames))
    assert by_id(paced) == by_id(frames)
    assert 1.9 < span < 2.0 + late, span
    fast, fast_span = replay(len(frames), "--rate", "4")
    assert by_id(fast) == by_id(frames) and 0.45 < fast_span < 0.5 + late, fast_span
    wanted = [bytes(f.data) for f in frames[250:] if f.arbitration_id == 0x110]
    part, _ = replay(
        len(wanted), "--as-fast-as-possible", "--only", "JointState1", "--start-offset", "1"
    )
    assert by_id(part) == {0x110: wanted}


@pytest.mark.parametrize(
    ("content", "named"),
    [
        (None, "no such file"),
        (b"", "empty"),
        (b"not a recording at all", "not an MCAP file"),
        (b"\x89MCAP0\r\n" + bytes(40), "scara-record recover"),
    ],
)
def test_bad_recordings_exit_2_with_a_message(
    tmp_path: Path, content: bytes | None, named: str
) -> None:
    file = tmp_path / "bad.mcap"
    if content is not None:
        file.write_bytes(content)
    for command, expected in (
        (["recorder.replay", str(file), "--interface", "virtual"], named),
        (["recorder.node", "recover", str(file)], "scara-record recover: "),
    ):
        done = subprocess.run(
            [sys.executable, "-m", *command],
            cwd=ROOT, capture_output=True, text=True, timeout=60 * SLOWDOWN,
        )  # fmt: skip
        assert done.returncode == 2, (command, done.stdout, done.stderr)
        assert "Traceback" not in done.stderr
        assert expected.lower() in done.stderr.lower(), done.stderr


def test_a_recording_replayed_into_a_bridge_shows_on_zenoh(
    transport: Transport, processes: Processes, tmp_path: Path
) -> None:
    """No plant, no controller: the bridge publishes the recorded joint states."""
    file = tmp_path / "joints.mcap"
    positions = [(0.1 + 0.001 * tick, 1.2, 0.15) for tick in range(400)]  # 2 s at 200 Hz
    with can.Logger(file) as writer:
        for tick, position in enumerate(positions):
            for joint, codec in enumerate(STATE):
                record = codec.Record(CommandEcho=tick % 16, Position=position[joint], Velocity=0.0)
                data = codec.encode(record, tick % 16)
                stamp = 1_800_000_000.0 + tick * 0.005
                writer.on_message_received(
                    can.Message(
                        timestamp=stamp,
                        arbitration_id=codec.frame_id,
                        data=data,
                        is_extended_id=False,
                    )
                )
    port = transport.options["port"]
    processes.start("bridge.node", "--zenoh-port", str(port), *transport.cli(), name="bridge")
    session = ZenohEndpoint("127.0.0.1", port).open()
    seen: list[list[float]] = []
    subscriber = session.declare_subscriber(
        f"scara/{DEFAULT_ROBOT}/joints",
        lambda sample: seen.append(json.loads(sample.payload.to_bytes())["position"]),
    )
    wait_until(
        lambda: bool(list(session.liveliness().get(f"scara/{DEFAULT_ROBOT}/alive/bridge"))),
        30.0,
        "the bridge",
    )
    done = subprocess.run(
        [sys.executable, "-m", "recorder.replay", str(file), *transport.cli()],
        cwd=ROOT, capture_output=True, text=True, timeout=60 * SLOWDOWN,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    last = round(positions[-1][0], 6)
    wait_until(lambda: bool(seen) and round(seen[-1][0], 6) == last, 5.0, "the last state")
    subscriber.undeclare()
    session.close()  # type: ignore[no-untyped-call]
    # the bridge's 100 Hz of a 200 Hz recording (fewer where the machine is slower)
    assert 150 / SLOWDOWN <= len(seen) <= 201, processes.outputs()
    theta1 = [round(position[0], 6) for position in seen]
    assert theta1 == sorted(theta1) and theta1[-1] == round(positions[-1][0], 6)
    assert set(theta1) <= {round(p[0], 6) for p in positions}


def test_the_decoded_state_of_a_recording_replays_onto_the_zenoh_keys(
    router: int, tmp_path: Path
) -> None:
    file = tmp_path / "state.mcap"
    payloads = [
        {"t": 1_800_000_000.0 + 0.01 * i, "seq": i, "x": 0.3, "y": 0.001 * i, "z": 0.2}
        for i in range(200)
    ]
    with file.open("wb") as stream:
        writer = open_writer(stream)
        schema_id = writer.register_schema("tcp", "jsonschema", json.dumps(schema("tcp")).encode())
        channel = writer.register_channel("scara/tcp", "json", schema_id)
        for payload in payloads:
            stamp = round(payload["t"] * 1e9)
            writer.add_message(channel, stamp, json.dumps(payload).encode(), stamp)
        finish(writer)
    session = ZenohEndpoint("127.0.0.1", router).open()
    seen: list[dict[str, Any]] = []
    subscriber = session.declare_subscriber(
        f"scara/{DEFAULT_ROBOT}/tcp",
        lambda sample: seen.append(json.loads(sample.payload.to_bytes())),
    )
    time.sleep(0.3 * SLOWDOWN)  # for the subscription to reach the router
    done = subprocess.run(
        [sys.executable, "-m", "recorder.replay", str(file), "--to", "zenoh",
         "--zenoh-port", str(router), "--rate", "2"],
        cwd=ROOT, capture_output=True, text=True, timeout=60 * SLOWDOWN,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    wait_until(lambda: len(seen) >= len(payloads), 5.0, "the replayed samples")
    subscriber.undeclare()
    session.close()  # type: ignore[no-untyped-call]
    assert seen == payloads


@pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux is not installed")
def test_the_space_bar_pauses_and_resumes_a_replay_in_a_terminal(
    transport: Transport, observer_on: Any, tmp_path: Path
) -> None:
    file = tmp_path / "slow.mcap"
    with can.Logger(file) as writer:
        for index in range(400):  # 4 s
            writer.on_message_received(
                can.Message(
                    timestamp=1_800_000_000.0 + 0.01 * index,
                    arbitration_id=0x123,
                    data=index.to_bytes(2, "little"),
                    is_extended_id=False,
                )
            )
    observer: Observer = observer_on(transport)
    session = f"replay-{transport.options['port']}"
    command = " ".join(
        [sys.executable, "-m", "recorder.replay", str(file), *transport.cli(), "; sleep 30"]
    )
    subprocess.run(
        ["tmux", "new-session", "-d", "-s", session, "-x", "120", "-y", "30", command],
        check=True, cwd=ROOT,
    )  # fmt: skip
    try:
        wait_until(lambda: len(observer.frames()) >= 50, 30.0, "the replay to start")
        subprocess.run(["tmux", "send-keys", "-t", session, " "], check=True)
        time.sleep(0.5 * SLOWDOWN)  # the key reaches it
        paused = len(observer.frames())
        time.sleep(1.5)
        assert len(observer.frames()) == paused, "frames went on while paused"
        subprocess.run(["tmux", "send-keys", "-t", session, " "], check=True)
        wait_until(lambda: len(observer.frames()) == 400, 30.0, "the rest of the replay")
    finally:
        subprocess.run(["tmux", "kill-session", "-t", session], capture_output=True)
    assert paused < 400
    received = [int.from_bytes(m.data, "little") for m in observer.frames()]
    assert received == list(range(400))
