"""Co-simulation: ``controller`` and ``plant_sim`` as two OS processes that talk CAN frames only.

Each test runs the real node processes on one transport: CAN over Zenoh through a router of
the test's own on 127.0.0.1, or SocketCAN ``vcan0`` (marked ``hil``; skipped where there is no
vcan0). Where a test needs to see or say something on the bus it opens a bus of its own (the
``observer``) before the nodes start. Frames carry the observer's receive time.

The tests assert what the product must do (complete, fault or not, the measures), never how
fast a shared machine was: a stall of the machine shows as a hold, and a hold is allowed.
"""

from __future__ import annotations

import math
import signal
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import pytest
from cosim import (
    CONTROLLER_IDS,
    FAULTS,
    PLANT_IDS,
    PLANT_LISTENS,
    STARTUP,
    assert_bit_identical,
    assert_run_is_clean,
    brief,
    by_time,
    command_of,
    controller_in,
    decode,
    finish_clean,
    launch,
    node_args,
    run_result,
    status_of,
)
from support import (
    LATE_DETOUR,
    SLOWDOWN,
    Observer,
    Process,
    Processes,
    Transport,
    real_time_needed,
    wait_until,
)

from protocol.messages import (
    NODE_COMMAND,
    STATE_IDS,
    STEP,
    ControllerFault,
    NodeId,
    NodeState,
    Request,
)
from protocol.scenario import Mode

# --------------------------------------------------------------------------- 1. lockstep


@pytest.mark.timeout(240)
@pytest.mark.parametrize("mode", [Mode.FUZZY, Mode.CONVENTIONAL], ids=lambda m: m.value)
def test_lockstep_run_is_bit_identical_to_the_in_process_simulation(
    transport: Transport, processes: Processes, tmp_path: Path, mode: Mode
) -> None:
    out = tmp_path / "run"
    code, result = launch(processes, transport, out, "lockstep", "--mode", mode.value)
    outputs = processes.outputs()
    assert code == 0, f"{brief(result)}\n{outputs}"
    assert result["mode"] == mode.value and result["clock"] == "lockstep"
    assert_run_is_clean(result, outputs)
    assert_bit_identical(result, out, mode)


@pytest.mark.timeout(240)
@pytest.mark.parametrize("timed_out", [False, True], ids=["late", "timed-out"])
def test_lockstep_run_of_a_late_task_ends_as_the_in_process_simulations(
    transport: Transport, processes: Processes, tmp_path: Path, timed_out: bool
) -> None:
    """A detour that outlasts the settling time: the run goes on until its task is done, or
    (its timeout as short as its plan) ends in TASK_TIMEOUT, as in the simulation."""
    scenario = LATE_DETOUR
    if timed_out:  # the plan's 1.5 s and 1 s of settling
        scenario = tmp_path / "late_timeout.toml"
        scenario.write_text("timeout = 2.5\n" + LATE_DETOUR.read_text())
    out = tmp_path / "run"
    code, result = launch(processes, transport, out, "lockstep", scenario=str(scenario))
    outputs = processes.outputs()
    assert code == int(timed_out), f"{brief(result)}\n{outputs}"
    assert result["outcome"] == ("task_timeout" if timed_out else "done"), brief(result)
    assert result["faults"] == (["TASK_TIMEOUT"] if timed_out else []), brief(result)
    assert result["measures"]["collision_free"] is True
    assert_bit_identical(result, out, Mode.FUZZY, str(scenario))


# --------------------------------------------------------------------------- 2. real time


@pytest.mark.timeout(120)
def test_realtime_fuzzy_run_completes_without_faults(
    transport: Transport, processes: Processes, tmp_path: Path
) -> None:
    real_time_needed()
    out = tmp_path / "run"
    code, result = launch(processes, transport, out, "realtime", "--mode", "fuzzy")
    outputs = processes.outputs()
    assert code == 0, f"{brief(result)}\n{outputs}"
    assert result["clock"] == "realtime" and result["mode"] == "fuzzy"
    assert_run_is_clean(result, outputs)
    assert max(result["measures"]["waypoint_miss"]) < 0.005, result["measures"]


ALONE = 0.2
"""s the controller is seen looping (its READY status, sent from its loop) before the plant
starts."""


