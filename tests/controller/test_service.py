"""The controller service and the bridge's operator node tested against each other over
python-can's in-process ``virtual`` bus (canopen-style), with the joint state sent by the
test: tasks over ISO-TP, run, stop, reset, describe, and nothing half-applied.

Where a test needs a transfer the operator node would never send (a malformed or cut-off
task), it speaks ISO-TP itself with its own :class:`IsoTpLink`, as any CAN tool could.
"""

from __future__ import annotations

import itertools
import json
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import can
import pytest
from support import SLOWDOWN, FakeClock, frame

from bridge.operator import Answer, OperatorNode
from controller.service import ServiceNode, with_approach
from protocol.codec import WIRE
from protocol.errors import ConfigError
from protocol.isotp_link import PARAMS, IsoTpLink
from protocol.kinematics import forward
from protocol.messages import (
    CONTROLLER_ANSWER,
    SCENARIO_DOWNLOAD,
    SCENARIO_UPLOAD,
    STATE,
    Answered,
    NodeState,
    Reason,
    Request,
)
from protocol.scenario import Scenario, encode_task, load_scenario, parse_task, task_document

REFERENCE = load_scenario("reference")
BASE = Scenario("service", (), None)
TASK = parse_task(task_document(REFERENCE), BASE)
_channels = itertools.count()


@dataclass
class Rig:
    """A service, an operator node and the test's own bus: the plant's joint state, and
    transfers of the test's own (:attr:`tool`)."""

    service: ServiceNode
    operator: OperatorNode
    plant: can.BusABC
    clock: FakeClock
    tool: IsoTpLink = field(init=False)
    answers: list[Answer] = field(default_factory=list)
    tool_answers: list[Any] = field(default_factory=list)
    counter: int = 0

    def __post_init__(self) -> None:
        self.tool = IsoTpLink(self.plant.send, SCENARIO_UPLOAD.frame_id, SCENARIO_DOWNLOAD.frame_id)

    def step(self, ticks: int = 1) -> None:
        """``ticks`` control periods: a joint state, then both nodes' loops and the tool's."""
        for _ in range(ticks):
            self.send_state()
            self.clock.now += self.service.period
            self.service.realtime_tick(self.clock.now)
            self.operator.step(0.0)
            while (message := self.plant.recv(timeout=0.0)) is not None:
                if message.arbitration_id == SCENARIO_DOWNLOAD.frame_id:
                    self.tool.feed(message)
                elif message.arbitration_id == CONTROLLER_ANSWER.frame_id:
                    self.tool_answers.append(WIRE.decode(message.arbitration_id, message.data)[2])
            self.tool.poll()

    def send_state(self) -> None:
        position = REFERENCE.initial_joints()
        for codec, joint_position in zip(STATE, position, strict=True):
            record = codec.Record(CommandEcho=0, Position=joint_position, Velocity=0.0)
            self.plant.send(frame(codec.frame_id, codec.encode(record, self.counter)))
        self.counter = (self.counter + 1) % 16

    def ask(self, what: Request | Scenario, ticks: int = 50) -> Answer:
        """Send a request (or a task) from the operator node; step until it is answered."""
        before = len(self.answers)
        if isinstance(what, Scenario):
            self.operator.set_task(what, self.answers.append)
        else:
            self.operator.request(what, self.answers.append)
        self.step_until(lambda: len(self.answers) > before, ticks, f"an answer to {what!r}")
        return self.answers[-1]

    def upload(self, payload: bytes, ticks: int = 50) -> Any:
        """A transfer of the test's own; the ControllerAnswer record it gets."""
        before = len(self.tool_answers)
        self.tool.send(payload)
        self.step_until(lambda: len(self.tool_answers) > before, ticks, "an answer to the upload")
        return self.tool_answers[-1]

    def step_until(self, condition: Callable[[], bool], ticks: int, what: str) -> None:
        for _ in range(ticks):
            self.step()
            if condition():
                return
        raise AssertionError(f"no {what} in {ticks} ticks")


