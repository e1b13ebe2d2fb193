"""The two nodes against a test peer over python-can's in-process ``virtual`` bus, with an
injected clock: E2E checks, the watchdogs, lockstep stepping, e-stop (canopen-style tests)."""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import can
import pytest

from controller.node import STALE_TICKS, ControllerNode
from controller.process import ClockMode
from controller.scenario import load_scenario
from plant_sim.node import COMMAND_TIMEOUT, PlantNode
from protocol.bus import parse_options, resolve_transport
from protocol.codec import WIRE
from protocol.e2e import Check, E2EMonitor
from protocol.errors import ConfigError
from protocol.faults import FaultSpec
from protocol.messages import COMMAND, STATE, STEP, STOP, ControllerFault, Counter, NodeState

SCENARIO = load_scenario("reference")
_channels = itertools.count()


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def buses() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    """A node's bus and the test's bus, on a fresh virtual channel."""
    channel = f"test-{next(_channels)}"
    node_bus = can.Bus(interface="virtual", channel=channel)
    peer = can.Bus(interface="virtual", channel=channel)
    yield node_bus, peer
    node_bus.shutdown()
    peer.shutdown()


def frame(frame_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=frame_id, data=data, is_extended_id=False)


def received(bus: can.BusABC) -> list[tuple[str, int, tuple[float, ...]]]:
    """Every frame waiting on ``bus``, decoded."""
    frames = []
    while (message := bus.recv(timeout=0.0)) is not None:
        codec, counter, values = WIRE.decode(message.arbitration_id, message.data)
        frames.append((codec.name, counter, values))
    return frames


def deliver(node_bus: can.BusABC, node: PlantNode | ControllerNode) -> None:
    while (message := node_bus.recv(timeout=0.0)) is not None:
        node.handle(message)


# --- E2E -----------------------------------------------------------------------------------


def test_alive_counter_classification() -> None:
    monitor = E2EMonitor()
    sequence = [(5, Check.FIRST), (6, Check.OK), (6, Check.REPEATED), (9, Check.LOST)]
    sequence += [(7, Check.STALE), (10, Check.OK), (15, Check.LOST), (0, Check.OK)]
    for counter, expected in sequence:
        assert monitor.check(0x100, counter) is expected, counter
    assert monitor.check(0x200, 3) is Check.FIRST  # each frame ID has its own counter
    counts = monitor.counts
    assert (counts.repeated, counts.stale, counts.lost) == (1, 1, 2 + 4)
    assert [c.usable for c in (Check.FIRST, Check.OK, Check.LOST)] == [True] * 3
    assert not Check.REPEATED.usable and not Check.STALE.usable
    monitor.forget()
    assert monitor.check(0x100, 3) is Check.FIRST


def test_alive_counter_resynchronises_after_a_long_gap() -> None:
    monitor = E2EMonitor()
    monitor.check(0x110, 0)
    # Ten frames lost: 11 looks like an old frame (stale), but 12 continues it, so the
    # sender has moved on and the receiver follows instead of rejecting everything after.
    assert [monitor.check(0x110, c) for c in (11, 12, 13)] == [Check.STALE, Check.OK, Check.OK]
    # A single late frame does not move the receiver back.
    assert monitor.check(0x110, 10) is Check.STALE
    assert monitor.check(0x110, 14) is Check.OK


def test_fault_spec_parsing_names_the_field() -> None:
    assert FaultSpec.parse("drop=0.05,corrupt=0.01,seed=3") == FaultSpec(0.05, 0.01, 3)
    with pytest.raises(ConfigError) as error:
        FaultSpec.parse("drop=2")
    assert error.value.field == "inject-faults.drop"
    with pytest.raises(ConfigError) as error:
        FaultSpec.parse("jitter=0.1")
    assert error.value.field == "inject-faults.jitter"


# --- plant ---------------------------------------------------------------------------------