@pytest.mark.timeout(120)
def test_realtime_controller_started_before_the_plant_still_completes(
    transport: Transport,
    processes: Processes,
    observer_on: Callable[[Transport], Observer],
    tmp_path: Path,
) -> None:
    real_time_needed()
    observer = observer_on(transport)
    out = tmp_path / "run"
    controller = processes.start(
        "controller.cli",
        *node_args(transport, "realtime", out, "--max-wall-time", "40"),
        name="controller",
    )
    first = observer.wait_for(controller_in(NodeState.READY), STARTUP)
    assert first is not None, f"the controller never reported READY\n{processes.outputs()}"
    looping = observer.wait_for(
        lambda m: m.timestamp >= first.timestamp + ALONE and controller_in(NodeState.READY)(m),
        STARTUP,
    )
    assert looping is not None, f"the controller stopped reporting READY\n{processes.outputs()}"
    plant = processes.start("plant_sim.node", *node_args(transport, "realtime", out), name="plant")
    result = finish_clean(processes, controller, plant, out)
    loop = result["loop"]
    assert loop["loops"] > loop["ticks"], loop  # it looped while there was no plant


# --------------------------------------------------------------------------- 3. faults


MARGIN = 1.0 * SLOWDOWN
"""s before a node's first frame (half of it after its last) in which it may or may not have
been reading."""


def corrupt_frames(frames: list[can.Message], ids: frozenset[int]) -> list[can.Message]:
    return [m for m in frames if m.arbitration_id in ids and decode(m) is None]


def count_between(frames: list[can.Message], start: float, end: float) -> int:
    return sum(start <= m.timestamp <= end for m in frames)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_lockstep_with_dropped_and_corrupted_frames_is_still_exact(
    transport: Transport,
    processes: Processes,
    observer_on: Callable[[Transport], Observer],
    tmp_path: Path,
) -> None:
    """Both nodes drop 5 % and corrupt 1 % of the frames they send. Every corrupt frame that
    reached a node while it was listening is counted, none is acted on (the run stays
    bit-identical), and lost frames cost retries.

    Which corrupt frames a node could have received is taken from the observer, which is on
    the bus before either node and sees every frame: a frame sent before the receiver had
    joined, or after it stopped reading, never reaches it (as on a real bus). Those sent
    while its loop ran must all be counted (strict); a margin around that span may or may
    not be (loose): a node's bus is open a while before it sends its first frame (the node
    is built and its memory settled in between) and is read a little after its last, a
    while that is SLOWDOWN times as long on a slow machine.
    """
    observer = observer_on(transport)
    out = tmp_path / "run"
    code, result = launch(
        processes, transport, out, "lockstep", "--mode", "fuzzy", "--inject-faults", FAULTS
    )
    outputs = processes.outputs()
    assert code == 0, f"{brief(result)}\n{outputs}"
    assert_run_is_clean(result, outputs)
    assert_bit_identical(result, out, Mode.FUZZY)

    plant = result["plant"]
    c_injected, p_injected = result["injected"], plant["injected"]

    def heard_all_sent() -> bool:
        seen = observer.frames()
        from_c = sum(m.arbitration_id in CONTROLLER_IDS for m in seen)
        from_p = sum(m.arbitration_id in PLANT_IDS for m in seen)
        return from_c >= c_injected["sent"] and from_p >= p_injected["sent"]

    wait_until(heard_all_sent, 5.0, "the observer to hear as many frames as the nodes sent")
    frames = by_time(observer.frames())
    c_e2e, p_e2e = result["e2e"], plant["e2e"]
    summary = (
        f"controller e2e {c_e2e} injected {c_injected}; plant e2e {p_e2e} injected {p_injected}"
    )
    assert c_injected["corrupted"] > 0 and p_injected["corrupted"] > 0, summary
    assert c_injected["dropped"] > 0 and p_injected["dropped"] > 0, summary
    assert c_e2e["corrupt"] > 0 and p_e2e["corrupt"] > 0, summary
    assert c_e2e["lost"] > 0 and p_e2e["lost"] > 0, summary
    assert result["loop"]["lockstep_retries"] > 0, result["loop"]

    # The observer saw every frame the nodes put on the bus, corrupt ones included.
    from_controller = [m for m in frames if m.arbitration_id in CONTROLLER_IDS]
    from_plant = [m for m in frames if m.arbitration_id in PLANT_IDS]
    bad_from_controller = corrupt_frames(frames, CONTROLLER_IDS)
    bad_from_plant = corrupt_frames(frames, PLANT_IDS)
    assert len(from_controller) == c_injected["sent"], summary
    assert len(from_plant) == p_injected["sent"], summary
    assert len(bad_from_controller) == c_injected["corrupted"], summary
    assert len(bad_from_plant) == p_injected["corrupted"], summary

    steps = [m for m in from_controller if m.arbitration_id == STEP.frame_id]
    c_first, c_last_step = from_controller[0].timestamp, steps[-1].timestamp
    c_last = from_controller[-1].timestamp
    p_first = from_plant[0].timestamp
    by_id = Counter(hex(m.arbitration_id) for m in bad_from_controller)
    strict = count_between(bad_from_plant, c_first, c_last_step)
    loose = count_between(bad_from_plant, c_first - MARGIN, c_last + MARGIN / 2)
    assert strict <= c_e2e["corrupt"] <= loose, (
        f"controller counted {c_e2e['corrupt']} corrupt frames; the plant sent "
        f"{strict} (up to {loose}) corrupt frames while the controller was reading. {summary}"
    )
    heard = [m for m in bad_from_controller if m.arbitration_id in PLANT_LISTENS]
    strict = count_between(heard, p_first, math.inf)
    loose = count_between(heard, p_first - MARGIN, math.inf)
    assert strict <= p_e2e["corrupt"] <= loose, (
        f"plant counted {p_e2e['corrupt']} corrupt frames; the controller sent {strict} "
        f"(up to {loose}) corrupt frames while the plant was reading, by frame id "
        f"{dict(by_id)} (0x700 = ControllerStatus). {summary}"
    )


