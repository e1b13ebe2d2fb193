"""The controller node against a test peer over python-can's in-process ``virtual`` bus, with
an injected clock (canopen-style): the comms-loss policy (hold, resume, latched fault), E2E
checks and e-stop."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import can
import pytest
from support import FakeClock, frame

from controller.node import STALE_TICKS, ControllerNode
from controller.safety import Filtered, filtered
from protocol.codec import WIRE
from protocol.errors import ConfigError
from protocol.messages import NODE_COMMAND, STATE, STOP, ControllerFault, NodeState
from protocol.node import ClockMode
from protocol.scenario import load_scenario

SCENARIO = load_scenario("reference")
ACCEL = SCENARIO.robot.accel_limits


def send_state(peer: can.BusABC, counter: int, echo: int = 0) -> None:
    position = SCENARIO.initial_joints()
    for codec, joint_position in zip(STATE, position, strict=True):
        record = codec.Record(CommandEcho=echo, Position=joint_position, Velocity=0.0)
        peer.send(frame(codec.frame_id, codec.encode(record, counter)))


def commands(peer: can.BusABC) -> list[tuple[float, ...]]:
    """(Enable, rates...) of every command waiting on the test's bus."""
    found = []
    while (message := peer.recv(timeout=0.0)) is not None:
        codec, _, record = WIRE.decode(message.arbitration_id, message.data)
        if codec.name == "JointVelocityCommand":
            found.append(tuple(record))
    return found


def tick(controller: ControllerNode, clock: FakeClock) -> None:
    clock.now += controller.period
    controller.realtime_tick(clock.now)


def start_running(
    peer: can.BusABC, controller: ControllerNode, clock: FakeClock, ticks: int = 200
) -> int:
    """Feed a fresh state every tick until the arm moves; return the next state counter."""
    for counter in range(ticks):
        send_state(peer, counter % 16)
        tick(controller, clock)
    assert controller.node_state is NodeState.RUNNING
    return ticks % 16


def test_controller_holds_after_three_ticks_without_state_and_resumes_from_rest(
    virtual_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = virtual_pair
    clock = FakeClock()
    controller = ControllerNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=clock)
    controller.realtime_tick(clock.now)
    assert controller.node_state is NodeState.READY
    assert commands(peer) == [(0, 0.0, 0.0, 0.0)]  # nothing to control yet: zero, disabled
    counter = start_running(peer, controller, clock)
    moving = commands(peer)[-1]
    assert moving[0] == 1 and any(abs(rate) > 0.01 for rate in moving[1:])
    plan_ticks = controller.tick
    sent = []
    for _ in range(STALE_TICKS + 2):
        tick(controller, clock)
        sent += commands(peer)
    # Two more ticks on the last state, then zero with Enable = 0 at once:
    assert [command[0] for command in sent] == [1] * (STALE_TICKS - 1) + [0] * 3
    assert all(command == (0, 0.0, 0.0, 0.0) for command in sent[STALE_TICKS - 1 :])
    assert controller.node_state is NodeState.HOLD
    assert controller.tick == plan_ticks + STALE_TICKS - 1  # the plan's clock stopped
    assert controller.stats.holds == 1
    send_state(peer, counter)  # a fresh state: resume
    tick(controller, clock)
    resumed = commands(peer)
    assert controller.node_state is NodeState.RUNNING
    assert resumed[0][0] == 1
    for rate, limit in zip(resumed[0][1:], ACCEL, strict=True):  # from zero, within the limit
        assert abs(rate) <= limit * controller.period + 1e-3  # (+ wire quantisation)
    # Held from the STALE_TICKS-th quiet tick to the tick that brought the fresh state:
    held_ticks = (STALE_TICKS + 2) + 1 - STALE_TICKS
    assert controller.stats.hold_time == pytest.approx(held_ticks * controller.period)
    assert ControllerFault.STALE_STATE not in controller.fault


