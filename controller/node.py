"""``controller``: the controller process. It owns the bus and the fixed-rate loop around the
pure :class:`~controller.control_law.ControlLaw`.

Real-time mode: ticks at absolute deadlines on the monotonic clock: it waits on the bus until
just before each deadline, then polls. Each tick takes the newest complete, valid joint
state, runs one control step and sends the command. If no valid joint state has arrived for
``STALE_TICKS`` ticks it sends zero (Enable = 0) and goes to fault; it never computes a
command from a stale state.

Lockstep mode: per tick it sends the command and a StepSync naming it, then waits for the
plant's answer. A lost or corrupt frame costs a retry, never a wrong step, so the run is
bit-identical to the in-process simulation.

Both modes: every received frame is checked (CRC, length, range, alive counter); bad ones are
counted and ignored. A NodeCommand ``reset`` restarts the scenario from the plant's present
state; an EmergencyStop latches the e-stop state until a reset.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import can
import numpy as np

from controller.control_law import ControlOutput
from controller.coordination import Mode
from controller.measures import compute_measures
from controller.process import (
    ClockMode,
    add_node_arguments,
    open_node,
    settle_memory,
    stop_on_signals,
)
from controller.runlog import COLUMNS, RunLog, row_of
from controller.scenario import Scenario
from controller.simulation import build_law
from protocol.e2e import E2EMonitor
from protocol.errors import EncodeError
from protocol.messages import (
    COMMAND,
    CONTROLLER_STATUS,
    NODE_COMMAND,
    PLANT_STATUS,
    STATE,
    STATE_IDS,
    STATUS_PERIOD,
    STEP,
    STOP,
    ControllerFault,
    Counter,
    Joints,
    NodeId,
    NodeState,
    PlantFault,
    Request,
    encode_status,
    send_frame,
)

STALE_TICKS = 3
"""Ticks without a new valid joint state before the controller stops and faults."""
SPIN = 0.0002
"""s before a deadline from which the loop polls instead of blocking (a blocking wait wakes
~100 us late here); each poll yields the GIL, which the transport's receive threads need."""
LATE_TOLERANCE = 0.25
"""A tick starting later than this fraction of the period counts as a missed deadline."""
LOCKSTEP_RETRY = 0.005
"""s the controller waits for the plant's answer in lockstep before sending again."""
LOCKSTEP_GIVE_UP = 1.0
"""s without any answer in lockstep before the controller faults (the plant is gone)."""


@dataclass(slots=True)
class JointState:
    position: Joints
    velocity: Joints
    echo: int
    received: float


@dataclass(slots=True)
class LoopStats:
    """How the loop kept time, and what the wire did."""

    loops: int = 0
    ticks: int = 0
    deadline_misses: int = 0
    overruns: int = 0
    stale_faults: int = 0
    lockstep_retries: int = 0
    lateness: list[float] = field(default_factory=list)
    answer_delay: list[float] = field(default_factory=list)

    def summary(self, period: float) -> dict[str, float | int | None]:
        lateness = np.asarray(self.lateness) if self.lateness else np.zeros(1)
        answers = np.asarray(self.answer_delay)
        # Real time only (loops counts its ticks): lockstep has no "within a tick".
        within = (
            float(np.sum(answers <= period)) / self.ticks if self.loops and self.ticks else None
        )
        return {
            "loops": self.loops,
            "ticks": self.ticks,
            "deadline_misses": self.deadline_misses,
            "deadline_miss_fraction": self.deadline_misses / max(self.loops, 1),
            "overruns": self.overruns,
            "stale_faults": self.stale_faults,
            "lockstep_retries": self.lockstep_retries,
            "lateness_p50_us": float(np.percentile(lateness, 50) * 1e6),
            "lateness_p99_us": float(np.percentile(lateness, 99) * 1e6),
            "lateness_max_us": float(lateness.max() * 1e6),
            "answered_within_tick_fraction": within,
            "answer_delay_p50_us": float(np.percentile(answers, 50) * 1e6) if len(answers) else 0.0,
            "answer_delay_p99_us": float(np.percentile(answers, 99) * 1e6) if len(answers) else 0.0,
        }