# --------------------------------------------------------------------------- 4. comms loss


def start_realtime_pair(
    transport: Transport, processes: Processes, out: Path, *controller_extra: str
) -> tuple[Process, Process]:
    plant = processes.start("plant_sim.node", *node_args(transport, "realtime", out), name="plant")
    controller = processes.start(
        "controller.cli",
        *node_args(transport, "realtime", out, "--max-wall-time", "40", *controller_extra),
        name="controller",
    )
    return plant, controller


def wait_running(observer: Observer, processes: Processes, seconds: float) -> None:
    """Wait until the controller reports RUNNING, then ``seconds`` more into the run."""
    running = observer.wait_for(controller_in(NodeState.RUNNING), STARTUP)
    assert running is not None, f"controller never reported RUNNING\n{processes.outputs()}"
    time.sleep(seconds)


def commands_between(frames: list[can.Message], start: float, end: float) -> list[Any]:
    return [c for m in frames if start < m.timestamp < end and (c := command_of(m))]


ZERO = (0, (0.0, 0.0, 0.0))
HOLD_WAIT = 5.0
"""s the plant stays stopped at most while the test waits for the controller to hold."""
HOLD_TIMEOUT = "10"
"""The controller's comms-loss timeout (s) in the hold test: above HOLD_WAIT, so that however
long the controller takes to notice the stop, the hold cannot become a fault."""


def holding(observer: Observer, since: float) -> bool:
    """The controller has reported HOLD since ``since``, and the last command it was heard to
    send commands zero with Enable = 0."""
    frames = observer.frames()
    commands = commands_between(frames, since, math.inf)
    reported = any(m.timestamp > since and controller_in(NodeState.HOLD)(m) for m in frames)
    return reported and bool(commands) and commands[-1] == ZERO


def enabled(message: can.Message) -> bool:
    """A valid JointVelocityCommand with Enable = 1: the controller is in control."""
    command = command_of(message)
    return command is not None and command[0] == 1


@pytest.mark.timeout(120)
def test_plant_stopped_until_the_controller_holds_then_it_resumes_and_completes(
    transport: Transport,
    processes: Processes,
    observer_on: Callable[[Transport], Observer],
    tmp_path: Path,
) -> None:
    """SIGSTOP the plant mid-run and keep it stopped until the controller reports HOLD and
    commands zero with Enable = 0 (how soon, 3 ticks, is the unit tests', with an injected
    clock); after SIGCONT it resumes on the first fresh state, and the run completes
    collision-free.

    The stop lasts until the hold is seen, not for a set time: the controller counts quiet
    ticks of its own loop, so a stop of a set length (50 ms, say) passes unnoticed whenever
    the controller is not scheduled for most of it. The comms-loss timeout is raised above
    the wait so that the hold cannot become a fault (the default is tested below)."""
    real_time_needed()
    observer = observer_on(transport)
    out = tmp_path / "run"
    plant, controller = start_realtime_pair(
        transport, processes, out, "--comms-timeout", HOLD_TIMEOUT
    )
    wait_running(observer, processes, 1.5)
    stopped = time.time()
    plant.signal(signal.SIGSTOP)
    try:
        wait_until(lambda: holding(observer, stopped), HOLD_WAIT, "the controller to hold")
    finally:
        continued = time.time()
        plant.signal(signal.SIGCONT)
    resumed = observer.wait_for(lambda m: m.timestamp > continued and enabled(m), STARTUP)
    assert resumed is not None, f"control never resumed\n{processes.outputs()}"
    result = finish_clean(processes, controller, plant, out)
    assert result["loop"]["holds"] >= 1, result["loop"]


