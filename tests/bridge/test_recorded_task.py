"""A recording of the service: ``scara-record`` on the robot's bus beside plant, controller
service and bridge (real processes on CAN over Zenoh), started without a scenario; the task
is set through the bridge, as the GUI and Foxglove set it. The recording must hold the task
the controller took, and draw it in its 3D scene, not the one the recorder started with."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jsonschema
from mcap.reader import make_reader
from robot_stack import REFERENCE, RUN_TIME, START, Recorder, Stack, command
from support import Processes, read_foxglove, wait_until

from bridge.scene import SCENE_TOPIC
from protocol.keys import schema
from recorder.replay import read_state


def last_scene(path: Path) -> Any:
    """The last ``foxglove.SceneUpdate`` of a recording, decoded with its own schema."""
    last = None
    with path.open("rb") as stream:
        for recorded_schema, _, message in make_reader(stream).iter_messages(topics=[SCENE_TOPIC]):
            assert recorded_schema is not None
            last = read_foxglove(recorded_schema.name, recorded_schema.data, message.data)
    return last


def test_a_recording_of_the_service_holds_the_task_the_controller_took_and_draws_it(
    stack: Stack, client: Any, processes: Processes, tmp_path: Path
) -> None:
    file = tmp_path / "service.mcap"
    recorder = processes.start("recorder.node", "--out", str(file), *stack.bus, name="recorder")
    wait_until(lambda: "recording to" in recorder.output(), START, "the recorder to start")
    operator = client(stack.zenoh_port)
    heard = Recorder(operator)
    stack.wait_ready(operator)
    for name, body in (
        ("waypoints", {"waypoints": REFERENCE["waypoints"]}),
        ("obstacle", {"obstacle": REFERENCE["obstacle"]}),
    ):
        assert command(operator, name, body) == (True, {"accepted": True, "reason": "none"})
    assert command(operator, "run") == (True, {"accepted": True, "reason": "none"})
    # sent over the bus like the others, and refused by the controller: never in force
    ok, refused = command(operator, "mode", {"mode": "conventional"})
    assert ok and refused["accepted"] is False and refused["reason"] == "busy", refused
    wait_until(lambda: heard.event("run_finished") is not None, RUN_TIME, "the run to finish")
    assert recorder.interrupt() == 0, recorder.output()

    tasks = [json.loads(sample.data) for sample in read_state(file) if sample.name == "scenario"]
    validator = jsonschema.Draft202012Validator(schema("scenario"))
    for task in tasks:
        validator.validate(task)
    # the two the bridge set, in order; its own key says the task in force at its status
    # rate, so it may skip the first when both came within one period, never differ
    assert [("obstacle" in task) for task in tasks] == [False, True]
    said = [payload for _, payload in heard.of("scenario")]
    assert said[-1] == tasks[-1] and all(task in tasks for task in said), said
    assert all(task["mode"] == "fuzzy" for task in tasks)
    assert [(w["x"], w["y"]) for w in tasks[-1]["waypoints"]] == [
        (w["x"], w["y"]) for w in REFERENCE["waypoints"]
    ]
    # the scene drawn at the end: the obstacle the arm went round, and its waypoints
    entities = {entity.id: entity for entity in last_scene(file).entities}
    drawn = entities["obstacle"].cylinders[0].pose.position
    assert (drawn.x, drawn.y) == (REFERENCE["obstacle"]["x"], REFERENCE["obstacle"]["y"])
    spheres = entities["waypoints"].spheres
    assert [(s.pose.position.x, s.pose.position.y) for s in spheres] == [
        (w["x"], w["y"]) for w in REFERENCE["waypoints"]
    ]
