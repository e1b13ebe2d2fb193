"""The plant node against a test peer over python-can's in-process ``virtual`` bus, with an
injected clock (canopen-style): answers, E2E checks, the brake, lockstep stepping, e-stop."""

from __future__ import annotations

import can
from support import FakeClock, frame

from plant_sim.node import COMMAND_TIMEOUT, PlantNode
from protocol.codec import WIRE
from protocol.messages import COMMAND, NODE_COMMAND, STEP, STOP, Counter, NodeState, PlantFault
from protocol.node import ClockMode
from protocol.scenario import load_scenario

SCENARIO = load_scenario("reference")


def command(rate1: float, counter: int, enable: int = 1, rate2: float = 0.0) -> can.Message:
    record = COMMAND.Record(Enable=enable, Theta1Rate=rate1, Theta2Rate=rate2, D3Rate=0.0)
    return frame(COMMAND.frame_id, COMMAND.encode(record, counter))


def step(command_counter: int, tick: int, counter: int) -> can.Message:
    record = STEP.Record(CommandCounter=command_counter, Tick=tick)
    return frame(STEP.frame_id, STEP.encode(record, counter))


def received(bus: can.BusABC) -> list[tuple[str, int, tuple[float, ...]]]:
    """Every frame waiting on ``bus``, decoded."""
    frames = []
    while (message := bus.recv(timeout=0.0)) is not None:
        codec, counter, record = WIRE.decode(message.arbitration_id, message.data)
        frames.append((codec.name, counter, tuple(record)))
    return frames


def deliver(node_bus: can.BusABC, node: PlantNode) -> None:
    while (message := node_bus.recv(timeout=0.0)) is not None:
        node.handle(message)


def test_plant_answers_a_command_with_its_counter_and_brakes_when_commands_stop(
    virtual_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = virtual_pair
    clock = FakeClock()
    plant = PlantNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=clock)
    peer.send(command(0.5, 7, rate2=-0.25))
    deliver(node_bus, plant)
    answer = received(peer)
    assert [name for name, _, _ in answer] == ["JointState1", "JointState2", "JointState3"]
    assert {values[0] for _, _, values in answer} == {7}  # CommandEcho
    assert len({counter for _, counter, _ in answer}) == 1  # one joint state, one counter
    assert plant.command == (0.5, -0.25, 0.0)
    clock.now += COMMAND_TIMEOUT / 2
    plant.on_period(clock.now)
    assert plant.command == (0.5, -0.25, 0.0)
    assert plant.model.velocity[0] > 0.0
    clock.now += COMMAND_TIMEOUT
    plant.on_period(clock.now)
    assert plant.command == (0.0, 0.0, 0.0)
    assert plant.stats.command_timeouts == 1
    assert PlantFault.COMMAND_TIMEOUT in plant.fault


def test_a_plant_that_was_not_scheduled_catches_up_with_its_brake(
    virtual_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    """After a stall (SIGSTOP) the plant integrates the last command only until its drives'
    20 ms watchdog, then the brake: it does not drive on blindly for the whole stall."""
    node_bus, peer = virtual_pair
    clock = FakeClock()
    plant = PlantNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=clock)
    peer.send(command(2.0, 1))
    deliver(node_bus, plant)
    stalled_from = plant.model.position[0]
    clock.now += 0.3  # 300 ms without being scheduled
    plant.on_period(clock.now)
    moved = plant.model.position[0] - stalled_from
    assert plant.command == (0.0, 0.0, 0.0)
    assert abs(plant.model.velocity[0]) < 1e-6  # braked to rest
    # 2 rad/s for 20 ms plus the braking distance, far less than 0.3 s at 2 rad/s:
    assert 0.0 < moved < 0.15
    assert plant.stats.command_timeouts == 1


def test_plant_never_acts_on_a_corrupt_or_repeated_command(
    virtual_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = virtual_pair
    plant = PlantNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=FakeClock())
    peer.send(command(0.5, 1))
    corrupt = bytearray(command(5.0, 2).data)
    corrupt[3] ^= 0x10
    peer.send(frame(COMMAND.frame_id, bytes(corrupt)))
    peer.send(command(3.0, 1))  # repeated counter
    peer.send(frame(COMMAND.frame_id, b"\x00\x01"))  # wrong length
    deliver(node_bus, plant)
    assert plant.command == (0.5, 0.0, 0.0)
    assert plant.monitor.counts.corrupt == 2
    assert plant.monitor.counts.repeated == 1


def test_plant_steps_once_per_step_frame_and_only_under_the_named_command(
    virtual_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = virtual_pair
    plant = PlantNode(node_bus, SCENARIO, ClockMode.LOCKSTEP, clock=FakeClock())
    steps = Counter()
    peer.send(command(1.0, 4))
    peer.send(step(3, 1, steps.next()))  # names command 3: no
    deliver(node_bus, plant)
    assert plant.tick == 0 and received(peer) == []
    assert plant.stats.unknown_step_requests == 1
    peer.send(step(4, 1, steps.next()))
    deliver(node_bus, plant)
    first = received(peer)
    assert plant.tick == 1 and len(first) == 3
    position = plant.model.position
    peer.send(step(4, 1, steps.next()))  # the answer was lost
    deliver(node_bus, plant)
    again = received(peer)
    assert plant.tick == 1 and plant.model.position == position
    assert [values for _, _, values in again] == [values for _, _, values in first]


def test_plant_does_not_step_under_a_command_it_never_received(
    virtual_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = virtual_pair
    plant = PlantNode(node_bus, SCENARIO, ClockMode.LOCKSTEP, clock=FakeClock())
    # The controller's first command (counter 0) was lost; its StepSync names counter 0,
    # which is also what the plant echoes before any command: it must not step.
    peer.send(step(0, 1, 0))
    deliver(node_bus, plant)
    assert plant.tick == 0 and plant.stats.steps == 0
    peer.send(command(1.0, 1))
    peer.send(step(1, 1, 1))
    deliver(node_bus, plant)
    assert plant.tick == 1 and plant.stats.steps == 1


def test_plant_latches_emergency_stop_until_a_reset(
    virtual_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = virtual_pair
    plant = PlantNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=FakeClock())
    peer.send(frame(STOP.frame_id, STOP.encode(STOP.Record(Source=3), 0)))
    peer.send(command(1.0, 0))
    deliver(node_bus, plant)
    assert plant.node_state is NodeState.ESTOP
    assert plant.command == (0.0, 0.0, 0.0)
    reset = NODE_COMMAND.Record(Command=1, Target=2, Source=3, Ticket=0)
    peer.send(frame(NODE_COMMAND.frame_id, NODE_COMMAND.encode(reset, 0)))
    peer.send(command(1.0, 1))
    deliver(node_bus, plant)
    assert plant.node_state is NodeState.RUNNING and plant.command == (1.0, 0.0, 0.0)


def test_status_frame_goes_out_on_the_dbcs_cycle_time(
    virtual_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = virtual_pair
    clock = FakeClock()
    plant = PlantNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=clock)
    sent = 0
    for _ in range(100):  # 1 s in 10 ms steps
        plant.send_status_if_due(clock.now)
        sent += sum(name == "PlantStatus" for name, _, _ in received(peer))
        clock.now += 0.01
    assert sent == 10