@pytest.fixture
def rig() -> Iterator[Rig]:
    channel = f"service-{next(_channels)}"
    buses = [can.Bus(interface="virtual", channel=channel) for _ in range(3)]
    clock = FakeClock()
    service = ServiceNode(buses[0], BASE, clock=clock, sleep=lambda seconds: None)
    operator = OperatorNode(buses[1], BASE, lambda *event: None, lambda received: None, clock=clock)
    yield Rig(service, operator, buses[2], clock)
    for bus in buses:
        bus.shutdown()


def document_of(task: Scenario, ticket: int, edit: Callable[[dict[str, Any]], None]) -> bytes:
    document = {"ticket": ticket} | task_document(task)
    edit(document)
    return json.dumps(document).encode()


def test_a_service_comes_up_idle_and_refuses_to_run_without_a_task(rig: Rig) -> None:
    rig.step(5)
    assert rig.service.node_state is NodeState.READY
    assert rig.ask(Request.RUN) == Answer(False, "no_scenario")
    assert rig.ask(Request.DESCRIBE) == Answer(False, "no_scenario")


def test_a_task_sent_over_isotp_is_accepted_and_described_back(rig: Rig) -> None:
    assert len(encode_task(TASK, 1)) > 7  # more than a single frame: segmented
    assert rig.ask(TASK) == Answer(True, "none")
    assert rig.service.task == TASK
    assert rig.operator.task == TASK
    rig.operator.task = None
    described = rig.ask(Request.DESCRIBE)
    assert described == Answer(True, "none", TASK)
    assert rig.operator.task == TASK


@pytest.mark.parametrize(
    ("edit", "reason"),
    [
        (lambda d: d["waypoints"][1].update(x=2.0), Reason.UNREACHABLE),
        (lambda d: d["waypoints"][2].update(x=0.455, y=-0.01), Reason.INSIDE_OBSTACLE),
        (lambda d: d.update(settle_time=-1.0), Reason.BAD_FIELD),
        (lambda d: d.update(colour="red"), Reason.BAD_FIELD),
        (lambda d: d.update(ticket="seven"), Reason.MALFORMED),
    ],
    ids=["unreachable", "inside-obstacle", "bad-value", "unknown-field", "bad-ticket"],
)
def test_a_task_the_rules_refuse_leaves_the_task_in_force(
    rig: Rig, edit: Callable[[dict[str, Any]], None], reason: Any
) -> None:
    assert rig.ask(TASK).accepted
    answer = rig.upload(document_of(moved(TASK, -0.02), 9, edit))
    assert (answer.Request, answer.Accepted, answer.Reason) == (Answered.SCENARIO, 0, reason)
    assert rig.service.task == TASK


def test_a_transfer_cut_off_midway_changes_nothing_and_the_next_one_goes_through(
    rig: Rig,
) -> None:
    assert rig.ask(TASK).accepted
    payload = encode_task(moved(TASK, -0.02), 5)
    sent: list[can.Message] = []
    cut = IsoTpLink(sent.append, SCENARIO_UPLOAD.frame_id, SCENARIO_DOWNLOAD.frame_id)
    cut.send(payload)
    cut.poll()  # the first frame only: then the sender goes silent
    assert len(sent) == 1 and sent[0].data[0] >> 4 == 1  # an ISO-TP first frame
    rig.plant.send(sent[0])
    errors = rig.service.transfers.errors
    deadline = time.monotonic() + PARAMS["rx_consecutive_frame_timeout"] / 1000 + SLOWDOWN
    while rig.service.transfers.errors == errors and time.monotonic() < deadline:
        rig.step()
        time.sleep(0.01)  # can-isotp times a transfer out on its own (real) clock
    assert rig.service.transfers.errors == errors + 1
    assert rig.service.task == TASK
    again = moved(TASK, -0.02)
    assert rig.ask(again) == Answer(True, "none")
    assert rig.service.task == again


