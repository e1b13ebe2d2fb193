"""The bridge's command queries fuzzed through a real ``scara-bridge`` process and a real
Zenoh session on 127.0.0.1 (the test's own router, multicast scouting off): a few examples
only, as each is a round trip through two processes.

The payloads are those of ``test_fuzz_commands.py``, less the ones the bridge would take
(with no controller on the bus they would wait for an answer that never comes). Properties:
each query gets exactly one reply, the one :func:`parse_payload` and :func:`edit_task` give,
in the shape of its schema (an error reply naming the field, or a refusal with its reason);
nothing reaches the CAN bus (the robot does not move); and the bridge is still there.
"""

from __future__ import annotations

import json
from typing import Any

import can
import jsonschema
import pytest
from fuzzing import fuzz
from hypothesis import assume, example, given
from support import SLOWDOWN, Processes, wait_until
from test_fuzz_commands import commands_and_payloads

from bridge.commands import (
    TASK_COMMANDS,
    MalformedCommandError,
    RefusedError,
    edit_task,
    parse_payload,
)
from bridge.session import ZenohEndpoint
from protocol.keys import alive_key, command_key, schema
from protocol.scenario import Scenario

pytestmark = pytest.mark.fuzz

ROBOT = "arm1"
BASE = Scenario("bridge", (), None)
START = 30.0
"""s the bridge may take to import and join on a loaded 2-core machine."""
ERROR = jsonschema.Draft202012Validator(schema("error"))
REPLY = jsonschema.Draft202012Validator(schema("reply"))


def local_verdict(command: str, payload: bytes) -> tuple[str, Any, str]:
    """What the bridge must answer, from the pure functions: ``("error", field, message)``,
    ``("refused", reason, message)`` or ``("taken", None, "")``."""
    try:
        body = parse_payload(command, payload)
        if command in TASK_COMMANDS:
            edit_task(command, body, None, BASE)  # the bridge has no task: no controller
    except MalformedCommandError as error:
        return "error", error.field, error.message
    except RefusedError as refusal:
        return "refused", refusal.reason, refusal.message
    return "taken", None, ""


def test_a_real_bridge_answers_fuzzed_commands_and_sends_nothing_on_the_bus(
    router: int, processes: Processes
) -> None:
    channel = f"fuzz{router}"
    bridge = processes.start(
        "bridge.node",
        "--zenoh-port", str(router), "--robot", ROBOT,
        "--interface", "zenoh", "--channel", channel, "--bus-option", f"port={router}",
        name="bridge",
    )  # fmt: skip
    bus = can.Bus(interface="zenoh", channel=channel, port=router)
    session = ZenohEndpoint("127.0.0.1", router).open()
    try:

        def bridge_up() -> bool:
            assert bridge.poll() is None, bridge.output()
            return bool(list(session.liveliness().get(alive_key(ROBOT, "bridge"), timeout=1.0)))

        wait_until(bridge_up, START, "the bridge's liveliness token")

        @fuzz(15)
        @given(commands_and_payloads())
        @example(("waypoints", b" " * 70_000 + b"{}"))  # past the size a command may take
        @example(("run", b'{"":{}}'))  # an unknown field with an empty name
        def answers(command_payload: tuple[str, bytes]) -> None:
            command, payload = command_payload
            verdict, detail, message = local_verdict(command, payload)
            assume(verdict != "taken" and len(payload) < 200_000)
            replies = list(
                session.get(command_key(ROBOT, command), payload=payload, timeout=5.0 * SLOWDOWN)
            )
            assert len(replies) == 1, f"{len(replies)} replies"
            reply = replies[0]
            if verdict == "error":
                assert reply.err is not None, reply.ok
                body = json.loads(reply.err.payload.to_bytes())
                ERROR.validate(body)
                assert body["field"] == detail and body["message"] == message
            else:
                assert reply.ok is not None, reply.err
                body = json.loads(reply.ok.payload.to_bytes())
                REPLY.validate(body)
                assert body["accepted"] is False and body["reason"] == detail
            sent = bus.recv(timeout=0.05)
            assert sent is None, f"the bridge sent {sent} for a command it refused"

        answers()
        assert bridge.poll() is None, bridge.output()
    finally:
        session.close()  # type: ignore[no-untyped-call]
        bus.shutdown()
