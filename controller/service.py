"""The controller as a service: idle holding the arm, it takes a task over the wire, runs it on
request, and comes back to idle.

What an operator (the Zenoh bridge, or any CAN tool) can do, each answered with a
ControllerAnswer frame carrying the request's ticket (accepted, or rejected with a reason):

- **set the task** (waypoints, obstacle, mode: the paper's GUI buttons): a task document sent
  over ISO-TP on ScenarioUpload, checked with the same rules as a scenario file, the
  controller's planned-path check included. Nothing is half-applied: a rejected or broken
  transfer leaves the task in force as it was, and a change while a run goes on is refused;
- **run**: the task starts from wherever the arm is: the plan gets an approach segment from
  the arm's position to the first waypoint;
- **stop**: the run ends where it is, and the service holds the arm (zero command);
- **reset**: faults and e-stop cleared, back to idle, the task kept;
- **describe**: the task in force, sent back over ISO-TP on ScenarioDownload.

The task's obstacle is the plant's world too (:mod:`protocol.world`): the service numbers it,
sends it to the plant over ISO-TP (WorldUpload) and again while the plant's PlantStatus shows
another number (a restarted plant); a new obstacle is answered once the plant holds it (or after
:data:`WORLD_WAIT`). A world not yet sent whose number the plant already reports takes the next
number: that world is another service's (a restarted service numbers from 1 again), so the
plant's number is only ever taken for ours once it came from us. A world whose obstacle holds
the arm where it stands is never sent: its task is dropped (a restarted service's start-up task
over an arm that the last one left elsewhere). A run starts only with a plant that is heard,
ready (no e-stop, no fault) and holding the task's world: otherwise it is refused with the
reason, and nothing moves.

A run keeps every rule of the one-shot controller (holds on comms loss, latched fault after
the comms-loss timeout) and, with ``--out``, writes its result and log when it ends.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import can

from controller.node import COMMS_TIMEOUT, ControllerNode
from controller.planner import check_plan
from controller.task_rules import accept, numbered
from protocol.errors import ConfigError
from protocol.kinematics import forward
from protocol.messages import (
    CONTROLLER_ANSWER,
    SCENARIO_DOWNLOAD,
    SCENARIO_UPLOAD,
    WORLD_FLOW,
    WORLD_UPLOAD,
    Answered,
    ControllerFault,
    NodeState,
    PlantFault,
    Reason,
    Request,
    reason_of,
)
from protocol.node import ClockMode
from protocol.scenario import Scenario, Waypoint, encode_task, read_task
from protocol.world import STARTUP_WORLD, World, next_world

APPROACH_SPEED = 0.1
"""m/s: the mean speed of the approach segment to the task's first waypoint."""
MIN_APPROACH = 0.5
"""s: the shortest approach segment."""
ALREADY_THERE = 0.001
"""m: closer than this to the first waypoint, a run needs no approach segment."""
PLANT_HEARD = 0.5
"""s after its last PlantStatus (10 Hz) the plant still counts as there."""
WORLD_RESEND = 0.5
"""s between two sends of a world the plant does not report holding."""
WORLD_WAIT = 1.0
"""s a new obstacle's answer waits at most for the plant to hold it (then it is accepted: the
task is the controller's; a run waits for the world)."""
PLANT_READY = (NodeState.READY, NodeState.RUNNING)
"""Plant states a run may start in (the plant stays running once commanded)."""


