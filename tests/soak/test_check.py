"""The soak's invariants (``soak/check.py``) on hand-made frame sequences: each fires where it
must and stays silent on a clean sequence; and a recording cut short counts only once
recovered."""

from __future__ import annotations

from pathlib import Path

import can

from protocol.config import RobotConfig
from protocol.isotp_link import seal
from protocol.kinematics import inverse
from protocol.messages import (
    COMMAND,
    CONTROLLER_STATUS,
    NODE_COMMAND,
    PLANT_STATUS,
    STATE,
    STOP,
    WORLD_UPLOAD,
    NodeId,
    NodeState,
    PlantFlag,
    Request,
)
from protocol.scenario import load_scenario
from protocol.world import World
from recorder.mcap_can import MCAPWriter
from recorder.recover import recover
from soak.check import (
    BACKLOG,
    ORDER_SKEW,
    RECOVERY_BOUND,
    Worlds,
    bad_frames_acted,
    collisions,
    decode,
    estop_latches,
    fault_latches,
    inside_obstacle,
    outages,
    readable,
    stale_commands,
)

REFERENCE = load_scenario("reference")
HOME = inverse(RobotConfig(), 0.30, -0.25, 0.25)
INSIDE = inverse(RobotConfig(), 0.455, -0.01, 0.25)  # the reference obstacle's axis


class Bus:
    """A hand-made recording: frames with their counters and times."""

    def __init__(self) -> None:
        self.t = 1000.0
        self.frames: list[can.Message] = []
        self.counters: dict[int, int] = {}

    def send(self, frame_id: int, data: bytes, dt: float = 0.002) -> None:
        self.t += dt
        self.frames.append(
            can.Message(timestamp=self.t, arbitration_id=frame_id, data=data, is_extended_id=False)
        )

    def next(self, codec: object, counter: int | None = None) -> int:
        frame_id = codec.frame_id  # type: ignore[attr-defined]
        if counter is None:
            counter = (self.counters.get(frame_id, -1) + 1) % 16
        self.counters[frame_id] = counter
        return counter

    def state(self, echo: int, joints: tuple[float, float, float] = HOME) -> None:
        counter = self.next(STATE[0])
        for codec, position in zip(STATE, joints, strict=True):
            record = codec.Record(CommandEcho=echo, Position=position, Velocity=0.0)
            self.send(codec.frame_id, codec.encode(record, counter), 0.0)
        self.t += 0.001

    def command(self, enable: bool = True, counter: int | None = None) -> int:
        counter = self.next(COMMAND, counter)
        record = COMMAND.Record(Enable=int(enable), Theta1Rate=0.1, Theta2Rate=0.0, D3Rate=0.0)
        self.send(COMMAND.frame_id, COMMAND.encode(record, counter))
        return counter

    def tick(self) -> None:
        """One control tick: a command, and the plant's answer echoing it."""
        self.state(self.command())

    def status(self, node: str, state: str, dt: float = 0.1, **fields: int) -> None:
        codec = CONTROLLER_STATUS if node == "controller" else PLANT_STATUS
        values = dict.fromkeys(codec.signal_names, 0) | fields
        values["State"] = NodeState[state.upper()]
        self.send(codec.frame_id, codec.encode(codec.Record(**values), self.next(codec)), dt)

    def both(self, controller: str, plant: str, dt: float = 0.1) -> None:
        self.status("controller", controller, dt)
        self.status("plant", plant, 0.0)

    def node_command(self, request: object, target: object = None) -> None:
        record = NODE_COMMAND.Record(
            Command=request, Target=target or NodeId.ALL, Source=NodeId.OPERATOR, Ticket=0
        )
        self.send(NODE_COMMAND.frame_id, NODE_COMMAND.encode(record, self.next(NODE_COMMAND)))

    def estop(self) -> None:
        record = STOP.Record(Source=NodeId.OPERATOR)
        self.send(STOP.frame_id, STOP.encode(record, self.next(STOP)))

    def seen(self) -> list:  # type: ignore[type-arg]
        return decode(self.frames)


