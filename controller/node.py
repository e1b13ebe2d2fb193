"""The controller's node: it owns the bus and the fixed-rate loop around the pure
:class:`~controller.control_law.ControlLaw` (the ``controller`` command is :mod:`controller.cli`).

Real time: the loop sleeps to absolute deadlines on the monotonic clock (no spinning: on a
shared machine a spinning loop loses the CPU for whole scheduler slices) and at each tick
takes every frame that arrived, runs one control step on the newest complete, valid joint
state and sends the command. Comms loss, as on a non-real-time OS:

- no new valid joint state for ``STALE_TICKS`` ticks: command zero with Enable = 0 at once
  and HOLD: the plan's clock stops;
- a fresh joint state during a hold: resume from the measured position, the command ramping
  up from zero within the acceleration limit;
- no fresh state for longer than the comms-loss timeout (default 100 ms, like a CANopen
  heartbeat consumer time): latched FAULT until a NodeCommand reset.

Holds are counted and timed, and the run's clock (the log's ``clock`` column) goes on during
them, so a held run shows as slower, never hidden.

Lockstep: per tick it sends the command and a StepSync naming it, then waits for the plant's
answer. A lost or corrupt frame costs a retry, never a wrong step, so the run is
bit-identical to the in-process simulation.

A run ends as :mod:`controller.run_end` says: its task done (back to ready), its timeout
reached on the run's clock, or no safe motion left (latched fault TASK_TIMEOUT or
NO_SAFE_MOTION, braking). A NodeCommand ``reset``
restarts the scenario from the plant's present state; an EmergencyStop latches e-stop until a
reset.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np

from controller.behaviours import TURN_LEFT, TURN_RIGHT
from controller.control_law import ControlLaw, ControlOutput
from controller.loop_stats import LoopStats
from controller.run_end import OUTCOMES, UNWATCHED, RunOutcome, ending, run_end_of
from controller.runlog import COLUMNS, RunLog, row_of
from protocol.codec import MessageCodec
from protocol.errors import ConfigError, EncodeError
from protocol.messages import (
    COMMAND,
    CONTROLLER_STATUS,
    COORDINATION,
    PLANT_STATUS,
    RUN_STATUS,
    STATE,
    STATE_IDS,
    STEP,
    Behaviour,
    ControllerFault,
    ControllerFlag,
    Joints,
    JointStateParts,
    NodeId,
    NodeState,
    PlantFault,
    Side,
    command_record,
)
from protocol.node import ClockMode, Node
from protocol.ops import SCALAR
from protocol.scenario import WAYPOINT_TOLERANCE, Mode, Scenario, scenario_document

STALE_TICKS = 3
"""Ticks without a new valid joint state before the controller holds."""
COMMS_TIMEOUT = 0.1
"""s without a fresh joint state before a hold becomes a latched fault (default)."""
LATE_TOLERANCE = 0.25
"""A tick starting later than this fraction of the period counts as a missed deadline."""
LOCKSTEP_RETRY = 0.005
"""s the controller waits at least for the plant's answer in lockstep before sending again:
the first wait for a tick is the longer of this and twice the usual round trip, and each
further wait for the same tick twice as long, up to LOCKSTEP_RETRY_MAX (a slow host is not
flooded with retries, and a lossy bus still gets many tries before LOCKSTEP_GIVE_UP)."""
LOCKSTEP_RETRY_MAX = 0.1
"""s: the longest wait between two sends of the same lockstep tick."""
LOCKSTEP_GIVE_UP = 1.0
"""s without any answer in lockstep before the controller faults (the plant is gone), unless
the environment variable named by GIVE_UP_VARIABLE sets another. Lockstep stays exact however
long an answer takes, but a plant that answers later than this is taken for a gone one: a host
that can stall the nodes for longer needs a longer bound (in the hil tier's emulated VM, on a
loaded host, the whole guest stopped for 1.25 s and a run faulted, docs/hil.md)."""
LOCKSTEP_STARTUP = 30.0
"""s the controller waits in lockstep for the plant's first answer (it may start before the
plant), unless the environment variable named by STARTUP_VARIABLE sets another."""
GIVE_UP_VARIABLE = "SCARA_LOCKSTEP_GIVE_UP"
STARTUP_VARIABLE = "SCARA_LOCKSTEP_STARTUP"
ZERO: Joints = (0.0, 0.0, 0.0)
_D_MAX = 0.255
"""m: d_L and d_R saturate here on the wire (sensing range 0.2 m by default)."""
_SIDES = {0: Side.NONE, TURN_LEFT: Side.LEFT, TURN_RIGHT: Side.RIGHT}
PREALLOCATED_ROWS = 65536
"""Log rows reserved up front (a longer run's log grows)."""


def lockstep_wait(variable: str, default: float) -> float:
    """s: the environment variable ``variable``'s value if set, else ``default``; a value that
    is not a positive number of seconds is a :class:`ConfigError` naming the variable."""
    text = os.environ.get(variable, "").strip()
    if not text:
        return default
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0.0):
        raise ConfigError(variable, f"{text!r} is not a positive number of seconds")
    return value