class ServiceNode(ControllerNode):
    """The controller process in service mode (see the module docstring)."""

    starts_on_first_state = False

    def __init__(
        self,
        bus: can.BusABC,
        base: Scenario,
        task: Scenario | None = None,
        comms_timeout: float = COMMS_TIMEOUT,
        out: Path | None = None,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.base = base
        self.task = task
        self.out = out
        self.runs = 0
        super().__init__(
            bus,
            task or base,
            ClockMode.REALTIME,
            comms_timeout,
            clock=clock,
            sleep=sleep,
            wall_clock=wall_clock,
        )
        self.transfers = self.add_link(
            SCENARIO_DOWNLOAD.frame_id, SCENARIO_UPLOAD.frame_id, "scenario"
        )
        self.worlds = self.add_link(WORLD_UPLOAD.frame_id, WORLD_FLOW.frame_id, "world")
        self.world = None if task is None else World.of(task, next_world(STARTUP_WORLD))
        """The world of the task in force, as the plant must hold it."""
        self._world_sent = -float("inf")
        self._task_answer: tuple[int, float] | None = None
        """A new obstacle's answer waiting for the plant: (ticket, give up at)."""

    # --- life cycle ----------------------------------------------------------------------

    def on_reset(self) -> None:
        """Faults and e-stop cleared; idle, holding the arm; the task kept."""
        self._last_output = None
        self.monitor.forget()
        self.fault = self.Fault(0)
        self.node_state = NodeState.READY

    @property
    def done(self) -> bool:
        return False  # a service serves until it is stopped

    @property
    def exit_code(self) -> int:
        return 0 if not self.fault else 1

    def on_run_end(self) -> None:
        self._end_run()

    def result(self) -> dict[str, Any]:
        """The last run's result, and how many runs the service made."""
        return super().result() | {"runs": self.runs, "completed": self.runs > 0 and self.finished}

    def _end_run(self) -> None:
        """Back to idle (a run that ended in a fault stays in it); the run's result and log
        written to ``out``, if given."""
        if self.node_state in (NodeState.RUNNING, NodeState.HOLD):
            self.node_state = NodeState.READY
        self.runs += 1
        self.log.info("run %d ended (%s)", self.runs, self.outcome or "stopped")
        if self.out is not None:
            self.out.mkdir(parents=True, exist_ok=True)
            self.save(self.out, self.result())

    # --- requests ------------------------------------------------------------------------

    def on_request(self, request: Any, ticket: int) -> None:
        if request == Request.RESET:
            self.on_reset()
            self._answer(Answered.RESET, ticket, Reason.NONE)
        elif request == Request.STOP:
            if self.node_state in (NodeState.RUNNING, NodeState.HOLD):
                self.send_zero()
                self._end_run()
            self._answer(Answered.STOP, ticket, Reason.NONE)
        elif request == Request.RUN:
            self._answer(Answered.RUN, ticket, self._start_run())
        elif request == Request.DESCRIBE:
            if self.task is None:
                self._answer(Answered.DESCRIBE, ticket, Reason.NO_SCENARIO)
            else:
                self._answer(Answered.DESCRIBE, ticket, Reason.NONE)
                self.transfers.send(encode_task(self.task, ticket))

    def _answer(self, request: Any, ticket: int, reason: Any) -> None:
        record = CONTROLLER_ANSWER.Record(
            Request=request, Ticket=ticket, Accepted=int(reason == Reason.NONE), Reason=reason
        )
        self.send(CONTROLLER_ANSWER, record)
        if reason != Reason.NONE:
            self.log.info("%s refused: %s", request.name.lower(), reason.name.lower())

    def _start_run(self) -> Any:
        """Start the task from where the arm is; the reason if it cannot start."""
        if self.node_state in (NodeState.RUNNING, NodeState.HOLD):
            return Reason.BUSY
        if self.node_state is not NodeState.READY:
            return Reason.FAULTED
        if self.task is None:
            return Reason.NO_SCENARIO
        state = self.state
        if state is None or self.clock() - self._last_fresh > self.comms_timeout:
            return Reason.NO_JOINT_STATE
        refusal = self._plant_refusal()
        if refusal is not None:
            return refusal
        try:
            run, approach = with_approach(self.task, forward(self.task.robot, *state.position))
        except ConfigError:
            return Reason.APPROACH_BLOCKED
        self.prepare(run, approach)
        self.node_state = NodeState.RUNNING
        self.log.info("run %d of %s started", self.runs + 1, self.task.name)
        return Reason.NONE

    # --- tasks over ISO-TP -----------------------------------------------------------------

    def _plant_refusal(self) -> Any:
        """Why the plant cannot take a run now (None: it can)."""
        plant = self.plant
        if self.clock() - plant.heard > PLANT_HEARD:
            self.log.info("run refused: no PlantStatus for %g s", PLANT_HEARD)
            return Reason.PLANT_NOT_READY
        if plant.state not in PLANT_READY or plant.faults & ~PlantFault.COMMAND_TIMEOUT:
            faults = PlantFault(plant.faults)
            self.log.info("run refused: the plant is %s (%s)", plant.state, faults)
            return Reason.PLANT_NOT_READY
        if self.world is not None and plant.world != self.world.number:
            self.log.info(
                "run refused: the plant holds world %d, not %d", plant.world, self.world.number
            )
            return Reason.WORLD_PENDING
        return None

    def serve(self, now: float) -> None:
        """Take the transfers completed since the last tick; keep the plant's world the
        task's."""
        for payload in self.transfers.poll():
            self._on_task(payload)
        self.worlds.poll()
        world = self.world
        if world is None:
            return
        heard = now - self.plant.heard <= PLANT_HEARD
        unsent = self._world_sent == -float("inf")
        if unsent and heard and self.plant.world == world.number:
            world = self.world = replace(world, number=next_world(world.number))
        synced = self.plant.world == world.number
        if not synced and heard and self.node_state in (NodeState.RUNNING, NodeState.HOLD):
            # A plant restarted during the run judges by its start-up world until it holds
            # the task's again: it would see collisions with an obstacle nobody avoids.
            self.log.warning("the plant holds world %d, not the run's", self.plant.world)
            self.enter_fault(ControllerFault.PLANT_FAULT)
        if not synced and heard and now - self._world_sent >= WORLD_RESEND:
            if unsent and self.task is not None and self._holds_the_arm(self.task):
                self._drop_task()
                return
            self.worlds.send(world.encode())
            self._world_sent = now
            self.log.info("world %d sent to the plant", world.number)
        if self._task_answer is not None:
            ticket, give_up = self._task_answer
            if synced or not heard or now >= give_up:
                self._task_answer = None
                self._answer(Answered.SCENARIO, ticket, Reason.NONE)

    def _drop_task(self) -> None:
        """The task whose world was about to be sent holds the arm: dropped, never sent."""
        assert self.task is not None
        self.log.warning("task %s dropped: its obstacle holds the arm", self.task.name)
        self.task = self.world = None
        if self._task_answer is not None:  # accepted before the arm was heard
            self._answer(Answered.SCENARIO, self._task_answer[0], Reason.INSIDE_OBSTACLE)
            self._task_answer = None

    def _on_task(self, payload: bytes) -> None:
        try:
            ticket, document = read_task(payload)
        except ConfigError as error:
            self.log.info("task refused: %s", error)
            self._answer(Answered.SCENARIO, 0, Reason.MALFORMED)
            return
        if self.node_state in (NodeState.RUNNING, NodeState.HOLD):
            self._answer(Answered.SCENARIO, ticket, Reason.BUSY)
            return
        try:
            task = accept(document, self.base)
        except ConfigError as error:
            self.log.info("task refused: %s", error)
            self._answer(Answered.SCENARIO, ticket, reason_of(error))
            return
        if self._holds_the_arm(task):
            self.log.info("task refused: its obstacle stands where the arm is")
            self._answer(Answered.SCENARIO, ticket, Reason.INSIDE_OBSTACLE)
            return
        self.task = task
        self.log.info("task %s set (%d waypoints)", task.name, len(task.waypoints))
        world = self.world
        if world is not None and (task.obstacle, task.tool_radius) == (
            world.obstacle,
            world.tool_radius,
        ):
            self._answer(Answered.SCENARIO, ticket, Reason.NONE)
            return
        self.world = World.of(task, next_world(STARTUP_WORLD if world is None else world.number))
        self._world_sent = -float("inf")
        if self._task_answer is not None:  # the task before, never held: its answer now
            self._answer(Answered.SCENARIO, self._task_answer[0], Reason.NONE)
        self._task_answer = (ticket, self.clock() + WORLD_WAIT)  # answered by serve()

    def _holds_the_arm(self, task: Scenario) -> bool:
        """The task's inflated obstacle holds the tool where the arm stands now: the plant
        would judge it a collision the moment it took the world, and no safe motion leads out
        (an obstacle set on the arm once put the plant in collision)."""
        if self.state is None or task.obstacle is None:
            return False
        return task.obstacle.holds(*forward(task.robot, *self.state.position))


def with_approach(task: Scenario, tcp: tuple[float, float, float]) -> tuple[Scenario, int]:
    """``task`` preceded by a segment from ``tcp`` to its first waypoint (at
    :data:`APPROACH_SPEED`, :data:`MIN_APPROACH` at least), and how many waypoints that added
    (0 when the arm is already there); a timeout the task sets is lengthened by the segment's
    time (the default follows the waypoints). :class:`ConfigError` if that segment is not a
    path."""
    first = task.waypoints[0]
    distance = math.dist(tcp, (first.x, first.y, first.z))
    if distance < ALREADY_THERE:
        return task, 0
    lead = max(MIN_APPROACH, distance / APPROACH_SPEED)
    start = Waypoint(first.t - lead, *tcp)
    timeout = None if task.timeout is None else task.timeout + lead
    run = replace(task, waypoints=(start, *task.waypoints), timeout=timeout)
    try:
        check_plan(run)
    except ConfigError as error:
        raise numbered(error) from error
    return run, 1
