"""The controller service, the bridge's operator node and the plant tested against each other
over python-can's in-process ``virtual`` bus (canopen-style), on a clock the test moves: tasks
over ISO-TP, the plant's world following the task, run, stop, reset, describe, and nothing
half-applied.

Where a test needs a transfer the operator node would never send (a malformed or cut-off
task), it speaks ISO-TP itself with its own :class:`IsoTpLink`, as any CAN tool could. A
listener that sends nothing (the recorder's :class:`TaskInForce`) follows them on a bus of its
own.
"""

from __future__ import annotations

import itertools
import json
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import can
import pytest
from support import LATE_DETOUR, SLOWDOWN, FakeClock

from bridge.operator import Answer, OperatorNode
from controller.service import ServiceNode, with_approach
from plant_sim.node import PlantNode
from protocol.codec import WIRE
from protocol.errors import ConfigError
from protocol.isotp_link import PARAMS, IsoTpLink
from protocol.kinematics import forward
from protocol.messages import (
    CONTROLLER_ANSWER,
    SCENARIO_DOWNLOAD,
    SCENARIO_UPLOAD,
    Answered,
    ControllerFault,
    NodeState,
    PlantFault,
    Reason,
    Request,
)
from protocol.node import ClockMode
from protocol.scenario import (
    TIMEOUT_ALLOWANCE,
    Scenario,
    encode_task,
    load_scenario,
    parse_task,
    task_document,
)
from recorder.tasks import TASK_IDS, TaskInForce

REFERENCE = load_scenario("reference")
BASE = Scenario("service", (), None)
TASK = parse_task(task_document(REFERENCE), BASE)
_channels = itertools.count()


@dataclass
class Rig:
    """A service, an operator node, a plant (started with the reference scenario, the arm at
    its first waypoint) and the test's own bus (:attr:`bus`), for transfers of its own
    (:attr:`tool`)."""

    service: ServiceNode
    operator: OperatorNode
    plant: PlantNode
    bus: can.BusABC
    clock: FakeClock
    tool: IsoTpLink = field(init=False)
    answers: list[Answer] = field(default_factory=list)
    tool_answers: list[Any] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.tool = IsoTpLink(self.bus.send, SCENARIO_UPLOAD.frame_id, SCENARIO_DOWNLOAD.frame_id)

    def step(self, ticks: int = 1) -> None:
        """``ticks`` control periods: the service's tick, the plant's answer and its period,
        the operator's loop and the tool's."""
        for _ in range(ticks):
            self.clock.now += self.service.period
            self.service.realtime_tick(self.clock.now)
            self.run_plant()
            self.operator.step(0.0)
            while (message := self.bus.recv(timeout=0.0)) is not None:
                if message.arbitration_id == SCENARIO_DOWNLOAD.frame_id:
                    self.tool.feed(message)
                elif message.arbitration_id == CONTROLLER_ANSWER.frame_id:
                    self.tool_answers.append(WIRE.decode(message.arbitration_id, message.data)[2])
            self.tool.poll()

    def run_plant(self) -> None:
        """One pass of the plant's loop at the rig's time."""
        self.plant.drain()
        self.plant.take_worlds()
        self.plant.on_period(self.clock.now)
        self.plant.send_status_if_due(self.clock.now)

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
    buses = [can.Bus(interface="virtual", channel=channel) for _ in range(4)]
    clock = FakeClock()
    service = ServiceNode(buses[0], BASE, clock=clock, sleep=lambda seconds: None)
    operator = OperatorNode(buses[1], BASE, lambda *event: None, lambda received: None, clock=clock)
    plant = PlantNode(buses[2], REFERENCE, ClockMode.REALTIME, clock=clock)
    yield Rig(service, operator, plant, buses[3], clock)
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
        (lambda d: d["waypoints"][2].update(x=0.455, y=0.045), Reason.NEAR_OBSTACLE),
        (lambda d: d["waypoints"][1].update(t=0.3), Reason.TOO_FAST),
        (
            lambda d: d["obstacle"].update(long_diameter=0.9, short_diameter=0.1),
            Reason.NO_WAY_ROUND,  # 15: once outside the signal's range, it could not be said
        ),
    ],
    ids=[
        "unreachable",
        "inside-obstacle",
        "bad-value",
        "unknown-field",
        "bad-ticket",
        "near-obstacle",
        "too-fast",
        "no-way-round",
    ],
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
    rig.bus.send(sent[0])
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