def test_plant_answers_a_command_with_its_counter_and_brakes_when_commands_stop(
    buses: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = buses
    clock = FakeClock()
    plant = PlantNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=clock)
    peer.send(frame(COMMAND.frame_id, COMMAND.encode((1, 0.5, -0.25, 0.0), 7)))
    deliver(node_bus, plant)
    answer = received(peer)
    assert [name for name, _, _ in answer] == ["JointState1", "JointState2", "JointState3"]
    assert {values[0] for _, _, values in answer} == {7}  # CommandEcho
    assert plant.command == (0.5, -0.25, 0.0)
    clock.now += COMMAND_TIMEOUT / 2
    plant.on_period(clock.now)
    assert plant.command == (0.5, -0.25, 0.0)
    assert plant.model.velocity[0] > 0.0
    clock.now += COMMAND_TIMEOUT
    plant.on_period(clock.now)
    assert plant.command == (0.0, 0.0, 0.0)
    assert plant.stats.command_timeouts == 1


def test_plant_never_acts_on_a_corrupt_or_repeated_command(
    buses: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = buses
    plant = PlantNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=FakeClock())
    good = COMMAND.encode((1, 0.5, 0.0, 0.0), 1)
    peer.send(frame(COMMAND.frame_id, good))
    corrupt = bytearray(COMMAND.encode((1, 5.0, 0.0, 0.0), 2))
    corrupt[3] ^= 0x10
    peer.send(frame(COMMAND.frame_id, bytes(corrupt)))
    peer.send(frame(COMMAND.frame_id, COMMAND.encode((1, 3.0, 0.0, 0.0), 1)))  # repeated counter
    peer.send(frame(COMMAND.frame_id, b"\x00\x01"))  # wrong length
    deliver(node_bus, plant)
    assert plant.command == (0.5, 0.0, 0.0)
    assert plant.monitor.counts.corrupt == 2
    assert plant.monitor.counts.repeated == 1


