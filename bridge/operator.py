"""The bridge's side of the CAN bus: a participant that listens, and speaks only when told to.

:class:`OperatorNode` adds no frame to the control loop's traffic: it sends nothing on its
own (no status frame), only the commands it is given (a task over ISO-TP, a NodeCommand, an
EmergencyStop). It hears every frame, checks each (E2E, counted), keeps :class:`RobotView`
current, and matches the controller's answers to the requests they answer by ticket.
Driven by the bridge's CAN thread (:meth:`step`); nothing here touches Zenoh.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import can

from bridge.view import VIEWED, Event, RobotView
from protocol.codec import MessageCodec
from protocol.messages import (
    CONTROLLER_ANSWER,
    CONTROLLER_STATUS,
    NODE_COMMAND,
    SCENARIO_DOWNLOAD,
    SCENARIO_UPLOAD,
    STATE_IDS,
    STOP,
    Answered,
    JointStateParts,
    NodeId,
    PlantFault,
    Reason,
    Request,
)
from protocol.node import Node
from protocol.scenario import Scenario, encode_task, parse_task, read_task

ANSWER_TIMEOUT = 2.0
"""s the controller has to answer a request (a task's transfer included)."""


@dataclass(frozen=True, slots=True)
class Answer:
    """The controller's answer to a request, or the bridge's when none came."""

    accepted: bool
    reason: str
    task: Scenario | None = None
    """For ``describe``: the task in force, as the controller sent it back."""


Reply = Callable[[Answer], None]


@dataclass(slots=True)
class Pending:
    request: Any
    deadline: float
    reply: Reply
    task: Scenario | None = None  # a task sent: in force once accepted
    answered: bool = False  # describe: the answer came; the task is on its way


class OperatorNode(Node):
    """The bridge's CAN participant (see the module docstring)."""

    name = "bridge"
    node_id = NodeId.OPERATOR
    status = CONTROLLER_STATUS  # it sends none of its own; this is what it watches most
    listens = (*VIEWED, CONTROLLER_ANSWER)
    Fault = PlantFault  # never raised: the bridge has no faults of its own on the bus

    def __init__(
        self,
        bus: can.BusABC,
        base: Scenario,
        on_event: Callable[[Event, float], None],
        on_joint_state: Callable[[float], None],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(bus, clock)
        self.base = base
        self.view = RobotView(base.robot)
        self.task: Scenario | None = None
        self._on_event = on_event
        self._on_joint_state = on_joint_state
        self._parts = JointStateParts()
        self._pending: dict[int, Pending] = {}
        self._ticket = 0
        self.frames = 0
        self.transfers = self.add_link(
            SCENARIO_UPLOAD.frame_id,
            SCENARIO_DOWNLOAD.frame_id,
            "scenario",
            # only the operator whose describe was answered answers the task's transfer
            asked=lambda: any(pending.answered for pending in self._pending.values()),
        )

    # --- frames in -----------------------------------------------------------------------

    def on_frame(
        self, codec: MessageCodec, counter: int, record: Any, message: can.Message
    ) -> None:
        self.frames += 1
        received = message.timestamp
        if codec.frame_id in STATE_IDS:
            complete = self._parts.add(STATE_IDS.index(codec.frame_id), counter, record)
            if complete is not None:
                self.view.on_joint_state(complete[0], complete[1], received)
                self._on_joint_state(received)
        elif codec is CONTROLLER_ANSWER:
            self._on_answer(record)
        else:
            for event in self.view.on_frame(codec, record, received):
                self._on_event(event, received)

    def emergency_stop(self) -> None:
        """An EmergencyStop on the bus: the bridge only reports it (in the status)."""

    def on_request(self, request: Any, ticket: int) -> None:
        """NodeCommands are for the controller and the plant, not for the bridge."""

    def on_reset(self) -> None:
        """Nothing to reset: the bridge holds no state of its own on the bus."""

    def statuses(self) -> list[tuple[MessageCodec, Any]]:
        return []  # the bridge adds nothing to the bus's cyclic traffic

    # --- requests ------------------------------------------------------------------------

    def set_task(self, task: Scenario, reply: Reply) -> None:
        """Send ``task`` over ISO-TP; ``reply`` gets the controller's answer."""
        ticket = self._next_ticket(Answered.SCENARIO, reply)
        self._pending[ticket].task = task
        self.transfers.send(encode_task(task, ticket))

    def request(self, request: Any, reply: Reply) -> None:
        """A NodeCommand (run, reset, stop, describe) for the controller; a reset for every
        node (an e-stop latched them all), answered by the controller."""
        answered = Answered[Request(request).name]
        ticket = self._next_ticket(answered, reply)
        target = NodeId.ALL if request == Request.RESET else NodeId.CONTROLLER
        record = NODE_COMMAND.Record(
            Command=request, Target=target, Source=NodeId.OPERATOR, Ticket=ticket
        )
        self.send(NODE_COMMAND, record)

    def estop(self) -> None:
        """EmergencyStop: every node brakes and latches (no answer: the status shows it)."""
        self.send(STOP, STOP.Record(Source=NodeId.OPERATOR))

    def _next_ticket(self, request: Any, reply: Reply) -> int:
        self._ticket = self._ticket % 255 + 1
        self._pending[self._ticket] = Pending(request, self.clock() + ANSWER_TIMEOUT, reply)
        return self._ticket

    def _on_answer(self, record: Any) -> None:
        pending = self._pending.get(record.Ticket)
        if pending is None or pending.request != record.Request:
            return  # another operator's, or one we gave up on
        reason = Reason(record.Reason).name.lower()
        if record.Request == Answered.DESCRIBE and record.Accepted:
            pending.answered = True  # the task follows over ISO-TP
            return
        del self._pending[record.Ticket]
        if record.Accepted and pending.task is not None:
            self.task = pending.task
        pending.reply(Answer(bool(record.Accepted), reason))

    # --- the loop ------------------------------------------------------------------------

    def step(self, timeout: float) -> None:
        """Take what the bus brought (waiting up to ``timeout`` for it), finish transfers,
        give up on requests not answered in time."""
        self.drain(timeout)
        for payload in self.transfers.poll():
            self._on_described(payload)
        now = self.clock()
        for ticket, pending in list(self._pending.items()):
            if now > pending.deadline:
                del self._pending[ticket]
                pending.reply(Answer(False, "no_answer"))

    def _on_described(self, payload: bytes) -> None:
        """The task the controller sent back for a describe request."""
        try:
            ticket, document = read_task(payload)
            task = parse_task(document, self.base)
        except Exception as error:  # a bad transfer must not stop the bridge
            self.log.warning("described task unreadable: %s", error)
            return
        pending = self._pending.pop(ticket, None)
        self.task = task
        if pending is not None:
            pending.reply(Answer(True, "none", task))