def test_a_command_enabled_more_than_three_ticks_after_the_last_state_is_caught() -> None:
    bus = Bus()
    for _ in range(5):
        bus.tick()
    bus.t += ORDER_SKEW  # (commands recorded sooner may have left before the state arrived)
    for _ in range(3):
        bus.command()  # the plant's answers lost: three ticks on the last state is allowed
    held = bus.command(enable=False)  # the hold
    bus.state(held)  # the plant heard again: the controller resumes
    bus.tick()
    assert stale_commands(bus.seen()) == []
    bus.t += ORDER_SKEW
    for _ in range(4):
        bus.command()
    found = stale_commands(bus.seen())
    assert [v.invariant for v in found] == ["stale_command"]
    assert "4 ticks" in found[0].detail


def test_a_corrupt_command_is_a_tick_and_a_state_just_after_a_command_counts_before_it() -> None:
    bus = Bus()
    bus.tick()
    bus.t += ORDER_SKEW
    bus.command()
    counter = bus.next(COMMAND)
    bus.send(COMMAND.frame_id, bytes(8))  # corrupt: no CRC holds for zeros here
    bus.command()
    bus.command()
    assert [v.invariant for v in stale_commands(bus.seen())] == ["stale_command"]
    bus.frames.insert(-1, bus.frames[-1])  # nothing: a duplicate of the last is no tick
    assert counter >= 0 and len(stale_commands(bus.seen())) == 1
    bus.t += ORDER_SKEW / 2
    bus.state(counter)  # recorded just after the last command
    assert stale_commands(bus.seen()) == []


def test_a_collision_the_plant_reports_is_caught_once() -> None:
    bus = Bus()
    bus.status("plant", "running")
    assert collisions(bus.seen()) == []
    for _ in range(3):
        bus.status("plant", "running", Flags=int(PlantFlag.COLLISION))
    assert len(collisions(bus.seen())) == 1


