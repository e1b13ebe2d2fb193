"""Fuzzing the bridge's command queries (``bridge/commands.py``), pure: no bus, no Zenoh.

The payloads start from each command's valid body and are broken: values anywhere replaced
by any JSON value (huge integers, NaN and infinities, lone surrogates, deep or empty
containers), keys removed or added, keys given twice, the text cut or edited as bytes,
nested thousands deep, padded or repeated to megabytes. Properties: :func:`parse_payload`
raises only :class:`MalformedCommandError`, naming a field, and what it takes fits the
command's schema; :func:`edit_task` raises only :class:`RefusedError`, with a reason the
controller's answer has and the field; and a task it takes is one the controller takes too,
as it gets it over ISO-TP (:func:`encode_task`, then the controller's own parsing).

One test goes through a real bridge process on a real Zenoh session on 127.0.0.1
(``test_fuzz_bridge_process.py``).
"""

from __future__ import annotations

import json
import math
from typing import Any

import pytest
from fuzzing import deep, fuzz, json_texts, json_values, mutated_json
from hypothesis import given
from hypothesis import strategies as st

from bridge.commands import (
    TASK_COMMANDS,
    MalformedCommandError,
    RefusedError,
    edit_task,
    parse_payload,
)
from controller.planner import check_plan
from protocol.errors import ConfigError
from protocol.keys import COMMANDS
from protocol.messages import Reason
from protocol.scenario import (
    MAX_TASK_BYTES,
    Scenario,
    encode_task,
    load_scenario,
    parse_task,
    read_task,
    task_document,
)
from protocol.validation import SUFFIX, check

pytestmark = pytest.mark.fuzz

REFERENCE = load_scenario("reference")
BASE = Scenario("bridge", (), None)
CURRENT = parse_task(task_document(REFERENCE), BASE)
WAYPOINTS = task_document(REFERENCE)["waypoints"]
OBSTACLE = task_document(REFERENCE)["obstacle"]
REASONS = {member.name.lower() for member in Reason} | {"busy", "no_scenario"}


def arc(count: int, digits: int = 3) -> list[dict[str, Any]]:
    """``count`` reachable waypoints on an arc round the base, values rounded to ``digits``."""
    return [
        {
            "t": round(index * 0.7, digits),
            "x": round(0.4 * math.cos(-1.4 + 2.8 * index / max(count, 1)), digits),
            "y": round(0.4 * math.sin(-1.4 + 2.8 * index / max(count, 1)), digits),
            "z": 0.25,
        }
        for index in range(count)
    ]


VALID_BODIES: dict[str, list[Any]] = {
    "waypoints": [{"waypoints": WAYPOINTS}, {"waypoints": arc(2)}, {"waypoints": arc(32, 15)}],
    "obstacle": [{"obstacle": OBSTACLE}, {"obstacle": None}],
    "mode": [{"mode": "fuzzy"}, {"mode": "conventional"}],
    "run": [{}],
    "reset": [{}],
    "stop": [{}],
    "estop": [{}],
}