class ControllerNode:
    """The controller's side of the wire around the control law of one scenario."""

    def __init__(
        self,
        bus: can.BusABC,
        scenario: Scenario,
        clock_mode: ClockMode,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.bus = bus
        self.scenario = scenario
        self.clock_mode = clock_mode
        self.clock = clock
        self.sleep = sleep
        self.period = scenario.controller.period
        self.ticks_to_run = round(scenario.duration / self.period) + 1
        self.law = build_law(scenario)
        self.monitor = E2EMonitor()
        self.stats = LoopStats()
        self.command_counter = Counter()
        self.step_counter = Counter()
        self.status_counter = Counter()
        self.running = True
        self.node_state = NodeState.READY
        self.fault = ControllerFault(0)
        self.states_received = 0
        self._seen = 0
        self._quiet_ticks = STALE_TICKS
        self._next_status = -float("inf")
        self._awaiting: dict[int, float] = {}  # command counter -> when it was sent
        self._parts: dict[int, list[tuple[float, float, int] | None]] = {}
        self.state: JointState | None = None
        self.reset()

    def reset(self) -> None:
        """Start the scenario again from the next joint state that arrives."""
        self.law.reset()
        self.log = RunLog(self.ticks_to_run)
        self.tick = 0
        self.state = None
        self._parts.clear()
        self.monitor.forget()
        self.fault = ControllerFault(0)
        self.node_state = NodeState.READY

    # --- frames in -------------------------------------------------------------------------

    def drain(self, timeout: float = 0.0) -> None:
        """Handle every frame waiting on the bus (waiting up to ``timeout`` for the first)."""
        message = self.bus.recv(timeout=timeout)
        while message is not None:
            self.handle(message)
            message = self.bus.recv(timeout=0.0)

    def handle(self, message: can.Message) -> None:
        accepted = self.monitor.accept(message, _RECEIVED)
        if accepted is None:
            return
        codec, counter, values = accepted
        if codec.frame_id in STATE_IDS:
            self._on_state_part(STATE_IDS.index(codec.frame_id), counter, values)
        elif codec is PLANT_STATUS:
            if int(values[1]) & (PlantFault.JOINT_LIMIT | PlantFault.COLLISION):
                self._enter_fault(ControllerFault.PLANT_FAULT)
        elif codec is STOP:
            self.fault |= ControllerFault.ESTOP
            self.node_state = NodeState.ESTOP
        elif codec is NODE_COMMAND:
            request, target = int(values[0]), int(values[1])
            if target in (NodeId.CONTROLLER, NodeId.ALL):
                if request == Request.RESET:
                    self.reset()
                elif request == Request.STOP:
                    self.running = False

    def _on_state_part(self, joint: int, counter: int, values: tuple[float, ...]) -> None:
        """Collect JointState1-3; the three frames of one plant step share one counter."""
        parts = self._parts.setdefault(counter, [None, None, None])
        parts[joint] = (values[1], values[2], int(values[0]))
        if all(part is not None for part in parts):
            complete = [part for part in parts if part is not None]
            echoes = {part[2] for part in complete}
            self._parts.clear()
            if len(echoes) != 1:
                return
            self.states_received += 1
            self.state = JointState(
                (complete[0][0], complete[1][0], complete[2][0]),
                (complete[0][1], complete[1][1], complete[2][1]),
                echoes.pop(),
                self.clock(),
            )
            sent = self._awaiting.pop(self.state.echo, None)
            if sent is not None:
                self.stats.answer_delay.append(self.state.received - sent)
        elif len(self._parts) > 4:  # incomplete sets of lost frames: keep only recent ones
            for old in list(self._parts)[:-2]:
                del self._parts[old]

    # --- frames out --------------------------------------------------------------------------

    def _send(self, frame_id: int, data: bytes) -> None:
        send_frame(self.bus, frame_id, data, "controller")

    def _send_command(self, rates: Joints, enable: bool) -> int:
        counter = self.command_counter.next()
        try:
            data = COMMAND.encode((int(enable), *rates), counter)
        except EncodeError as error:
            print(f"controller: {error}", file=sys.stderr)
            self._enter_fault(ControllerFault.ENCODE)
            data = COMMAND.encode((0, 0.0, 0.0, 0.0), counter)
        self._send(COMMAND.frame_id, data)
        return counter

    def _send_status(self) -> None:
        flags = int(self.clock_mode is ClockMode.LOCKSTEP) | (
            int(self.scenario.mode is Mode.FUZZY) << 1
        )
        data = encode_status(
            CONTROLLER_STATUS,
            self.status_counter.next(),
            self.node_state,
            int(self.fault),
            flags,
            self.monitor.counts.bad,
            min(self.stats.deadline_misses, 0xFFFF),
        )
        self._send(CONTROLLER_STATUS.frame_id, data)

    def _enter_fault(self, reason: ControllerFault) -> None:
        self.fault |= reason
        if self.node_state is not NodeState.ESTOP:
            self.node_state = NodeState.FAULT

    # --- one control step ----------------------------------------------------------------------

    def _control(self, state: JointState) -> ControlOutput:
        t = self.scenario.waypoints[0].t + self.tick * self.period
        output = self.law.step(t, state.position)
        self.log.append(row_of(t, state.position, state.velocity, output))
        self.tick += 1
        return output

    @property
    def finished(self) -> bool:
        return self.tick >= self.ticks_to_run

    # --- real time -----------------------------------------------------------------------------

    def run_realtime(self, max_wall_time: float | None = None) -> None:
        """Tick at absolute deadlines until the scenario is done, or stopped.

        A tick that starts late still runs; slots missed entirely are skipped (and counted),
        never run back to back.
        """
        start = self.clock()
        deadline = start
        while self.running and not (self.node_state is NodeState.RUNNING and self.finished):
            if max_wall_time is not None and self.clock() - start > max_wall_time:
                break
            now = self.clock()
            while now < deadline:
                if deadline - now > SPIN:
                    self.drain(timeout=deadline - now - SPIN)
                else:
                    self.sleep(0.0)  # yields the GIL to the transport's threads
                now = self.clock()
            lateness = now - deadline
            self.stats.lateness.append(lateness)
            if lateness > LATE_TOLERANCE * self.period:
                self.stats.deadline_misses += 1
            self.realtime_tick(now)
            deadline += self.period
            now = self.clock()
            if now > deadline:
                self.stats.overruns += 1
                missed = int((now - deadline) / self.period)
                self.stats.deadline_misses += missed
                deadline += missed * self.period

    def realtime_tick(self, now: float) -> None:
        """One real-time tick: take what arrived, check freshness, command, report.

        The joint state is stale once STALE_TICKS ticks have run without a new one arriving;
        from then on the command is zero with Enable = 0 and the node is in fault.
        """
        self.stats.loops += 1
        self.drain()
        self._quiet_ticks = 0 if self.states_received != self._seen else self._quiet_ticks + 1
        self._seen = self.states_received
        state = self.state
        if self.node_state is NodeState.READY and self._quiet_ticks == 0:
            self.node_state = NodeState.RUNNING
        if self.node_state is NodeState.RUNNING and self._quiet_ticks >= STALE_TICKS:
            self.stats.stale_faults += 1
            self._enter_fault(ControllerFault.STALE_STATE)
        if self.node_state is NodeState.RUNNING and state is not None:
            output = self._control(state)
            counter = self._send_command(output.command, True)
            self._awaiting[counter] = self.clock()
            self.stats.ticks += 1
        else:
            self._send_command((0.0, 0.0, 0.0), False)
        if now >= self._next_status:
            self._send_status()
            self._next_status = now + STATUS_PERIOD

    # --- lockstep --------------------------------------------------------------------------------

    def run_lockstep(
        self, startup_timeout: float = 30.0, max_wall_time: float | None = None
    ) -> None:
        """Step the plant tick by tick; a lost answer is asked for again.

        If no answer comes for LOCKSTEP_GIVE_UP the plant is taken as gone: the controller
        sends zero with Enable = 0, goes to fault and returns. A fault, an e-stop or a reset
        received meanwhile also ends the run (zero sent).
        """
        started = self.clock()
        state = self._exchange(tick=0, command=None, give_up=started + startup_timeout)
        if state is None:
            return
        self.node_state = NodeState.RUNNING
        next_status = self.clock()
        while self.running and not self.finished:
            if self.node_state is not NodeState.RUNNING or (
                max_wall_time is not None and self.clock() - started > max_wall_time
            ):
                self.send_zero()
                return
            output = self._control(state)
            command = self._send_command(output.command, True)
            give_up = self.clock() + LOCKSTEP_GIVE_UP
            answer = self._exchange(self.tick, command, give_up=self.clock() + LOCKSTEP_RETRY)
            while answer is None and self.running:
                self.stats.lockstep_retries += 1
                if self.clock() >= give_up:
                    self.stats.stale_faults += 1
                    self._enter_fault(ControllerFault.STALE_STATE)
                    self.send_zero()
                    self._send_status()
                    return
                command = self._send_command(output.command, True)  # same values, new counter
                answer = self._exchange(self.tick, command, give_up=self.clock() + LOCKSTEP_RETRY)
                if self.clock() >= next_status:
                    self._send_status()
                    next_status += STATUS_PERIOD
            if answer is None:
                return
            state = answer
            self.stats.ticks += 1
            if self.clock() >= next_status:
                self._send_status()
                next_status += STATUS_PERIOD

    def _exchange(self, tick: int, command: int | None, give_up: float) -> JointState | None:
        """Send StepSync(tick) naming ``command`` and wait for the joint state answering it.

        Only an answer echoing the latest command is taken: the plant steps only under a
        command it received since its last step, and echoes the last command it received.
        """
        self.state = None
        while self.running:
            step = STEP.encode((command or 0, tick), self.step_counter.next())
            self._send(STEP.frame_id, step)
            resend = min(give_up, self.clock() + LOCKSTEP_RETRY)
            while self.clock() < resend:
                self.drain(timeout=max(0.0, resend - self.clock()))
                state = self.state
                if state is not None and (command is None or state.echo == command):
                    return state
            if self.clock() >= give_up:
                return None
        return None

    def stop(self) -> None:
        self.running = False

    def send_zero(self) -> None:
        """Leave the plant braking: the last word of a controller that stops."""
        self._send_command((0.0, 0.0, 0.0), False)

    # --- results ---------------------------------------------------------------------------------

    def result(self) -> dict[str, object]:
        measures = (
            compute_measures(self.scenario, self.log).as_dict() if len(self.log) > 20 else None
        )
        return {
            "scenario": self.scenario.name,
            "mode": self.scenario.mode.value,
            "clock": self.clock_mode.value,
            "rate_hz": self.scenario.controller.rate_hz,
            "completed": self.finished,
            "state": self.node_state.name,
            "faults": [flag.name for flag in ControllerFault if flag in self.fault],
            "measures": measures,
            "loop": self.stats.summary(self.period),
            "e2e": asdict(self.monitor.counts),
        }


_RECEIVED = {codec.frame_id for codec in (*STATE, PLANT_STATUS, STOP, NODE_COMMAND)}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="controller",
        description="The SCARA controller: runs a scenario at a fixed rate and commands the "
        "plant's joint velocities over CAN.",
    )
    add_node_arguments(parser, "real time at absolute deadlines, or lockstep with the plant")
    parser.add_argument(
        "--mode", choices=[m.value for m in Mode], help="coordination (default: the scenario's)"
    )
    parser.add_argument("--out", type=Path, help="write result JSON and the run log (.npz) here")
    parser.add_argument("--max-wall-time", type=float, help="give up after this many seconds")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    setup = open_node(args, "controller")
    if setup is None:
        return 2
    scenario = setup.scenario.with_mode(Mode(args.mode)) if args.mode else setup.scenario
    node = ControllerNode(setup.bus, scenario, ClockMode(args.clock))
    stop_on_signals(node.stop)
    settle_memory()
    started = time.monotonic()
    try:
        if node.clock_mode is ClockMode.LOCKSTEP:
            node.run_lockstep(max_wall_time=args.max_wall_time)
        else:
            node.run_realtime(args.max_wall_time)
        node.send_zero()
    finally:
        setup.bus.shutdown()
    wall_time = time.monotonic() - started
    result = node.result()
    result["wall_time_s"] = wall_time
    result["realtime_factor"] = node.tick * node.period / wall_time
    result["injected"] = asdict(setup.injector.counts) if setup.injector else None
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "controller_result.json").write_text(json.dumps(result, indent=2) + "\n")
        np.savez_compressed(
            args.out / "controller_log.npz", data=node.log.data, columns=np.array(COLUMNS)
        )
    else:
        print(json.dumps(result, indent=2))
    return 0 if result["completed"] and not result["faults"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
