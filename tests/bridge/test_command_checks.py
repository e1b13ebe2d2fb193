"""Commands as they come from Zenoh: a payload that does not fit its schema is an error that
names the field; one that fits but makes a task the controller would refuse is refused with
the controller's own reason; a good one makes the task the controller will get."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest

from bridge.commands import MalformedCommandError, RefusedError, edit_task, parse_payload
from protocol.errors import ConfigError
from protocol.keys import COMMANDS
from protocol.scenario import Mode, Scenario, load_scenario, parse_task, task_document

REFERENCE = load_scenario("reference")
BASE = Scenario("bridge", (), None)
CURRENT = parse_task(task_document(REFERENCE), BASE)
WAYPOINTS = task_document(REFERENCE)["waypoints"]
OBSTACLE = task_document(REFERENCE)["obstacle"]


@pytest.mark.parametrize(
    ("command", "payload", "field"),
    [
        ("mode", b"{", "payload"),
        ("mode", b"\xff", "payload"),
        ("mode", b'{"mode": "sideways"}', "mode"),
        ("mode", b'{"mode": "fuzzy", "speed": 2}', "speed"),
        ("waypoints", b'{"waypoints": [{"t": 0, "x": 0.3, "y": 0.1}]}', "waypoints"),
        (
            "waypoints",
            b'{"waypoints": [{"t": 0, "x": 0.3, "y": 0.1, "z": 0.2}, '
            b'{"t": 1, "x": "a", "y": 0, "z": 0}]}',
            "waypoints[1].x",
        ),
        ("obstacle", b'{"obstacle": {"x": 0.4}}', "obstacle"),
        (
            "obstacle",
            b'{"obstacle": {"x": 0.4, "y": 0, "long_diameter": -0.1, '
            b'"short_diameter": 0.05, "height": 0.3}}',
            "obstacle.long_diameter",
        ),
        ("run", b"[1]", "payload"),
        ("estop", b'{"now": true}', "now"),
    ],
)
def test_a_malformed_payload_is_an_error_naming_the_field(
    command: str, payload: bytes, field: str
) -> None:
    with pytest.raises(MalformedCommandError) as raised:
        parse_payload(command, payload)
    assert raised.value.field == field, raised.value


@pytest.mark.parametrize("command", ["run", "reset", "stop", "estop"])
def test_the_buttons_without_arguments_take_an_empty_payload_or_an_empty_object(
    command: str,
) -> None:
    assert command in COMMANDS
    assert parse_payload(command, b"") == {}
    assert parse_payload(command, b" {} ") == {}


def edited(command: str, body: dict[str, Any], current: Scenario | None = CURRENT) -> Scenario:
    return edit_task(command, parse_payload(command, json.dumps(body).encode()), current, BASE)


def test_each_button_changes_its_part_of_the_task_and_keeps_the_rest() -> None:
    conventional = edited("mode", {"mode": "conventional"})
    assert conventional.mode is Mode.CONVENTIONAL
    assert conventional.waypoints == CURRENT.waypoints and conventional.obstacle == CURRENT.obstacle
    no_obstacle = edited("obstacle", {"obstacle": None})
    assert no_obstacle.obstacle is None and no_obstacle.waypoints == CURRENT.waypoints
    shifted = [w | {"x": w["x"] - 0.01} for w in WAYPOINTS]
    moved = edited("waypoints", {"waypoints": shifted})
    assert [w.x for w in moved.waypoints] == pytest.approx([w["x"] for w in shifted])
    assert moved.obstacle == CURRENT.obstacle and moved.mode is CURRENT.mode


def test_the_first_task_starts_with_waypoints() -> None:
    first = edited("waypoints", {"waypoints": WAYPOINTS}, current=None)
    assert first.obstacle is None and first.mode is Mode.FUZZY
    with pytest.raises(RefusedError) as raised:
        edited("obstacle", {"obstacle": OBSTACLE}, current=None)
    assert raised.value.reason == "no_scenario"


@pytest.mark.parametrize(
    ("command", "body", "reason", "field"),
    [
        (
            "waypoints",
            {"waypoints": [WAYPOINTS[0], WAYPOINTS[1] | {"x": 2.0}]},
            "unreachable",
            "waypoints[1]",
        ),
        (
            "waypoints",
            {"waypoints": [WAYPOINTS[0], WAYPOINTS[1] | {"x": 0.455, "y": -0.01}]},
            "inside_obstacle",
            "waypoints[1]",
        ),
        (
            "obstacle",
            {"obstacle": OBSTACLE | {"x": 0.30, "y": -0.25}},
            "inside_obstacle",
            "waypoints[0]",
        ),
        ("waypoints", {"waypoints": [WAYPOINTS[1], WAYPOINTS[0]]}, "bad_field", "waypoints[1].t"),
        (
            "waypoints",
            {"waypoints": [WAYPOINTS[0], WAYPOINTS[1] | {"x": 0.455, "y": -0.07}]},
            "near_obstacle",
            "waypoints[1]",
        ),
        (
            "waypoints",
            {"waypoints": [WAYPOINTS[0], WAYPOINTS[1] | {"t": 0.3}]},
            "too_fast",
            "waypoints[0..1]",
        ),
    ],
    ids=[
        "unreachable",
        "waypoint-in-obstacle",
        "obstacle-on-waypoint",
        "time-backwards",
        "waypoint-beside-obstacle",
        "too-fast",
    ],
)
def test_a_task_the_controller_would_refuse_is_refused_with_its_reason(
    command: str, body: dict[str, Any], reason: str, field: str
) -> None:
    with pytest.raises(RefusedError) as raised:
        edited(command, body)
    assert (raised.value.reason, raised.value.field) == (reason, field), raised.value
    reply = raised.value.reply()
    assert reply["accepted"] is False and reply["reason"] == reason and reply["message"]
    assert reply["message"].endswith(")") and "(rule " in reply["message"]


def test_the_bridge_and_the_controller_cap_the_waypoints_alike() -> None:
    """The bridge's check of a command and the controller's parser read the same schema."""
    cap = 32
    arc = [
        {"t": float(i), "x": 0.4 * math.cos(i / cap), "y": 0.4 * math.sin(i / cap), "z": 0.25}
        for i in range(cap + 1)
    ]
    assert len(edited("waypoints", {"waypoints": arc[:cap]}, current=None).waypoints) == cap
    with pytest.raises(MalformedCommandError) as raised:
        parse_payload("waypoints", json.dumps({"waypoints": arc}).encode())
    assert raised.value.field == "waypoints"
    with pytest.raises(ConfigError) as refused:
        parse_task({"waypoints": arc}, BASE)
    assert refused.value.field == "waypoints"