class Listener:
    """:class:`TaskInForce` on a bus of its own beside the rig's: every task that came into
    force, as it heard them."""

    def __init__(self, rig: Rig) -> None:
        self.bus = can.Bus(interface="virtual", channel=rig.bus.channel_id)
        self.tasks = TaskInForce(BASE)
        self.in_force: list[Scenario] = []

    def hear(self) -> list[Scenario]:
        while (message := self.bus.recv(timeout=0.0)) is not None:
            if message.arbitration_id in TASK_IDS:
                task = self.tasks.on_transfer_frame(message)
            elif message.arbitration_id == CONTROLLER_ANSWER.frame_id:
                task = self.tasks.on_answer(WIRE.decode(message.arbitration_id, message.data)[2])
            else:
                continue
            if task is not None:
                self.in_force.append(task)
        return self.in_force


def test_a_listener_follows_the_task_in_force_and_never_a_refused_one(rig: Rig) -> None:
    listener = Listener(rig)
    assert rig.ask(TASK).accepted
    assert listener.hear() == [TASK]
    refused = moved(TASK, -0.02)
    answer = rig.upload(document_of(refused, 9, lambda d: d["waypoints"][1].update(x=2.0)))
    assert answer.Reason == Reason.UNREACHABLE
    assert rig.ask(Request.RUN).accepted
    assert rig.ask(refused) == Answer(False, "busy")
    assert listener.hear() == [TASK]  # neither refused task came into force
    assert rig.ask(Request.STOP).accepted
    assert rig.ask(refused).accepted
    assert listener.hear() == [TASK, refused]
    assert listener.tasks.unreadable == 1  # the unreachable one: the controller's rules too

    late = Listener(rig)  # started after the task was set: the controller's describe tells it
    assert rig.ask(Request.DESCRIBE) == Answer(True, "none", refused)
    assert late.hear() == [refused]
    listener.bus.shutdown()
    late.bus.shutdown()


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
    rig.service.realtime_tick(rig.clock.now)  # the plant's last answer taken
    rig.clock.now += 1.0  # then the plant went quiet: the last state is old
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


def test_a_reset_clears_the_plants_estop_too(rig: Rig) -> None:
    """An e-stop latches every node; the operator's reset clears every node (it once reached
    the controller only, and the plant stayed in e-stop)."""
    assert rig.ask(TASK).accepted
    rig.operator.estop()
    rig.step(2)
    assert rig.plant.node_state is NodeState.ESTOP
    assert rig.ask(Request.RESET) == Answer(True, "none")
    rig.step(2)
    assert rig.plant.node_state is NodeState.READY
    assert not rig.plant.fault


def test_no_run_while_the_plant_is_in_estop_or_faulted_and_nothing_moves(rig: Rig) -> None:
    """A run the plant cannot follow is refused with the reason (it was once accepted and
    reported finished, the arm never having moved)."""
    assert rig.ask(moved(TASK, -0.05)).accepted
    rig.plant.emergency_stop()  # the plant alone: an e-stop the controller did not hear
    rig.step(2)
    assert rig.ask(Request.RUN) == Answer(False, "plant_not_ready")
    assert rig.service.node_state is NodeState.READY
    assert rig.plant.model.velocity == (0.0, 0.0, 0.0)
    rig.plant.on_reset()
    rig.plant.enter_fault(PlantFault.JOINT_LIMIT)
    rig.step(2)
    assert rig.ask(Request.RUN) == Answer(False, "plant_not_ready")
    rig.plant.on_reset()
    rig.step(2)
    assert rig.ask(Request.RUN) == Answer(True, "none")


def test_a_plant_fault_during_a_run_ends_it_in_a_fault(rig: Rig) -> None:
    assert rig.ask(moved(TASK, -0.05)).accepted
    assert rig.ask(Request.RUN) == Answer(True, "none")
    rig.step(10)
    rig.plant.emergency_stop()
    rig.step(60)  # the plant's next status, at most 100 ms later
    assert rig.service.node_state is NodeState.FAULT
    assert rig.service.fault & ControllerFault.PLANT_FAULT