@st.composite
def payloads(draw: st.DrawFn, command: str) -> bytes:
    """A payload for ``command``: its valid body broken, any JSON at all, or a pathological
    text (deep, huge, not JSON)."""
    valid = st.sampled_from(VALID_BODIES[command])
    kind = draw(st.sampled_from(["mutated", "mutated", "valid", "any", "deep", "huge"]))
    if kind == "mutated":
        return draw(json_texts(valid.flatmap(mutated_json)))
    if kind == "valid":
        return draw(json_texts(valid))
    if kind == "any":
        return draw(json_texts(json_values))
    if kind == "deep":
        depth = draw(st.sampled_from([10, 500, 900, 990, 1000, 3000, 100_000]))
        opener, closer = draw(st.sampled_from([(b"[", b"]"), (b'{"a":', b"}")]))
        key = draw(st.sampled_from([command, "waypoints", "x"])).encode()
        return b'{"' + key + b'": ' + deep(depth, opener, closer) + b"}"
    count = draw(st.sampled_from([33, 1000, 100_000]))
    if command == "waypoints":
        return json.dumps({"waypoints": WAYPOINTS * (count // 4 + 1)}).encode()
    return b" " * (count * 40) + json.dumps(draw(valid)).encode()


@st.composite
def commands_and_payloads(draw: st.DrawFn) -> tuple[str, bytes]:
    command = draw(st.sampled_from(COMMANDS), label="command")
    return command, draw(payloads(command), label="payload")


def the_controller_takes(task: Scenario) -> None:
    """What the bridge sends for ``task`` (the longest ticket) is one ISO-TP transfer that
    the controller's parser and its planned-path check accept, as the same task."""
    payload = encode_task(task, 255)
    assert len(payload) <= MAX_TASK_BYTES
    ticket, document = read_task(payload)
    again = parse_task(document, BASE)
    check_plan(again)
    assert ticket == 255 and again.waypoints == task.waypoints and again.mode is task.mode


@fuzz(300)
@given(commands_and_payloads())
def test_a_command_is_taken_or_refused_naming_the_field(command_payload: tuple[str, bytes]) -> None:
    taken_or_refused(*command_payload)


def taken_or_refused(command: str, payload: bytes) -> None:
    try:
        body = parse_payload(command, payload)
    except MalformedCommandError as error:
        assert error.field and error.message, error
        assert len(str(error)) < 2000, "an error message is a sentence, not the payload"
        return
    check(body, f"cmd-{command}{SUFFIX}", root="payload")  # it fits its schema
    if command not in TASK_COMMANDS:
        assert body == {}
        return
    for current in (None, CURRENT):
        try:
            task = edit_task(command, body, current, BASE)
        except RefusedError as refusal:
            assert refusal.reason in REASONS, refusal
            assert refusal.field or refusal.reason == "no_scenario", refusal
            assert refusal.reply()["accepted"] is False
            continue
        the_controller_takes(task)


@st.composite
def long_tasks(draw: st.DrawFn) -> dict[str, Any]:
    """Tasks near the size of one transfer: the most waypoints, long numbers, a long name in
    characters that JSON escapes, an obstacle."""
    count = draw(st.integers(20, 32))
    digits = draw(st.integers(3, 17))
    characters = st.sampled_from("a\u00e9\u4e2d\U0001f916")
    name = draw(characters) * draw(st.integers(0, 1500)) + draw(st.text(characters, max_size=8))
    document: dict[str, Any] = {"name": name, "waypoints": arc(count, digits)}
    if draw(st.booleans()):
        document["obstacle"] = OBSTACLE | {"x": 0.1, "y": 0.0, "long_diameter": 0.05}
    return document


@fuzz(40)
@given(long_tasks())
def test_a_task_the_controller_takes_can_be_sent_back_whole(document: dict[str, Any]) -> None:
    """The controller describes its task back in one transfer: a task it takes must fit one,
    written as the controller writes it (every field, its names escaped)."""
    try:
        task = parse_task(document, BASE)
        check_plan(task)
    except ConfigError as error:
        assert error.field, error
        return
    the_controller_takes(task)


@pytest.mark.parametrize(
    ("command", "payload", "fields"),
    [
        ("mode", b"1" * 5000, {"payload"}),  # past Python's 4300 digits: a ValueError
        ("waypoints", deep(100_000), {"payload"}),  # a RecursionError in json
        ("stop", b'"' + b'\\"' * 32_000, {"payload"}),  # no quadratic scan for the depth
        ("mode", b'{"mode": ' + deep(990) + b"}", {"payload"}),  # ... or in a repr
        (
            "waypoints",
            json.dumps({"waypoints": [WAYPOINTS[0], WAYPOINTS[1] | {"x": 10**400}]}).encode(),
            {"waypoints[1].x"},  # an integer no float holds: an OverflowError when parsed
        ),
        (
            "obstacle",
            json.dumps({"obstacle": OBSTACLE | {"yaw_deg": -(10**309)}}).encode(),
            {"obstacle.yaw_deg"},
        ),
        ("run", b'{"":{}}', {'""'}),  # an unknown field with no name: named by nothing
        ("stop", b'{"' + b"k" * 5000 + b'": 1}', {'"' + "k" * 64 + '"...'}),
        ("estop", b" " * 70_000 + b"{}", {"payload"}),  # read whole, however long
    ],
    ids=[
        "long-int",
        "deep",
        "escaped-quotes",
        "deep-repr",
        "huge-int",
        "huge-yaw",
        "empty-key",
        "long-key",
        "huge",
    ],
)
def test_what_the_fuzzing_found_is_refused_naming_the_field(
    command: str, payload: bytes, fields: set[str]
) -> None:
    with pytest.raises(MalformedCommandError) as raised:
        parse_payload(command, payload)
    assert raised.value.field in fields, raised.value
    assert len(str(raised.value)) < 2000


def test_a_task_with_a_name_too_long_to_send_back_is_refused_naming_it() -> None:
    """Found by ``test_a_task_the_controller_takes_can_be_sent_back_whole``: 1500 non-ASCII
    characters took 4097 bytes once escaped, and describing the task crashed the controller
    (``encode_task`` raised in its loop)."""
    with pytest.raises(ConfigError) as raised:
        parse_task({"name": "\U0001f916" * 400, "waypoints": arc(4)}, BASE)
    assert raised.value.field == "name" and str(MAX_TASK_BYTES) in str(raised.value)
