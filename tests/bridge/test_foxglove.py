"""``scara-bridge --foxglove-port``: a real bridge, plant and controller, and a Foxglove client
written here from the protocol alone (``websockets``, subprotocol ``foxglove.sdk.v1``): what
the Foxglove app does, without it."""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Callable
from typing import Any

import jsonschema
import pytest
from foxglove_client import FoxgloveClient
from robot_stack import REFERENCE, RUN_TIME, START, Stack, start_router
from support import (
    ROOT,
    Processes,
    free_port,
    listening_sockets,
    quill_in_world,
    read_foxglove,
    wait_until,
)

from bridge.commands import TASK_COMMANDS, edit_task, parse_payload
from bridge.node import build_parser, foxglove_from_args
from bridge.scene import SCENE_TOPIC, TF_TOPIC, TRAIL_STEP, WORLD
from controller.task_rules import load_task
from protocol.config import RobotConfig
from protocol.keys import COMMANDS, STATE_KEYS, schema
from protocol.kinematics import forward


@pytest.fixture
def foxglove_client() -> Any:
    opened: list[FoxgloveClient] = []

    def open_one(port: int) -> FoxgloveClient:
        found: list[FoxgloveClient] = []

        def connects() -> bool:
            try:
                found.append(FoxgloveClient(port))
            except OSError:  # the bridge is not listening yet
                return False
            return True

        wait_until(connects, START, f"the bridge's Foxglove server on {port}")
        opened.append(found[0])
        return found[0]

    yield open_one
    for client in opened:
        client.close()