def test_a_run_not_done_by_its_timeout_ends_in_task_timeout_until_a_reset(rig: Rig) -> None:
    """A task a detour makes late, its timeout as short as its plan: the run ends in the
    fault, writes its result as a run that timed out, and holds the arm until a reset."""
    late = load_scenario(LATE_DETOUR)
    task = parse_task(task_document(late) | {"timeout": late.duration}, BASE)
    assert rig.ask(task).accepted
    assert rig.ask(Request.RUN) == Answer(True, "none")
    limit = round(rig.service.scenario.time_limit / rig.service.period)
    rig.step_until(lambda: rig.service.node_state is not NodeState.RUNNING, limit + 1, "end")
    assert rig.service.node_state is NodeState.FAULT
    assert rig.service.fault == ControllerFault.TASK_TIMEOUT
    assert rig.service.tick == limit + 1
    result = rig.service.result()
    assert result["runs"] == 1 and result["outcome"] == "task_timeout"
    assert not result["completed"] and rig.service.exit_code == 1
    assert rig.ask(Request.RUN) == Answer(False, "faulted")
    assert rig.ask(Request.RESET).accepted
    assert rig.ask(Request.RUN) == Answer(True, "none")


def test_the_plant_judges_collisions_by_the_obstacle_of_the_task_in_force(rig: Rig) -> None:
    """The task without the obstacle the plant started with, its way straight through where
    that obstacle stands: the run completes, and the plant saw no collision (it once judged by
    its start-up scenario's obstacle, faulted, and went back to fault after every reset)."""
    document = task_document(TASK)
    del document["obstacle"]
    through = parse_task(document, BASE)
    assert rig.ask(through) == Answer(True, "none")
    assert rig.plant.world.number == rig.service.world.number != 0  # held before the answer
    assert rig.plant.obstacle is None
    assert rig.ask(Request.RUN) == Answer(True, "none")
    rig.step_until(
        lambda: rig.service.node_state is not NodeState.RUNNING, rig.service.ticks_to_run, "end"
    )
    assert rig.service.node_state is NodeState.READY
    assert rig.service.waypoints_reached == len(through.waypoints)
    assert rig.plant.stats.collisions == 0 and not rig.plant.fault
    assert rig.ask(TASK).accepted  # the obstacle back: the plant holds it again
    assert rig.plant.obstacle == TASK.obstacle.grown(TASK.tool_radius - TASK.obstacle.inflation)


def test_an_obstacle_set_where_the_arm_stands_is_refused_and_the_plant_sees_no_collision(
    rig: Rig,
) -> None:
    """An obstacle whose inflated section holds the tool where the arm stands (at the
    reference's first waypoint), its waypoints elsewhere: refused, the world unchanged. It was
    once accepted, and the plant, given the world, judged the arm in collision at once (found
    by scara-soak, seed 1: the operator's next task set its obstacle over the arm)."""
    assert rig.ask(TASK).accepted
    rig.step(5)  # the service has the arm's joint state
    world = rig.plant.world.number
    first = REFERENCE.waypoints[0]
    document = task_document(TASK)
    document["waypoints"] = document["waypoints"][1:]
    document["obstacle"] |= {
        "x": first.x, "y": first.y, "long_diameter": 0.04, "short_diameter": 0.03,
    }  # fmt: skip
    on_the_arm = parse_task(document, BASE)
    assert rig.ask(on_the_arm) == Answer(False, "inside_obstacle")
    assert rig.service.task == TASK
    rig.step(20)
    assert rig.plant.world.number == world and not rig.plant.fault
    assert rig.plant.stats.collisions == 0


def test_a_restarted_plant_gets_the_world_again_and_a_plant_without_it_runs_nothing(
    rig: Rig,
) -> None:
    document = task_document(TASK)
    document["obstacle"]["x"] = 0.2  # another world than the plant's scenario file
    task = parse_task(document, BASE)
    assert rig.ask(task).accepted
    number = rig.service.world.number
    assert rig.plant.world.number == number
    rig.plant = PlantNode(rig.plant.bus, REFERENCE, ClockMode.REALTIME, clock=rig.clock)
    assert rig.plant.world.number == 0  # restarted: its scenario file's world
    rig.step(round(0.6 / rig.service.period))  # a status, then the world sent again
    assert rig.plant.world.number == number
    assert rig.plant.obstacle == task.obstacle.grown(task.tool_radius - task.obstacle.inflation)
    rig.plant = PlantNode(rig.plant.bus, REFERENCE, ClockMode.REALTIME, clock=rig.clock)
    rig.plant.take_worlds = lambda: None  # a plant that never takes the world
    rig.step(round(0.3 / rig.service.period))  # its status counters taken up (two in a row)
    assert rig.ask(Request.RUN) == Answer(False, "world_pending")