@dataclass(slots=True)
class PlantSeen:
    """The plant as its last PlantStatus showed it."""

    state: Any = None
    """NodeState; None before the first PlantStatus."""
    faults: int = 0
    """PlantFault bits."""
    world: int = 0
    heard: float = -float("inf")
    """When it came, on the controller's clock."""


PLANT_STOPS_A_RUN = PlantFault.JOINT_LIMIT | PlantFault.COLLISION | PlantFault.ESTOP
"""Plant faults that end a run under way: the arm no longer follows the commands."""


@dataclass(slots=True)
class JointState:
    position: Joints
    velocity: Joints
    echo: int
    received: float
    """When the last of its frames arrived (the bus's receive time, wall clock)."""


class ControllerNode(Node):
    """The controller's side of the wire around the control law of one scenario."""

    name = "controller"
    node_id = NodeId.CONTROLLER
    status = CONTROLLER_STATUS
    listens = (*STATE, PLANT_STATUS)
    Fault = ControllerFault
    starts_on_first_state = True
    """A run of the scenario starts with the first joint state (the service waits for run)."""

    def __init__(
        self,
        bus: can.BusABC,
        scenario: Scenario,
        clock_mode: ClockMode,
        comms_timeout: float = COMMS_TIMEOUT,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        super().__init__(bus, clock)
        self.period = scenario.controller.period
        if not comms_timeout > STALE_TICKS * self.period:
            raise ConfigError(
                "--comms-timeout",
                f"{comms_timeout:g} s must exceed {STALE_TICKS} ticks "
                f"({STALE_TICKS * self.period:g} s at {scenario.controller.rate_hz:g} Hz)",
            )
        self.scenario = scenario
        self.clock_mode = clock_mode
        self.comms_timeout = comms_timeout
        self.lockstep_give_up = LOCKSTEP_GIVE_UP
        self.lockstep_startup = LOCKSTEP_STARTUP
        if clock_mode is ClockMode.LOCKSTEP:  # read here: a bad value stops the start, named
            self.lockstep_give_up = lockstep_wait(GIVE_UP_VARIABLE, LOCKSTEP_GIVE_UP)
            self.lockstep_startup = lockstep_wait(STARTUP_VARIABLE, LOCKSTEP_STARTUP)
        self.sleep = sleep
        self.wall_clock = wall_clock
        self.stats = LoopStats(self.period)
        """The run's (the service's idle loop's before its first run)."""
        self._run_started = clock()
        self._late_max = 0.0
        self.states_received = 0
        self._seen = 0
        self._quiet_ticks = STALE_TICKS
        self._last_fresh = -float("inf")
        self._hold_started = 0.0
        self._awaiting: dict[int, float] = {}  # command counter -> wall time it was sent
        self._parts = JointStateParts()
        self.state: JointState | None = None
        self.plant = PlantSeen()
        self._round_trip = LOCKSTEP_RETRY / 2.0
        """s from a lockstep command to its answer, smoothed (the first retry waits twice)."""
        self._commands: list[int] = []
        """Lockstep: the counter the plant echoed at the start, then the counter of each
        command sent, in order (see :meth:`_answers`)."""
        self._echoed = 0
        """Lockstep: the command (index in ``_commands``) the last answer echoed, at least."""
        self.ticks_to_run = self.tick = self.slot = 0  # no run prepared yet
        self.outcome: RunOutcome | None = None
        """How the run prepared last ended (None: it has not)."""
        self._next_waypoint = self._approach = 0
        self._last_output: ControlOutput | None = None
        self.log_rows: RunLog | None = None
        """The log of the run prepared last (a service has none before its first run)."""
        self.on_reset()

    def on_reset(self) -> None:
        """Start the scenario again from the next joint state that arrives."""
        self.prepare(self.scenario)
        self.state = None
        self._parts.clear()
        self.monitor.forget()
        self.fault = ControllerFault(0)
        self.node_state = NodeState.READY

    def prepare(self, scenario: Scenario, approach: int = 0) -> None:
        """Make ``scenario`` the one to run, from its start; ``approach`` is how many of its
        first waypoints were added to reach the task (not the task's own)."""
        self.scenario = scenario
        self.end = run_end_of(scenario)
        self.watch = UNWATCHED
        self.ticks_to_run = self.end.end_tick + 1
        """Ticks of a run done on time (a late one goes on, up to its timeout)."""
        self.outcome = None
        self.law = ControlLaw.for_scenario(scenario)
        self.log_rows = RunLog(min(self.ticks_to_run, PREALLOCATED_ROWS))
        self.stats = LoopStats(self.period)
        self._run_started = self.clock()
        self.tick = 0  # control steps taken: the plan's clock
        self.slot = 0  # ticks since the run started, holds and missed slots included
        self._next_waypoint = 0
        self._approach = approach
        self._last_output = None

    # --- frames in -------------------------------------------------------------------------

    def on_frame(
        self, codec: MessageCodec, counter: int, record: Any, message: can.Message
    ) -> None:
        if codec.frame_id in STATE_IDS:
            joint = STATE_IDS.index(codec.frame_id)
            self._on_state_part(joint, counter, record, message.timestamp)
        elif codec is PLANT_STATUS:
            self.plant = PlantSeen(
                NodeState(record.State), record.FaultCode, record.World, self.clock()
            )
            # Only a run under way: a status sent before the plant took a reset can still
            # arrive after the controller took the same reset.
            if record.FaultCode & PLANT_STOPS_A_RUN and self.node_state in (
                NodeState.RUNNING,
                NodeState.HOLD,
            ):
                self.enter_fault(ControllerFault.PLANT_FAULT)

    def _on_state_part(self, joint: int, counter: int, record: Any, received: float) -> None:
        """Collect JointState1-3; a complete, consistent set is the newest joint state."""
        complete = self._parts.add(joint, counter, record)
        if complete is None:
            return
        position, velocity, echo = complete
        self.states_received += 1
        self.state = JointState(position, velocity, echo, received)
        sent = self._awaiting.pop(echo, None)
        if sent is not None:
            self.stats.add_answer(received - sent)

    # --- frames out --------------------------------------------------------------------------

    def _send_command(self, rates: Joints, enable: bool) -> int:
        try:
            return self.send(COMMAND, command_record(rates, enable))
        except EncodeError as error:
            self.log.error("%s", error)
            self.enter_fault(ControllerFault.ENCODE)
            return self.send(COMMAND, command_record(ZERO, False))

    def send_zero(self) -> None:
        """Leave the plant braking: the last word of a controller that stops or holds."""
        self._send_command(ZERO, False)

    def statuses(self) -> list[tuple[MessageCodec, Any]]:
        """For monitors the coordination and the run's progress, then ControllerStatus."""
        flags = ControllerFlag(0)
        if self.clock_mode is ClockMode.LOCKSTEP:
            flags |= ControllerFlag.LOCKSTEP
        if self.scenario.mode is Mode.FUZZY:
            flags |= ControllerFlag.FUZZY
        status = CONTROLLER_STATUS.Record(
            State=self.node_state,
            FaultCode=int(self.fault),
            Flags=int(flags),
            BadFrames=min(self.monitor.counts.bad, 0xFFFF),
            Extra=min(self.stats.deadline_misses, 0xFFFF),
        )
        output = self._last_output
        moving = output is not None and self.node_state is NodeState.RUNNING
        if output is None:
            coordination = COORDINATION.Record(
                Side=Side.NONE, KT=0.0, KC=0.0, Beta=0.0, DLeft=0.0, DRight=0.0
            )
        else:
            measurement = output.measurement
            coordination = COORDINATION.Record(
                Side=_SIDES[self.law.side],
                KT=min(max(output.k_t, 0.0), 1.0),  # a sum of products may be 1 + 1 ulp
                KC=min(max(output.k_c, 0.0), 1.0),
                Beta=measurement.beta,
                DLeft=min(measurement.d_left, _D_MAX),
                DRight=min(measurement.d_right, _D_MAX),
            )
        run = RUN_STATUS.Record(
            Behaviour=_behaviour(output) if moving and output is not None else Behaviour.NONE,
            Holds=min(self.stats.holds, 0xFFFF),
            Waypoint=min(self.waypoints_reached, 0xFF),
            Progress=100
            if self.finished
            else min(99, round(100 * self.tick / max(self.ticks_to_run, 1))),
            LatenessMax=min(round(self._late_max * 1e6), 0xFFFF),
        )
        self._late_max = 0.0
        # The details first: a monitor that sees the state change knows the run's progress.
        return [(COORDINATION, coordination), (RUN_STATUS, run), (CONTROLLER_STATUS, status)]

    # --- one control step ----------------------------------------------------------------------

    def _control(self, state: JointState) -> ControlOutput:
        """One control step; a run that ends at it other than done latches the fault of its
        outcome's name (TASK_TIMEOUT, NO_SAFE_MOTION, NO_PROGRESS)."""
        start = self.scenario.waypoints[0].t
        t = start + self.tick * self.period
        output = self.law.step(t, state.position)
        clock = start + self.slot * self.period
        if self.log_rows is not None:  # always, once a run is prepared
            self.log_rows.append(row_of(t, state.position, state.velocity, output, clock))
        law = self.law.state
        code, self.watch = ending(
            SCALAR, self.end, law.reached, output, state.velocity, self.tick, self.slot, self.watch
        )
        if code:
            self.outcome = OUTCOMES[code - 1]
            if self.outcome is not RunOutcome.DONE:
                self.enter_fault(ControllerFault[self.outcome.name])
        self.tick += 1
        self._last_output = output
        waypoints = self.scenario.waypoints
        if self._next_waypoint < len(waypoints):
            target = waypoints[self._next_waypoint]
            x, y, z = output.tcp
            if math.dist((x, y, z), (target.x, target.y, target.z)) <= WAYPOINT_TOLERANCE:
                self._next_waypoint += 1
        return output

    @property
    def waypoints_reached(self) -> int:
        """Waypoints of the task the TCP came within 2 mm of, in order (an approach segment's
        start, the arm's position when the run began, is not one of the task's)."""
        return max(0, self._next_waypoint - self._approach)

    @property
    def finished(self) -> bool:
        """The run's task is done."""
        return self.outcome is RunOutcome.DONE

    @property
    def done(self) -> bool:
        """The loop has nothing more to do: the run ended (:mod:`controller.run_end`)."""
        return self.outcome is not None

    def serve(self, now: float) -> None:
        """Work of a tick beside control, after the frames were taken (the service's)."""

    def on_run_end(self) -> None:
        """The run ended: idle again once its task is done (another outcome's fault stays
        latched; the next status frame says which)."""
        if self.finished:
            self.node_state = NodeState.READY

    # --- real time -----------------------------------------------------------------------------

    def run_realtime(self, max_wall_time: float | None = None) -> None:
        """Tick at absolute deadlines until the scenario is done, or stopped.

        A tick that starts late still runs; slots missed entirely are skipped (and counted),
        never run back to back.
        """
        start = self.clock()
        deadline = start
        self.send_status_if_due(start)  # ready: the run starts with the first joint state
        while self.running and not self.done:
            if max_wall_time is not None and self.clock() - start > max_wall_time:
                self.log.warning("gave up after %g s (--max-wall-time)", max_wall_time)
                break
            remaining = deadline - self.clock()
            if remaining > 0.0:
                self.sleep(remaining)
            now = self.clock()
            lateness = now - deadline
            self.stats.lateness.add(lateness)
            self._late_max = max(self._late_max, lateness)
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
                if self.node_state in (NodeState.RUNNING, NodeState.HOLD):
                    self.slot += missed

    def realtime_tick(self, now: float) -> None:
        """One real-time tick: take what arrived, check freshness, command, report."""
        self.drain()
        self.serve(now)
        self.stats.loops += 1  # after the requests: the tick that starts a run is the run's
        fresh = self.states_received != self._seen
        self._seen = self.states_received
        if fresh:
            self._quiet_ticks = 0
            self._last_fresh = now
        else:
            self._quiet_ticks += 1
        self._update_link_state(now, fresh)
        state = self.state
        if self.node_state is NodeState.RUNNING and state is not None:
            output = self._control(state)
            if self.node_state is NodeState.RUNNING:  # not ended in a fault
                counter = self._send_command(output.command, True)
                self._awaiting[counter] = self.wall_clock()
                self.stats.ticks += 1
            else:
                self.send_zero()
            if self.outcome is not None:
                self.on_run_end()
        else:
            self.send_zero()
        if self.node_state in (NodeState.RUNNING, NodeState.HOLD):
            self.slot += 1
        self.send_status_if_due(now)

    def _update_link_state(self, now: float, fresh: bool) -> None:
        """READY -> RUNNING on the first state; RUNNING <-> HOLD; HOLD -> FAULT on timeout."""
        if self.node_state is NodeState.READY and fresh and self.starts_on_first_state:
            self.node_state = NodeState.RUNNING
        elif self.node_state is NodeState.RUNNING and self._quiet_ticks >= STALE_TICKS:
            self.node_state = NodeState.HOLD
            self._hold_started = now
            self.stats.holds += 1
            self.log.info("hold: no joint state for %d ticks", self._quiet_ticks)
        elif self.node_state is NodeState.HOLD:
            if fresh:
                self._end_hold(now)
                self.node_state = NodeState.RUNNING
                self.law.resume_from_rest()
                self.log.info("resumed after %.1f ms", 1e3 * (now - self._hold_started))
            elif now - self._last_fresh > self.comms_timeout:
                self._end_hold(now)
                self.enter_fault(ControllerFault.STALE_STATE)

    def _end_hold(self, now: float) -> None:
        held = now - self._hold_started
        self.stats.hold_time += held
        self.stats.longest_hold = max(self.stats.longest_hold, held)

    # --- lockstep --------------------------------------------------------------------------------

    def run_lockstep(
        self,
        startup_timeout: float | None = None,
        max_wall_time: float | None = None,
        give_up: float | None = None,
    ) -> None:
        """Step the plant tick by tick; a lost answer is asked for again.

        If no answer comes for ``give_up`` s (default: ``lockstep_give_up``, LOCKSTEP_GIVE_UP
        or its environment variable's) the plant is taken as gone: the controller sends zero
        with Enable = 0, goes to fault and returns; the plant's first answer may take
        ``startup_timeout`` s (default: ``lockstep_startup``). A fault, an e-stop or a reset
        received meanwhile also ends the run (zero sent).
        """
        if startup_timeout is None:
            startup_timeout = self.lockstep_startup
        if give_up is None:
            give_up = self.lockstep_give_up
        started = self.clock()
        self.send_status_if_due(started)  # ready, until the plant answers
        state = self._exchange(0, None, give_up=started + startup_timeout)
        if state is None:
            return
        # Number the commands on from the counter the plant echoes now (0 from a new plant):
        # the first is then not that counter, which late answers to the start's StepSyncs echo.
        while self.next_counter(COMMAND) != state.echo:
            pass
        self._commands = [state.echo]
        self._echoed = 0
        self.node_state = NodeState.RUNNING
        while self.running and not self.done:
            if self.node_state is not NodeState.RUNNING or (
                max_wall_time is not None and self.clock() - started > max_wall_time
            ):
                self.send_zero()
                return
            output = self._control(state)
            self.slot += 1
            if self.node_state is not NodeState.RUNNING:  # ended in a fault
                break
            answer = self._exchange(self.tick, output.command, self.clock() + give_up)
            if answer is None:
                if self.running and self.node_state is NodeState.RUNNING:
                    self.enter_fault(ControllerFault.STALE_STATE)
                self.send_zero()
                self.send_status_if_due(self.clock())
                return
            state = answer
            self.stats.ticks += 1
        if self.done:
            if not self.finished:
                self.send_zero()
            self.on_run_end()
            self.send_status_if_due(self.clock())

    def _exchange(self, tick: int, rates: Joints | None, give_up: float) -> JointState | None:
        """Send the command ``rates`` and a StepSync(tick) naming it, together, and wait for
        the joint state answering it; after LOCKSTEP_RETRY without one, send both again (the
        same values under new counters), each wait longer (see LOCKSTEP_RETRY), until ``give_up``.
        ``rates`` None: StepSync alone, which the plant answers without stepping (the start).

        An answer to any of the commands sent for this tick is taken: they all carry the same
        rates, and the plant steps once per tick whichever of them it stepped under. Waiting
        only for the latest would never end on a host whose round trip is longer than the
        wait: each answer would arrive just after the next retry made it old. Which command an
        answer is to, its echo tells together with the order of the answers (:meth:`_answers`).
        """
        self.state = None
        first = len(self._commands)
        wait = min(max(LOCKSTEP_RETRY, 2.0 * self._round_trip), LOCKSTEP_RETRY_MAX)
        first_sent = self.clock()
        while self.running:
            frames = []
            command = 0
            if rates is not None:
                command = self.next_counter(COMMAND)
                self._commands.append(command)
                frames.append((COMMAND, command_record(rates), command))
            step = STEP.Record(CommandCounter=command, Tick=tick)
            frames.append((STEP, step, self.next_counter(STEP)))
            try:
                self.send_together(frames)
            except EncodeError as error:
                self.log.error("%s", error)
                self.enter_fault(ControllerFault.ENCODE)
                return None
            self.send_status_if_due(self.clock())
            resend = min(give_up, self.clock() + wait)
            wait = min(2.0 * wait, LOCKSTEP_RETRY_MAX)
            while True:  # read what came at least once, even after a stall of this process
                self.drain(timeout=max(0.0, resend - self.clock()))
                state = self.state
                if state is not None and (rates is None or self._answers(state.echo, first)):
                    self._round_trip += 0.1 * (self.clock() - first_sent - self._round_trip)
                    return state
                self.state = None
                if self.clock() >= resend:
                    break
            if self.clock() >= give_up:
                return None
            if rates is not None:
                self.stats.lockstep_retries += 1
        return None

    def _answers(self, echo: int, first: int) -> bool:
        """Whether a joint state echoing the command counter ``echo`` answers this tick, whose
        first command is ``_commands[first]``.

        The plant takes frames in the order they were sent and echoes the last command it
        took, so an answer echoes a command at or after the one the previous answer echoed:
        the first such command with this counter, if it is one of this tick's, makes the answer
        this tick's. If it is an earlier one, the answer may be a late one to an earlier tick
        (the plant answers a StepSync repeated after it had answered; at the start, before any
        command, it echoes 0, the counter of a first command numbered from 0). The counter
        alone would take such an answer for this tick's: counters repeat every 16 commands,
        and a tick retried for long reuses them all.
        """
        for index in range(self._echoed, len(self._commands)):
            if self._commands[index] == echo:
                self._echoed = index
                return index >= first
        return False  # none of this run's commands since: not an answer to them

    # --- results ---------------------------------------------------------------------------------

    def finish(self) -> None:
        self.send_zero()

    def result(self) -> dict[str, Any]:
        run_time = max(self.clock() - self._run_started, 1e-9)
        return super().result() | {
            "scenario": self.scenario.name,
            "scenario_document": scenario_document(self.scenario),
            "mode": self.scenario.mode.value,
            "clock": self.clock_mode.value,
            "rate_hz": self.scenario.controller.rate_hz,
            "completed": self.finished,
            "outcome": self.outcome or (RunOutcome.CUT_SHORT if self.tick else None),
            "loop": self.stats.summary(),
            "realtime_factor": self.tick * self.period / run_time,
        }

    def save(self, out: Path, result: dict[str, Any]) -> None:
        super().save(out, result)
        if self.log_rows is not None:
            np.savez_compressed(
                out / "controller_log.npz", data=self.log_rows.data, columns=np.array(COLUMNS)
            )

    @property
    def exit_code(self) -> int:
        return 0 if self.finished and not self.fault else 1


def _behaviour(output: ControlOutput) -> Any:
    """Which behaviour the blend of the last step came from (eq. 30's weights)."""
    if output.k_c == 0.0:
        return Behaviour.TRACKING
    if output.k_t == 0.0:
        return Behaviour.AVOIDING
    return Behaviour.BLENDED