def test_foxglove_sees_the_run_in_3d_and_its_services_run_the_task_through_the_checks(
    make_stack: Callable[..., Stack], foxglove_client: Any
) -> None:
    port = free_port()
    make_stack("--foxglove-port", str(port), "--foxglove-commands")
    client: FoxgloveClient = foxglove_client(port)
    topics = {*(f"scara/{name}" for name in STATE_KEYS), SCENE_TOPIC, TF_TOPIC}
    wait_until(
        lambda: (
            {c["topic"] for c in client.channels.values()} == topics
            and set(client.services) == {f"cmd/{name}" for name in COMMANDS}
        ),
        10.0,
        "every channel and service advertised",
    )
    assert "services" in client.server_info["capabilities"]
    client.subscribe_all()

    # every channel carries its schema: the keys' JSON Schemas, Foxglove's protobuf ones
    for channel in client.channels.values():
        name = channel["topic"].removeprefix("scara/")
        if channel["encoding"] == "json":
            assert channel["schemaEncoding"] == "jsonschema"
            assert json.loads(channel["schema"]) == schema(name)
        else:
            assert channel["encoding"] == channel["schemaEncoding"] == "protobuf"
            expected = {"scene": "foxglove.SceneUpdate", "tf": "foxglove.FrameTransforms"}
            assert channel["schemaName"] == expected[name]
    services = client.services
    assert json.loads(services["cmd/waypoints"]["request"]["schema"]) == schema("cmd-waypoints")
    assert json.loads(services["cmd/run"]["response"]["schema"]) == schema("reply")

    def ready() -> bool:
        statuses = client.json_of("scara/status")
        last = statuses[-1] if statuses else None
        return bool(
            last
            and last["controller"]["alive"]
            and last["plant"]["alive"]
            and last["controller"]["state"] == "ready"
        )

    wait_until(ready, START, "a ready controller and plant on scara/status")

    # refused by the bridge's own checks, with the reason; malformed: the call fails
    assert client.call("cmd/obstacle", {"obstacle": REFERENCE["obstacle"]}) == (
        True,
        {"accepted": False, "reason": "no_scenario", "message": "set the waypoints first"},
    )
    bad = {"waypoints": [{"t": 0.0, "x": "far", "y": 0.0, "z": 0.2}]}
    ok, failure = client.call("cmd/waypoints", bad)
    assert not ok and "waypoints" in failure, failure
    out_of_reach = [*REFERENCE["waypoints"][:-1], {"t": 9.0, "x": 2.0, "y": 0.0, "z": 0.2}]
    ok, reply = client.call("cmd/waypoints", {"waypoints": out_of_reach})
    assert ok and reply["accepted"] is False and reply["reason"] == "unreachable", reply

    for name, body in (
        ("waypoints", {"waypoints": REFERENCE["waypoints"]}),
        ("obstacle", {"obstacle": REFERENCE["obstacle"]}),
        ("mode", {"mode": "fuzzy"}),
    ):
        assert client.call(f"cmd/{name}", body) == (True, {"accepted": True, "reason": "none"})
    assert client.call("cmd/run") == (True, {"accepted": True, "reason": "none"})
    ok, busy = client.call("cmd/mode", {"mode": "conventional"})
    assert ok and busy["accepted"] is False and busy["reason"] == "busy", busy

    def finished() -> bool:
        return any(e["event"] == "run_finished" for e in client.json_of("scara/events"))

    wait_until(finished, RUN_TIME, "the run to finish on scara/events")

    # the joint states fit their schema; the transforms drawn from them put the quill where
    # the forward kinematics put the tool
    robot = RobotConfig()
    transforms = client.of(TF_TOPIC)  # first: each came after the joint state it is drawn from
    joints = {log_time: json.loads(data) for log_time, data in client.of("scara/joints")}
    validator = jsonschema.Draft202012Validator(schema("joints"))
    for sample in joints.values():
        validator.validate(sample)
    # the server takes one subscription after another, in its own order of the channels: a
    # transform may come before the joints' subscription does, never after it without them
    transforms = [(log_time, data) for log_time, data in transforms if log_time >= min(joints)]
    assert len(transforms) > 30
    tf_channel = next(c for c in client.channels.values() if c["topic"] == TF_TOPIC)
    for log_time, data in transforms:
        decoded = read_foxglove(tf_channel["schemaName"], _schema_bytes(tf_channel), data)
        position = joints[log_time]["position"]  # the same log time: the same joint state
        assert quill_in_world(decoded) == pytest.approx(forward(robot, *position), abs=1e-9)
    weights = client.json_of("scara/coordination")
    assert any(w["k_c"] > 0.0 for w in weights) and all(0 <= w["k_t"] <= 1 for w in weights)

    # the scene: the task's obstacle and waypoints, and the path the tool travelled to the end
    scene_channel = next(c for c in client.channels.values() if c["topic"] == SCENE_TOPIC)
    scenes = [
        read_foxglove(scene_channel["schemaName"], _schema_bytes(scene_channel), data)
        for _, data in client.of(SCENE_TOPIC)
    ]
    entities = {entity.id: entity for entity in scenes[-1].entities}
    real = entities["obstacle"].cylinders[0]
    obstacle = REFERENCE["obstacle"]
    assert (real.pose.position.x, real.pose.position.y) == (obstacle["x"], obstacle["y"])
    spheres = entities["waypoints"].spheres
    assert [(s.pose.position.x, s.pose.position.y) for s in spheres] == [
        (w["x"], w["y"]) for w in REFERENCE["waypoints"]
    ]
    travelled = entities["travelled"].lines[0].points
    last = REFERENCE["waypoints"][-1]
    end = (travelled[-1].x, travelled[-1].y, travelled[-1].z)
    # a point every TRAIL_STEP of the tool's, and the arm settles within 1 mm of the waypoint
    assert math.dist(end, (last["x"], last["y"], last["z"])) < TRAIL_STEP + 0.002


def _schema_bytes(channel: dict[str, Any]) -> bytes:
    """An advertised protobuf channel's schema (base64 of its FileDescriptorSet)."""
    return base64.b64decode(channel["schema"])


def test_without_foxglove_commands_the_server_is_read_only(
    processes: Processes, foxglove_client: Any
) -> None:
    router = start_router(processes, name="router")
    port = free_port()
    bridge = processes.start(
        "bridge.node", "--zenoh-port", str(router), "--foxglove-port", str(port),
        "--interface", "zenoh", "--channel", f"robot{router}", "--bus-option", f"port={router}",
        name="bridge",
    )  # fmt: skip
    client: FoxgloveClient = foxglove_client(port)
    wait_until(lambda: len(client.channels) == len(STATE_KEYS) + 2, 10.0, "the channels")
    assert client.services == {}
    assert "services" not in client.server_info["capabilities"]
    # the kernel agrees: the bridge listens on loopback only, on the Foxglove port and on the
    # SDK's own behind it (TLS no browser trusts: tests/attack), and nothing else
    listening = listening_sockets(bridge.pid)
    if listening is not None:
        assert ("127.0.0.1", port) in listening and len(listening) == 2, listening
        assert {host for host, _ in listening} == {"127.0.0.1"}, listening