def test_a_plant_restarted_during_a_run_ends_it_in_a_plant_fault(rig: Rig) -> None:
    """The new plant judges by its start-up world until it holds the task's again: the run
    ended there (it once went on, and the plant saw a collision with an obstacle the
    controller did not avoid; found by scara-soak --minutes 10 --seed 1 at 169.8 s)."""
    document = task_document(TASK)
    document["obstacle"]["x"] = 0.2  # another world than the plant's scenario file
    assert rig.ask(parse_task(document, BASE)).accepted
    assert rig.ask(Request.RUN) == Answer(True, "none")
    rig.step(50)
    assert rig.service.node_state is NodeState.RUNNING
    rig.plant = PlantNode(rig.plant.bus, REFERENCE, ClockMode.REALTIME, clock=rig.clock)
    rig.step_until(lambda: rig.service.node_state is NodeState.FAULT, 200, "the fault")
    assert ControllerFault.PLANT_FAULT in rig.service.fault


def restart_service(rig: Rig, task: Scenario) -> None:
    """The service killed and started again on its bus, with ``task`` as its start-up task
    (``scara-run --serve SCENARIO``); the plant goes on as it was."""
    rig.service = ServiceNode(
        rig.service.bus, BASE, task, clock=rig.clock, sleep=lambda seconds: None
    )


def test_a_restarted_service_sends_its_world_though_the_plant_holds_the_same_number(
    rig: Rig,
) -> None:
    """The plant holds world 1 of the service before; the new one numbers its start-up world
    1 too. It took the plant's number for its own and never sent its world: the plant judged
    by an obstacle the controller did not avoid (reported by scara-soak, seed 1)."""
    document = task_document(TASK)
    document["obstacle"]["x"] = 0.2
    assert rig.ask(parse_task(document, BASE)).accepted
    assert rig.plant.world.number == 1
    restart_service(rig, TASK)
    rig.step(round(1.0 / rig.service.period))
    assert rig.plant.world.number == rig.service.world.number != 1
    assert rig.plant.obstacle == TASK.obstacle.grown(TASK.tool_radius - TASK.obstacle.inflation)


def test_a_restarted_services_start_up_task_over_the_arm_is_dropped_and_never_sent(
    rig: Rig,
) -> None:
    """The arm where the service before left it, the new one's start-up obstacle over it: sent,
    the plant would judge the arm in collision at once, and no safe motion leads out."""
    rig.step(5)
    first = REFERENCE.waypoints[0]
    document = task_document(TASK)
    document["waypoints"] = document["waypoints"][1:]
    document["obstacle"] |= {"x": first.x, "y": first.y}
    world = rig.plant.world
    restart_service(rig, parse_task(document, BASE))
    rig.step(round(1.0 / rig.service.period))
    assert rig.service.task is None and rig.service.world is None
    assert rig.plant.world == world and not rig.plant.fault
    assert rig.plant.stats.collisions == 0
    assert rig.ask(Request.RUN) == Answer(False, "no_scenario")


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
    span = run.waypoints[-1].t - run.waypoints[0].t
    assert run.time_limit == 2 * span + TASK.settle_time + TIMEOUT_ALLOWANCE  # the whole run's
    timed = replace(TASK, timeout=TASK.duration)
    assert with_approach(timed, tcp)[0].time_limit == run.duration  # the task's plus the lead
    at_start = forward(TASK.robot, *TASK.initial_joints())
    assert with_approach(TASK, at_start) == (TASK, 0)
    with pytest.raises(ConfigError):
        with_approach(TASK, (2.0, 0.0, 0.2))  # from out of reach: no path


def moved(task: Scenario, dx: float) -> Scenario:
    document = task_document(task)
    for waypoint in document["waypoints"]:
        waypoint["x"] += dx
    return parse_task(document, BASE)