def world_frames(bus: Bus, world: World, flip: int | None = None) -> None:
    """An ISO-TP transfer of ``world`` on WorldUpload, by hand: first and consecutive
    frames (the plant's flow control left out); with ``flip``, that bit of it flipped."""
    payload = bytearray(seal(world.encode()))
    if flip is not None:
        payload[flip // 8] ^= 1 << flip % 8
    bus.send(
        WORLD_UPLOAD.frame_id, bytes([0x10 | len(payload) >> 8, len(payload) & 0xFF]) + payload[:6]
    )
    rest, index = payload[6:], 1
    while rest:
        bus.send(WORLD_UPLOAD.frame_id, bytes([0x20 | index % 16]) + rest[:7])
        rest, index = rest[7:], index + 1


def test_the_tool_inside_the_inflated_obstacle_of_the_plants_world_is_caught() -> None:
    bus = Bus()
    world_frames(bus, World(7, REFERENCE.obstacle, REFERENCE.tool_radius))
    bus.status("plant", "running", World=7)
    bus.state(0, HOME)
    worlds = Worlds()
    assert inside_obstacle(bus.seen(), worlds) == ([], 0)
    assert worlds.obstacles[7] == REFERENCE.obstacle
    bus.state(0, INSIDE)
    found, _ = inside_obstacle(bus.seen(), Worlds())
    assert [v.invariant for v in found] == ["inside_obstacle"]
    bus.status("plant", "running", World=8)  # a world whose upload is not recorded
    bus.state(0, INSIDE)
    assert inside_obstacle(bus.seen(), Worlds())[1] == 1


def test_a_world_that_failed_its_crc_is_not_taken_for_the_plants() -> None:
    bus = Bus()
    world_frames(bus, World(7, REFERENCE.obstacle, REFERENCE.tool_radius), flip=8 * 12)
    worlds = Worlds()
    inside_obstacle(bus.seen(), worlds)
    assert worlds.obstacles == {}


def test_an_obstacle_removed_leaves_the_way_through_free() -> None:
    bus = Bus()
    world_frames(bus, World(3, None, REFERENCE.tool_radius))
    bus.status("plant", "running", World=3)
    bus.state(0, INSIDE)
    assert inside_obstacle(bus.seen(), Worlds()) == ([], 0)


def test_a_fault_left_without_a_reset_is_caught_and_one_left_after_a_reset_is_not() -> None:
    bus = Bus()
    bus.both("running", "running")
    bus.both("fault", "running")
    bus.node_command(Request.RESET)
    bus.both("fault", "running")  # sent before the controller took the reset
    bus.both("ready", "ready")
    bus.both("estop", "estop")
    assert fault_latches(bus.seen()) == []
    bus.node_command(Request.RESET, NodeId.PLANT)  # a reset of the plant alone
    bus.both("ready", "ready")
    found = fault_latches(bus.seen())
    assert [(v.invariant, "controller" in v.detail) for v in found] == [("fault_latch", True)]


def test_a_restarted_node_keeps_no_latch() -> None:
    bus = Bus()
    bus.both("fault", "ready")
    bus.counters[CONTROLLER_STATUS.frame_id] = 15  # its next status starts at 0 again
    bus.status("controller", "ready", dt=3.0)
    assert fault_latches(bus.seen()) == []


def test_an_estop_every_node_must_say() -> None:
    bus = Bus()
    bus.both("running", "running")
    bus.estop()
    bus.both("estop", "estop")
    bus.both("estop", "estop")
    bus.node_command(Request.RESET)
    bus.both("ready", "ready")
    assert estop_latches(bus.seen()) == []
    bus.estop()
    for _ in range(5):
        bus.both("estop", "running")
    found = estop_latches(bus.seen())
    assert [(v.invariant, "plant" in v.detail) for v in found] == [("estop_latch", True)]


def recording_before_the_commands() -> Bus:
    """A recording begun over :data:`BACKLOG` before the controller's first command: the plant
    echoes no command sent before it (which its first echoes would fit as well)."""
    bus = Bus()
    bus.status("plant", "ready")
    bus.t += BACKLOG
    return bus


def test_the_plant_acting_on_a_corrupt_or_stale_command_is_caught() -> None:
    bus = recording_before_the_commands()
    for _ in range(20):
        bus.tick()
    assert bad_frames_acted(bus.seen()) == []
    # a corrupt command (its CRC broken): the plant echoing its counter acted on it
    counter = bus.next(COMMAND)
    record = COMMAND.Record(Enable=1, Theta1Rate=0.1, Theta2Rate=0.0, D3Rate=0.0)
    data = bytearray(COMMAND.encode(record, counter))
    data[0] ^= 0x01
    bus.send(COMMAND.frame_id, bytes(data))
    bus.state(counter)
    for _ in range(20):
        bus.tick()  # (judged once the recording holds the commands that could follow)
    assert [v.invariant for v in bad_frames_acted(bus.seen())] == ["bad_frame_acted"]


def test_a_reordered_command_acted_on_is_caught() -> None:
    bus = recording_before_the_commands()
    for _ in range(20):
        bus.tick()
    late = bus.next(COMMAND)
    newer = bus.command(counter=(late + 1) % 16)
    bus.state(newer)
    bus.command(counter=late)  # arrives after the newer one: stale
    bus.state(newer)
    assert bad_frames_acted(bus.seen()) == []
    bus.state(late)  # the plant took the stale one
    bus.counters[COMMAND.frame_id] = newer  # the controller goes on after the newer one
    for _ in range(20):
        bus.tick()
    assert [v.invariant for v in bad_frames_acted(bus.seen())] == ["bad_frame_acted"]


def test_the_recorders_interleaving_of_the_two_senders_does_not_matter() -> None:
    """Each sender's frames are in order; the plant's answers recorded well before the
    commands they answer (a paused recorder, a flood) are no violation."""
    bus = recording_before_the_commands()
    for _ in range(20):
        bus.tick()
    answers = []
    for _ in range(10):
        bus.tick()
        answers.append(bus.frames.pop())
        answers.extend([bus.frames.pop(), bus.frames.pop()][::-1])
    bus.frames[-20:-20] = answers  # recorded 20 frames early
    assert bad_frames_acted(bus.seen()) == []


def test_a_reset_plant_may_echo_zero_before_its_first_command() -> None:
    bus = Bus()
    for _ in range(5):
        bus.tick()
    bus.node_command(Request.RESET)
    bus.state(0)
    bus.state(0)
    bus.tick()
    assert bad_frames_acted(bus.seen()) == []


def a_plant_a_cycle_behind(ticks: int, acted_on: int | None = None) -> Bus:
    """The start of the recording where a soak (seed 73) found a violation that was none. The
    recorder, starting, got the controller's commands in bursts: 24 within 0.4 ms, counters
    4..15 then 0..11, and the next ones 58 ms in; meanwhile the plant, working through its
    backlog, echoed one a millisecond from 25 ms in, a 16-counter cycle behind them: from 3 (the
    first cycle's, sent before the recording began), through 4..15 and 0..12, skipping the
    second cycle's 13, which failed its CRC, to 14, ... The controller sends every 2 ms,
    ``ticks`` commands after the first 24, and the plant, once caught up, answers each 1 ms
    after it. Three commands in a row are lost on the wire 1.2 s in: cycles all alike fit the
    echoes equally, and a wire's losses tell which one the plant is on. With ``acted_on``,
    that tick's command failed its CRC and the plant took it."""
    bus = Bus()
    start = bus.t
    commands = []  # sent, recorded, counter, passes its CRC, taken by the plant
    for index, counter in enumerate([*range(4, 16), *range(12)]):
        recorded = start + 0.0004 * index / 23
        commands.append((recorded - 0.048, recorded, counter, True, True))
    for tick in range(ticks):
        if tick not in (600, 601, 602):
            good = tick not in (1, acted_on)
            sent = start + 0.002 * (tick + 1)
            recorded = max(sent, start + 0.058 + 0.00002 * tick)
            commands.append((sent, recorded, (12 + tick) % 16, good, good or tick == acted_on))
    echoes = [(start + 0.025, 3)]
    for sent, _, counter, _, taken in commands:
        if taken:
            echoes.append((max(echoes[-1][0], sent) + 0.001, counter))
    events = sorted(
        [(t, False, counter, good) for _, t, counter, good, _ in commands]
        + [(t, True, echo, True) for t, echo in echoes]
    )
    record = COMMAND.Record(Enable=1, Theta1Rate=0.1, Theta2Rate=0.0, D3Rate=0.0)
    for t, answer, counter, good in events:
        bus.t = t
        if answer:
            bus.state(counter)
            continue
        data = bytearray(COMMAND.encode(record, counter))
        data[0] ^= 0 if good else 0x01
        bus.send(COMMAND.frame_id, bytes(data), 0.0)
    return bus


def test_a_plant_a_cycle_behind_at_a_recordings_start_is_not_followed_a_cycle_ahead() -> None:
    """Its first echo, 3, fits the only 3 recorded near it (the second cycle's) and the one sent
    before the recording began alike; the echoes after it fit both cycles until the plant
    catches up, and the first cycle's 13 is no bad frame acted on."""
    assert bad_frames_acted(a_plant_a_cycle_behind(1300).seen()) == []


def test_after_a_start_a_cycle_behind_a_bad_frame_acted_on_is_still_caught() -> None:
    bus = a_plant_a_cycle_behind(1300, acted_on=1200)
    found = bad_frames_acted(bus.seen())
    assert [v.invariant for v in found] == ["bad_frame_acted"]
    assert f"counter {(12 + 1200) % 16}," in found[0].detail
    assert abs(found[0].t - (bus.frames[0].timestamp + 0.002 * 1201)) < 0.01


def test_an_outage_longer_than_the_bound_is_caught() -> None:
    bus = Bus()
    bus.both("ready", "ready")
    for _ in range(int(RECOVERY_BOUND / 2 / 0.1)):
        bus.both("fault", "ready")
    bus.both("ready", "ready")
    assert outages(bus.seen()) == []
    for _ in range(int(RECOVERY_BOUND * 1.2 / 0.1)):
        bus.both("ready", "estop")
    bus.both("ready", "ready")
    assert [v.invariant for v in outages(bus.seen())] == ["recovery"]
    for _ in range(int(RECOVERY_BOUND * 1.2 / 0.1)):
        bus.status("controller", "ready")  # the plant not heard
    bus.both("ready", "ready")
    assert len(outages(bus.seen())) == 2


def test_a_recording_cut_short_counts_only_with_its_recovered_twin(tmp_path: Path) -> None:
    bus = Bus()
    for _ in range(3000):
        bus.tick()
    path = tmp_path / "run-000.mcap"
    writer = MCAPWriter(path)
    for frame in bus.frames:
        writer.on_message_received(frame)
    writer.stop()
    assert readable(path) == (path, "")
    cut = tmp_path / "run-001.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    source, why = readable(cut)
    assert source is None and "not recovered" in why
    report = recover(cut, cut.with_suffix(".recovered.mcap"))
    assert report.frames > 0
    assert readable(cut) == (cut.with_suffix(".recovered.mcap"), "")