@pytest.mark.parametrize(
    ("args", "refused"),
    [
        (["--foxglove-host", "192.0.2.7"], "--allow-remote"),
        (["--foxglove-host", "0.0.0.0", "--allow-remote"], "wildcard"),
        (["--foxglove-host", "192.0.2.7", "--allow-remote", "--foxglove-commands"], "users"),
    ],
)
def test_a_foxglove_address_off_loopback_needs_allow_remote_and_never_takes_commands(
    args: list[str], refused: str
) -> None:
    with pytest.raises(ValueError, match=refused):
        foxglove_from_args(build_parser().parse_args(["--foxglove-port", "8765", *args]))
    allowed = ["--foxglove-port", "8765", "--foxglove-host", "192.0.2.7", "--allow-remote"]
    settings = foxglove_from_args(build_parser().parse_args(allowed))
    assert settings is not None and (settings.host, settings.commands) == ("192.0.2.7", False)


LAYOUT = ROOT / "config" / "foxglove" / "scara.json"


def test_the_shipped_layout_shows_what_is_served_and_its_buttons_send_commands_that_pass() -> None:
    layout = json.loads(LAYOUT.read_text())
    panels: dict[str, dict[str, Any]] = layout["configById"]
    served = {*(f"scara/{name}" for name in STATE_KEYS), SCENE_TOPIC, TF_TOPIC}

    def panel_ids(node: Any) -> set[str]:
        if isinstance(node, str):
            return {node}
        return panel_ids(node["first"]) | panel_ids(node["second"])

    assert panel_ids(layout["layout"]) == set(panels)  # every panel placed, none missing
    three_d = panels["3D!scene"]
    assert three_d["followTf"] == WORLD and set(three_d["topics"]) == {SCENE_TOPIC, TF_TOPIC}
    plotted = [path["value"] for kind, config in panels.items() if kind.startswith("Plot!")
               for path in config["paths"]]  # fmt: skip
    assert "scara/joints.position[2]" in plotted and "scara/coordination.k_c" in plotted
    for path in plotted:
        topic, _, field = path.partition(".")
        assert topic in served, path
        properties = schema(topic.removeprefix("scara/"))["properties"]
        assert field.split("[")[0] in properties, path
    raw = {config["topicPath"] for kind, config in panels.items() if kind.startswith("Raw")}
    assert "scara/status" in raw and raw <= served

    buttons = {c["serviceName"]: c for k, c in panels.items() if k.startswith("CallService!")}
    assert set(buttons) == {f"cmd/{name}" for name in COMMANDS}
    base = load_task("reference")
    task = None
    for name in ("waypoints", "obstacle", "mode", "run", "reset", "stop", "estop"):
        body = parse_payload(name, buttons[f"cmd/{name}"]["requestPayload"].encode())
        if name in TASK_COMMANDS:  # the task the buttons make is one the controller takes
            task = edit_task(name, body, task, base)
    assert task is not None and task.obstacle is not None and task.mode.value == "conventional"


@pytest.mark.parametrize(
    ("given", "taken"),
    [
        ([], ("https://app.foxglove.dev",)),
        (
            ["http://localhost:8080", "https://studio.example"],
            ("http://localhost:8080", "https://studio.example"),
        ),
    ],
)
def test_foxglove_takes_the_app_s_origin_unless_told_which(
    given: list[str], taken: tuple[str, ...]
) -> None:
    flags = [part for origin in given for part in ("--foxglove-allow-origin", origin)]
    settings = foxglove_from_args(build_parser().parse_args(["--foxglove-port", "8765", *flags]))
    assert settings is not None and settings.origins == taken


@pytest.mark.parametrize(
    "origin", ["app.foxglove.dev", "https://app.foxglove.dev/", "*", "ftp://x"]
)
def test_an_allowed_origin_that_is_not_one_is_refused_naming_it(origin: str) -> None:
    args = build_parser().parse_args(["--foxglove-port", "8765", "--foxglove-allow-origin", origin])
    with pytest.raises(ValueError, match="is not an origin") as refused:
        foxglove_from_args(args)
    assert repr(origin) in str(refused.value)