def test_plant_steps_once_per_step_frame_and_only_under_the_named_command(
    buses: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = buses
    plant = PlantNode(node_bus, SCENARIO, ClockMode.LOCKSTEP, clock=FakeClock())
    steps = Counter()
    peer.send(frame(COMMAND.frame_id, COMMAND.encode((1, 1.0, 0.0, 0.0), 4)))
    peer.send(frame(STEP.frame_id, STEP.encode((3, 1), steps.next())))  # names command 3: no
    deliver(node_bus, plant)
    assert plant.tick == 0 and received(peer) == []
    assert plant.stats.unknown_step_requests == 1
    peer.send(frame(STEP.frame_id, STEP.encode((4, 1), steps.next())))
    deliver(node_bus, plant)
    first = received(peer)
    assert plant.tick == 1 and len(first) == 3
    position = plant.model.position
    peer.send(frame(STEP.frame_id, STEP.encode((4, 1), steps.next())))  # the answer was lost
    deliver(node_bus, plant)
    again = received(peer)
    assert plant.tick == 1 and plant.model.position == position
    assert [values for _, _, values in again] == [values for _, _, values in first]


def test_plant_does_not_step_under_a_command_it_never_received(
    buses: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = buses
    plant = PlantNode(node_bus, SCENARIO, ClockMode.LOCKSTEP, clock=FakeClock())
    # The controller's first command (counter 0) was lost; its StepSync names counter 0,
    # which is also what the plant echoes before any command: it must not step.
    peer.send(frame(STEP.frame_id, STEP.encode((0, 1), 0)))
    deliver(node_bus, plant)
    assert plant.tick == 0 and plant.stats.steps == 0
    peer.send(frame(COMMAND.frame_id, COMMAND.encode((1, 1.0, 0.0, 0.0), 1)))
    peer.send(frame(STEP.frame_id, STEP.encode((1, 1), 1)))
    deliver(node_bus, plant)
    assert plant.tick == 1 and plant.stats.steps == 1


def test_plant_latches_emergency_stop(buses: tuple[can.BusABC, can.BusABC]) -> None:
    node_bus, peer = buses
    plant = PlantNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=FakeClock())
    peer.send(frame(STOP.frame_id, STOP.encode((3,), 0)))
    peer.send(frame(COMMAND.frame_id, COMMAND.encode((1, 1.0, 0.0, 0.0), 0)))
    deliver(node_bus, plant)
    assert plant.node_state is NodeState.ESTOP
    assert plant.command == (0.0, 0.0, 0.0)


# --- controller ----------------------------------------------------------------------------


def send_state(peer: can.BusABC, counter: int, echo: int = 0) -> None:
    position = SCENARIO.initial_joints()
    for codec, joint_position in zip(STATE, position, strict=True):
        peer.send(frame(codec.frame_id, codec.encode((echo, joint_position, 0.0), counter)))


def commands(peer: can.BusABC) -> list[tuple[float, ...]]:
    return [values for name, _, values in received(peer) if name == "JointVelocityCommand"]


def test_controller_faults_after_three_ticks_without_state_and_sends_only_zero(
    buses: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = buses
    clock = FakeClock()
    controller = ControllerNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=clock)
    controller.realtime_tick(clock.now)
    assert controller.node_state is NodeState.READY
    assert commands(peer) == [(0, 0.0, 0.0, 0.0)]  # nothing to control yet: zero, disabled
    for counter in range(5):
        send_state(peer, counter)
        clock.now += controller.period
        controller.realtime_tick(clock.now)
    assert controller.node_state is NodeState.RUNNING
    assert all(command[0] == 1 for command in commands(peer))
    sent_enabled = []
    for _ in range(STALE_TICKS + 2):
        clock.now += controller.period
        controller.realtime_tick(clock.now)
        sent_enabled += [command[0] for command in commands(peer)]
    assert sent_enabled == [1] * (STALE_TICKS - 1) + [0] * 3
    assert controller.node_state is NodeState.FAULT
    assert ControllerFault.STALE_STATE in controller.fault
    send_state(peer, 5)  # the plant is back: the fault stays until a reset
    clock.now += controller.period
    controller.realtime_tick(clock.now)
    assert controller.node_state is NodeState.FAULT
    assert commands(peer) == [(0, 0.0, 0.0, 0.0)]


def test_controller_ignores_corrupt_and_mixed_state_frames(
    buses: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = buses
    controller = ControllerNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=FakeClock())
    position = SCENARIO.initial_joints()
    data = bytearray(STATE[0].encode((0, position[0], 0.0), 0))
    data[4] ^= 0x01
    peer.send(frame(STATE[0].frame_id, bytes(data)))
    for codec, joint_position in zip(STATE[1:], position[1:], strict=True):
        peer.send(frame(codec.frame_id, codec.encode((0, joint_position, 0.0), 0)))
    deliver(node_bus, controller)
    assert controller.state is None  # joint 1 never arrived intact: no joint state
    assert controller.monitor.counts.corrupt == 1
    send_state(peer, 1, echo=2)
    deliver(node_bus, controller)
    assert controller.state is not None and controller.state.position == pytest.approx(position)


def test_controller_goes_to_estop_on_an_emergency_stop(
    buses: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = buses
    clock = FakeClock()
    controller = ControllerNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=clock)
    send_state(peer, 0)
    controller.realtime_tick(clock.now)
    peer.send(frame(STOP.frame_id, STOP.encode((2,), 0)))
    send_state(peer, 1)
    clock.now += controller.period
    controller.realtime_tick(clock.now)
    assert controller.node_state is NodeState.ESTOP
    assert commands(peer)[-1] == (0, 0.0, 0.0, 0.0)


# --- transport selection ---------------------------------------------------------------------


def test_transport_comes_from_flags_then_python_can_config_then_default(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    assert resolve_transport("virtual", "x") == ("virtual", "x")
    monkeypatch.setenv("CAN_INTERFACE", "udp_multicast")
    monkeypatch.setenv("CAN_CHANNEL", "239.74.163.2")
    assert resolve_transport(None, None) == ("udp_multicast", "239.74.163.2")
    monkeypatch.delenv("CAN_INTERFACE")
    monkeypatch.delenv("CAN_CHANNEL")
    monkeypatch.setenv("HOME", "/nonexistent")
    interface, _ = resolve_transport(None, None)
    assert interface in ("socketcan", "zenoh")
    assert parse_options(["port=17447", "express=false", "host=127.0.0.1"]) == {
        "port": 17447,
        "express": False,
        "host": "127.0.0.1",
    }