def test_a_run_starts_from_where_the_arm_is_and_a_change_while_running_is_refused(
    rig: Rig,
) -> None:
    away = moved(TASK, -0.05)  # the arm stands at the reference's first waypoint, 5 cm off
    assert rig.ask(away).accepted
    assert rig.ask(Request.RUN) == Answer(True, "none")
    assert rig.service.node_state is NodeState.RUNNING
    assert rig.ask(TASK) == Answer(False, "busy")
    assert rig.ask(Request.RUN) == Answer(False, "busy")
    assert rig.service.task == away
    assert rig.ask(Request.STOP) == Answer(True, "none")
    assert rig.service.node_state is NodeState.READY
    assert rig.service.runs == 1
    assert rig.ask(TASK).accepted  # idle again: changes are taken


def test_each_run_reports_only_its_own_loop_statistics(rig: Rig) -> None:
    """The service's second run of the task reports its own ticks, not the two runs' sum."""
    assert rig.ask(TASK).accepted
    rig.step(20)  # idle ticks before the first run: in no run's statistics
    for run in (1, 2):
        assert rig.ask(Request.RUN) == Answer(True, "none")
        ticks = rig.service.ticks_to_run
        rig.step_until(
            lambda: rig.service.node_state is not NodeState.RUNNING, ticks, f"the end of run {run}"
        )
        loop = rig.service.result()["loop"]
        assert rig.service.runs == run
        assert loop["ticks"] == ticks, loop
        assert loop["loops"] == ticks, loop  # the tick that took the request is the first
        rig.step(20)


def test_a_run_needs_a_fresh_joint_state(rig: Rig) -> None:
    assert rig.ask(TASK).accepted
    rig.clock.now += 1.0  # the plant went quiet: the last state is old
    rig.service.realtime_tick(rig.clock.now)
    rig.operator.request(Request.RUN, rig.answers.append)
    rig.clock.now += rig.service.period
    rig.service.realtime_tick(rig.clock.now)
    rig.operator.step(0.0)
    assert rig.answers[-1] == Answer(False, "no_joint_state")


def test_an_estop_latches_until_reset_and_the_task_survives_it(rig: Rig) -> None:
    assert rig.ask(TASK).accepted
    rig.operator.estop()
    rig.step(2)
    assert rig.service.node_state is NodeState.ESTOP
    assert rig.ask(Request.RUN) == Answer(False, "faulted")
    assert rig.ask(Request.RESET) == Answer(True, "none")
    assert rig.service.node_state is NodeState.READY
    assert rig.ask(Request.RUN) == Answer(True, "none")


def test_an_unanswered_request_times_out_with_no_answer(rig: Rig) -> None:
    rig.operator.request(Request.RUN, rig.answers.append)
    rig.clock.now += 3.0  # the service is not stepped: it never answers
    rig.operator.step(0.0)
    assert rig.answers == [Answer(False, "no_answer")]


def test_the_approach_segment_leads_from_the_arm_to_the_first_waypoint() -> None:
    first = TASK.waypoints[0]
    tcp = (first.x - 0.1, first.y, first.z)
    run, added = with_approach(TASK, tcp)
    assert added == 1
    assert (run.waypoints[0].x, run.waypoints[0].y, run.waypoints[0].z) == pytest.approx(tcp)
    assert run.waypoints[1:] == TASK.waypoints
    assert first.t - run.waypoints[0].t >= 0.5
    at_start = forward(TASK.robot, *TASK.initial_joints())
    assert with_approach(TASK, at_start) == (TASK, 0)
    with pytest.raises(ConfigError):
        with_approach(TASK, (2.0, 0.0, 0.2))  # from out of reach: no path


def moved(task: Scenario, dx: float) -> Scenario:
    document = task_document(task)
    for waypoint in document["waypoints"]:
        waypoint["x"] += dx
    return parse_task(document, BASE)
