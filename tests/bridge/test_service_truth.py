"""What an operator saw go wrong, tried again from the outside: our own Zenoh session as the
operator, and a python-can bus on the robot's CAN transport as any CAN tool would be. Plant,
controller service and bridge are real processes on CAN over Zenoh through the test's router.
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path
from typing import Any

import can
from robot_stack import (
    REFERENCE,
    ROBOT,
    RUN_TIME,
    Recorder,
    Stack,
    command,
    inside_obstacle,
    latest,
)
from support import SLOWDOWN, Observer, Processes, wait_until

from protocol.messages import CONTROLLER_STATUS, NODE_COMMAND, NodeId, Request


def status_of(operator: Any) -> dict[str, Any]:
    return latest(operator, f"scara/{ROBOT}/status") or {}


def wait_for_states(operator: Any, controller: str, plant: str, what: str) -> None:
    def reached() -> bool:
        status = status_of(operator)
        return bool(status) and (status["controller"]["state"], status["plant"]["state"]) == (
            controller,
            plant,
        )

    wait_until(reached, 10.0, what)


def test_the_plant_judges_collisions_by_the_obstacle_the_operator_set(
    stack: Stack, client: Any
) -> None:
    """Obstacle none, then the reference's way straight through where the plant's start-up
    obstacle stands: the run finishes with no collision (the plant once judged by its own
    scenario file's obstacle, faulted, and went back to fault after every reset)."""
    operator = client(stack.zenoh_port)
    recorder = Recorder(operator)
    stack.wait_ready(operator)
    for name, body in (
        ("waypoints", {"waypoints": REFERENCE["waypoints"]}),
        ("obstacle", {"obstacle": None}),
    ):
        assert command(operator, name, body) == (True, {"accepted": True, "reason": "none"})
    wait_until(  # the bridge's status comes within a status period of the plant's
        lambda: status_of(operator)["plant"]["world"] != 0, 2.0, "the plant to hold the world"
    )
    assert command(operator, "run") == (True, {"accepted": True, "reason": "none"})
    wait_until(lambda: recorder.event("run_finished") is not None, RUN_TIME, "the run to finish")
    names = [event["event"] for event in recorder.events()]
    assert "collision" not in names and "fault" not in names, names
    path = [(p["x"], p["y"]) for _, p in recorder.of("tcp")]
    assert any(inside_obstacle(x, y) for x, y in path)  # through where it stood at start-up
    status = status_of(operator)
    assert status["plant"]["faults"] == [] and not status["plant"]["collision"]
    assert status["controller"]["waypoints_reached"] == len(REFERENCE["waypoints"])


def test_a_reset_after_an_estop_clears_every_node_and_the_arm_runs_again(
    stack: Stack, client: Any
) -> None:
    operator = client(stack.zenoh_port)
    recorder = Recorder(operator)
    stack.wait_ready(operator)
    assert command(operator, "waypoints", {"waypoints": REFERENCE["waypoints"]})[1]["accepted"]
    assert command(operator, "estop") == (True, {"accepted": True, "reason": "none"})
    wait_for_states(operator, "estop", "estop", "both nodes to latch the e-stop")
    assert command(operator, "reset") == (True, {"accepted": True, "reason": "none"})
    wait_for_states(operator, "ready", "ready", "both nodes to come back ready")
    assert command(operator, "run") == (True, {"accepted": True, "reason": "none"})
    wait_until(lambda: recorder.event("run_finished") is not None, RUN_TIME, "the run to finish")
    path = [(p["x"], p["y"]) for _, p in recorder.of("tcp")]
    assert max(y for _, y in path) > 0.3  # the arm went on to the last waypoint


def test_a_run_the_plant_cannot_follow_is_refused_and_nothing_moves(
    stack: Stack, client: Any
) -> None:
    """The plant left in e-stop (a reset sent to the controller alone, by a CAN tool): a run is
    refused with the reason (it was once accepted and reported finished, the arm not having
    moved, its waypoints "reached")."""
    operator = client(stack.zenoh_port)
    recorder = Recorder(operator)
    stack.wait_ready(operator)
    assert command(operator, "waypoints", {"waypoints": REFERENCE["waypoints"]})[1]["accepted"]
    assert command(operator, "estop")[1]["accepted"]
    wait_for_states(operator, "estop", "estop", "both nodes to latch the e-stop")
    channel = f"robot{stack.can_port}"
    with can.Bus(interface="zenoh", channel=channel, port=stack.can_port) as tool:
        record = NODE_COMMAND.Record(
            Command=Request.RESET, Target=NodeId.CONTROLLER, Source=NodeId.OPERATOR, Ticket=0
        )
        for counter in (0, 1):  # two in a row: a receiver takes them up whatever it saw last
            data = NODE_COMMAND.encode(record, counter)
            tool.send(
                can.Message(arbitration_id=NODE_COMMAND.frame_id, data=data, is_extended_id=False)
            )
    wait_for_states(operator, "ready", "estop", "the controller alone to come back ready")
    before = latest(operator, f"scara/{ROBOT}/joints")
    assert command(operator, "run") == (True, {"accepted": False, "reason": "plant_not_ready"})
    assert recorder.event("run_started") is None
    after = latest(operator, f"scara/{ROBOT}/joints")
    assert before is not None and after is not None and after["position"] == before["position"]


def test_a_service_stopped_before_any_run_exits_cleanly_and_says_it_ran_nothing(
    router: int, processes: Processes, tmp_path: Path
) -> None:
    """Ctrl-C before the first run once ended in an AttributeError (no log to save)."""
    out = tmp_path / "out"
    bus = ["--interface", "zenoh", "--channel", "svc", "--bus-option", f"port={router}"]
    observer = Observer(can.Bus(interface="zenoh", channel="svc", port=router))
    try:
        service = processes.start("controller.cli", *bus, "--out", str(out), name="service")
        status = observer.wait_for(
            lambda frame: frame.arbitration_id == CONTROLLER_STATUS.frame_id, 30.0
        )
        assert status is not None, processes.outputs()  # its loop runs: signals are handled
    finally:
        observer.close()
    service.signal(signal.SIGINT)
    assert service.wait(10.0) == 0, processes.outputs()
    assert "Traceback" not in service.log.read_text()
    result = json.loads((out / "controller.json").read_text())
    assert result["runs"] == 0 and result["completed"] is False
    assert not (out / "controller_log.npz").exists()


def test_a_wildcard_query_on_the_commands_runs_none_of_them(stack: Stack, client: Any) -> None:
    """One query on ``cmd/**`` once reached every command: estop, run, reset and stop ran."""
    operator = client(stack.zenoh_port)
    stack.wait_ready(operator)
    assert command(operator, "waypoints", {"waypoints": REFERENCE["waypoints"]})[1]["accepted"]
    replies = list(operator.get(f"scara/{ROBOT}/cmd/**", timeout=5.0 * SLOWDOWN))
    assert len(replies) == 7 and all(reply.err is not None for reply in replies)
    assert {json.loads(reply.err.payload.to_bytes())["field"] for reply in replies} == {"key"}
    time.sleep(0.3 * SLOWDOWN)  # an e-stop or a run would show in the next status
    status = status_of(operator)
    assert (status["controller"]["state"], status["plant"]["state"]) == ("ready", "ready")