def test_a_hold_longer_than_the_comms_timeout_latches_a_fault(
    virtual_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = virtual_pair
    clock = FakeClock()
    controller = ControllerNode(
        node_bus, SCENARIO, ClockMode.REALTIME, comms_timeout=0.05, clock=clock
    )
    counter = start_running(peer, controller, clock, ticks=20)
    states = []
    for _ in range(40):  # 80 ms without a joint state
        tick(controller, clock)
        states.append(controller.node_state)
    assert NodeState.HOLD in states
    assert controller.node_state is NodeState.FAULT
    assert ControllerFault.STALE_STATE in controller.fault
    assert states.index(NodeState.FAULT) * controller.period == pytest.approx(0.05, abs=0.004)
    commands(peer)
    send_state(peer, counter)  # the plant is back: the fault stays until a reset
    tick(controller, clock)
    assert controller.node_state is NodeState.FAULT
    assert commands(peer) == [(0, 0.0, 0.0, 0.0)]
    reset = NODE_COMMAND.Record(Command=1, Target=1, Source=3, Ticket=0)
    peer.send(frame(NODE_COMMAND.frame_id, NODE_COMMAND.encode(reset, 0)))
    send_state(peer, (counter + 1) % 16)
    tick(controller, clock)
    assert controller.node_state is NodeState.RUNNING and not controller.fault


def test_comms_timeout_must_exceed_the_hold_ticks() -> None:
    bus = can.Bus(interface="virtual", channel="comms-timeout")
    try:
        with pytest.raises(ConfigError) as error:
            ControllerNode(bus, SCENARIO, ClockMode.REALTIME, comms_timeout=0.004)
        assert error.value.field == "--comms-timeout"
    finally:
        bus.shutdown()


def test_controller_ignores_corrupt_and_mixed_state_frames(
    virtual_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = virtual_pair
    controller = ControllerNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=FakeClock())
    position = SCENARIO.initial_joints()
    record = STATE[0].Record(CommandEcho=0, Position=position[0], Velocity=0.0)
    data = bytearray(STATE[0].encode(record, 0))
    data[4] ^= 0x01
    peer.send(frame(STATE[0].frame_id, bytes(data)))
    for codec, joint_position in zip(STATE[1:], position[1:], strict=True):
        good = codec.Record(CommandEcho=0, Position=joint_position, Velocity=0.0)
        peer.send(frame(codec.frame_id, codec.encode(good, 0)))
    controller.drain()
    assert controller.state is None  # joint 1 never arrived intact: no joint state
    assert controller.monitor.counts.corrupt == 1
    send_state(peer, 1, echo=2)
    controller.drain()
    assert controller.state is not None and controller.state.position == pytest.approx(position)


def test_controller_goes_to_estop_on_an_emergency_stop(
    virtual_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = virtual_pair
    clock = FakeClock()
    controller = ControllerNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=clock)
    send_state(peer, 0)
    controller.realtime_tick(clock.now)
    peer.send(frame(STOP.frame_id, STOP.encode(STOP.Record(Source=2), 0)))
    send_state(peer, 1)
    tick(controller, clock)
    assert controller.node_state is NodeState.ESTOP
    assert commands(peer)[-1] == (0, 0.0, 0.0, 0.0)


def test_the_run_clock_counts_holds_the_plan_clock_does_not(
    virtual_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    node_bus, peer = virtual_pair
    clock = FakeClock()
    controller = ControllerNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=clock)
    counter = start_running(peer, controller, clock, ticks=10)
    for _ in range(STALE_TICKS + 5):
        tick(controller, clock)
    send_state(peer, counter)
    tick(controller, clock)
    log = controller.log_rows
    # Of the quiet ticks, the first STALE_TICKS - 1 still controlled (on the last state);
    # the rest held: no control step, no row, but the run's clock went on.
    without_row = STALE_TICKS + 5 - (STALE_TICKS - 1)
    assert log["t"][-1] - log["t"][-2] == pytest.approx(controller.period)
    gap = log["clock"][-1] - log["clock"][-2]
    assert gap == pytest.approx((without_row + 1) * controller.period)


def test_a_run_goes_on_past_its_plan_until_its_timeout_then_latches_task_timeout_braking(
    virtual_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    """The plant reports the arm where it started, tick after tick: the task is never done."""
    node_bus, peer = virtual_pair
    clock = FakeClock()
    scenario = replace(SCENARIO, timeout=SCENARIO.duration + 0.5)
    controller = ControllerNode(node_bus, scenario, ClockMode.REALTIME, clock=clock)
    limit = round(scenario.time_limit / controller.period)
    counter = 0
    while controller.tick < limit and controller.node_state is not NodeState.FAULT:
        send_state(peer, counter % 16)
        counter += 1
        tick(controller, clock)
        sent = commands(peer)
        if controller.tick == controller.ticks_to_run:  # where a run used to end
            assert controller.node_state is NodeState.RUNNING and not controller.done
            assert sent[-1][0] == 1
    assert controller.node_state is NodeState.RUNNING  # the timeout's tick is the next one
    send_state(peer, counter % 16)
    tick(controller, clock)
    assert controller.tick == limit + 1 and len(controller.log_rows) == limit + 1
    assert controller.node_state is NodeState.FAULT
    assert controller.fault == ControllerFault.TASK_TIMEOUT
    assert commands(peer)[-1] == (0, 0.0, 0.0, 0.0)  # braking, not the tick's command
    run = {codec.name: record for codec, record in controller.statuses()}["ControllerRun"]
    assert run.Progress == 99  # 100: done
    result = controller.result()
    assert result["outcome"] == "task_timeout" and result["faults"] == ["TASK_TIMEOUT"]
    assert not result["completed"] and controller.done and controller.exit_code == 1
    send_state(peer, (counter + 1) % 16)
    tick(controller, clock)
    assert controller.node_state is NodeState.FAULT and controller.tick == limit + 1
    assert commands(peer) == [(0, 0.0, 0.0, 0.0)]


def test_a_run_that_makes_no_progress_latches_no_progress_long_before_its_timeout(
    virtual_pair: tuple[can.BusABC, can.BusABC],
) -> None:
    """The plant reports the arm where it started: the plan runs on to its first inner
    waypoint and waits there for the arm, which comes no nearer; after the task's
    no_progress_time the run ends so."""
    node_bus, peer = virtual_pair
    clock = FakeClock()
    scenario = replace(SCENARIO, no_progress_time=0.3, timeout=SCENARIO.duration + 30.0)
    controller = ControllerNode(node_bus, scenario, ClockMode.REALTIME, clock=clock)
    counter = 0
    while controller.node_state is not NodeState.FAULT:
        assert controller.tick < round(scenario.time_limit / controller.period)
        send_state(peer, counter % 16)
        counter += 1
        tick(controller, clock)
        commands(peer)
    waiting_from = scenario.waypoints[1].t - scenario.waypoints[0].t
    # the plan ran on (progress) until it stopped to wait at waypoint 1, then 0.3 s of none
    assert waiting_from < controller.tick * controller.period < waiting_from + 0.3 + 0.1
    assert controller.fault == ControllerFault.NO_PROGRESS
    status = {codec.name: record for codec, record in controller.statuses()}
    assert status["ControllerStatus"].FaultCode == ControllerFault.NO_PROGRESS.value
    result = controller.result()
    assert result["outcome"] == "no_progress" and result["faults"] == ["NO_PROGRESS"]
    assert not result["completed"] and controller.exit_code == 1
    send_state(peer, counter % 16)
    tick(controller, clock)
    assert commands(peer) == [(0, 0.0, 0.0, 0.0)]  # braking


def test_no_safe_motion_during_a_run_latches_its_fault_and_brakes(
    virtual_pair: tuple[can.BusABC, can.BusABC], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The safety filter finds no safe command from the 50th tick of the run on."""
    node_bus, peer = virtual_pair
    clock = FakeClock()
    controller = ControllerNode(node_bus, SCENARIO, ClockMode.REALTIME, clock=clock)

    def unsafe_late(ops: Any, wanted: Any, box: Any, barrier: Any) -> Filtered:
        return Filtered(filtered(ops, wanted, box, barrier).command, controller.tick >= 50)

    monkeypatch.setattr("controller.control_law.filtered", unsafe_late)
    counter = start_running(peer, controller, clock, ticks=50)
    assert controller.node_state is NodeState.RUNNING
    assert commands(peer)[-1][0] == 1  # moving
    send_state(peer, counter)
    tick(controller, clock)
    assert controller.node_state is NodeState.FAULT
    assert controller.fault == ControllerFault.NO_SAFE_MOTION
    assert commands(peer) == [(0, 0.0, 0.0, 0.0)]  # braking, not the tick's command
    result = controller.result()
    assert result["outcome"] == "no_safe_motion" and result["faults"] == ["NO_SAFE_MOTION"]
    assert not result["completed"] and controller.done and controller.exit_code == 1