@pytest.mark.timeout(120)
def test_plant_stopped_past_the_comms_timeout_latches_a_fault_with_zero_commands_and_braked(
    transport: Transport,
    processes: Processes,
    observer_on: Callable[[Transport], Observer],
    tmp_path: Path,
) -> None:
    """SIGSTOP the plant for 300 ms, and on until the controller reports the fault (default
    comms-loss timeout, 100 ms): the fault stays latched, with zero commands, after the plant
    is back, and the plant brakes."""
    real_time_needed()
    observer = observer_on(transport)
    out = tmp_path / "run"
    plant, controller = start_realtime_pair(transport, processes, out)
    wait_running(observer, processes, 1.5)
    stopped = time.time()
    plant.signal(signal.SIGSTOP)
    try:
        time.sleep(0.3)
        faulted = observer.wait_for(
            lambda m: m.timestamp > stopped and controller_in(NodeState.FAULT)(m), HOLD_WAIT
        )
    finally:
        plant.signal(signal.SIGCONT)
    assert faulted is not None, f"no FAULT status with the plant stopped\n{processes.outputs()}"
    time.sleep(1.0)  # the fault is latched: joint states flow again, the arm stays braked
    frames = by_time(observer.frames())
    controller.interrupt()
    plant.interrupt()
    result = run_result(out, controller, plant)
    assert "STALE_STATE" in result["faults"], brief(result)
    assert result["state"] == "FAULT" and not result["completed"], brief(result)

    states = [m for m in frames if m.arbitration_id in STATE_IDS]
    late = commands_between(frames, faulted.timestamp, math.inf)
    assert late and all(command == ZERO for command in late), late[:5]
    statuses = [s for m in frames if m.timestamp >= faulted.timestamp and (s := status_of(m))]
    assert statuses and all(state == NodeState.FAULT for state, _ in statuses), statuses
    assert all(fault & ControllerFault.STALE_STATE for _, fault in statuses), statuses
    # The plant braked: its last second of joint states shows every joint at rest.
    final = [decode(m) for m in states if m.timestamp > frames[-1].timestamp - 0.3]
    velocities = [d[2].Velocity for d in final if d is not None]
    assert velocities and all(v == 0.0 for v in velocities), velocities[-6:]


@pytest.mark.timeout(120)
def test_controller_resumes_after_plant_killed_restarted_and_reset(
    transport: Transport,
    processes: Processes,
    observer_on: Callable[[Transport], Observer],
    tmp_path: Path,
) -> None:
    """Start the plant first, kill it (SIGKILL): the controller holds, then faults. A new
    plant joins (the bus has no first process); after a reset the run completes."""
    real_time_needed()
    observer = observer_on(transport)
    out = tmp_path / "run"
    plant, controller = start_realtime_pair(transport, processes, out)
    wait_running(observer, processes, 1.5)
    killed = time.time()
    plant.kill()
    faulted = observer.wait_for(
        lambda m: m.timestamp > killed and controller_in(NodeState.FAULT)(m), 5.0
    )
    assert faulted is not None, f"no FAULT status after the plant died\n{processes.outputs()}"
    frames = by_time(observer.frames())
    states = [m.timestamp for m in frames if m.arbitration_id in STATE_IDS]
    assert max(states) < faulted.timestamp, "joint states after the controller gave the plant up"
    assert ZERO in commands_between(frames, killed, faulted.timestamp), "no hold before the fault"

    restarted = time.time()
    new_plant = processes.start(
        "plant_sim.node", *node_args(transport, "realtime", out), name="plant2"
    )
    new_state = observer.wait_for(
        lambda m: m.arbitration_id in STATE_IDS and m.timestamp > restarted, STARTUP
    )
    assert new_state is not None, f"the new plant is not heard\n{processes.outputs()}"
    time.sleep(0.5)  # joint states flow, but the fault is latched until a reset
    before = by_time(observer.frames())
    held = [s for m in before if m.timestamp > faulted.timestamp and (s := status_of(m))]
    assert held and all(state == NodeState.FAULT for state, _ in held), held
    assert ZERO in commands_between(before, faulted.timestamp, math.inf)
    assert all(c == ZERO for c in commands_between(before, faulted.timestamp, math.inf))

    record = NODE_COMMAND.Record(
        Command=Request.RESET, Target=NodeId.CONTROLLER, Source=NodeId.OPERATOR, Ticket=0
    )
    reset = observer.send(NODE_COMMAND.frame_id, NODE_COMMAND.encode(record, 0))
    running = observer.wait_for(
        lambda m: m.timestamp > reset and controller_in(NodeState.RUNNING)(m), 5.0
    )
    assert running is not None, f"no RUNNING status after the reset\n{processes.outputs()}"
    finish_clean(processes, controller, new_plant, out)
