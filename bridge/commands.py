"""Commands as they arrive from Zenoh: checked before anything reaches the bus.

A payload is JSON checked against its command's JSON Schema (``protocol/validation.py``): what
does not fit is :class:`MalformedCommandError`, naming the field, and gets an error reply. A
payload that fits but would make a task the controller must refuse (a waypoint out of reach or
inside the obstacle, a path leaving the workspace) is :class:`RefusedError` with the same
reason the controller would give. Pure: no bus, no Zenoh.
"""

from __future__ import annotations

from typing import Any

from controller.task_rules import accept
from protocol.errors import ConfigError, ScaraError
from protocol.messages import reason_of
from protocol.scenario import Scenario, task_document
from protocol.validation import SUFFIX, check, read_json

TASK_COMMANDS = ("waypoints", "obstacle", "mode")
"""Commands that change the task (sent over ISO-TP); the others are NodeCommands."""
MAX_PAYLOAD_BYTES = 65536
"""The longest payload a command is read from: 32 waypoints, pretty-printed, take a few
kilobytes, and a task travels in one ISO-TP transfer of at most 4091 bytes anyway. Anything
longer is refused unread (reading and checking megabytes would hold the bridge up)."""


class MalformedCommandError(ScaraError):
    """The payload is not the command's JSON: ``field`` names where."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


class RefusedError(Exception):
    """A well-formed command the controller would refuse: ``reason`` as it would say it."""

    def __init__(self, reason: str, field: str = "", message: str = "") -> None:
        super().__init__(f"{reason}: {field}: {message}" if field else reason)
        self.reason = reason
        self.field = field
        self.message = message

    def reply(self) -> dict[str, Any]:
        answer: dict[str, Any] = {"accepted": False, "reason": self.reason}
        if self.field:
            answer["field"] = self.field
        if self.message:
            answer["message"] = self.message
        return answer


def parse_payload(command: str, payload: bytes) -> dict[str, Any]:
    """The command's JSON body (an empty payload is ``{}``), checked against its schema."""
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise MalformedCommandError(
            "payload", f"{len(payload)} bytes; a command takes at most {MAX_PAYLOAD_BYTES}"
        )
    try:
        body: Any = read_json(payload, "payload") if payload.strip() else {}
        check(body, f"cmd-{command}{SUFFIX}", root="payload")
    except ConfigError as error:
        message = str(error).removeprefix(f"{error.field}: ")
        raise MalformedCommandError(error.field, message) from None
    result: dict[str, Any] = body
    return result


def edit_task(
    command: str, body: dict[str, Any], current: Scenario | None, base: Scenario
) -> Scenario:
    """The task after ``command`` (one of :data:`TASK_COMMANDS`), checked with the rules the
    controller applies; :class:`RefusedError` if it would refuse it."""
    if current is None and command != "waypoints":
        raise RefusedError("no_scenario", message="set the waypoints first")
    document = (
        task_document(current) if current is not None else {"name": "operator", "mode": "fuzzy"}
    )
    if command == "waypoints":
        document["waypoints"] = body["waypoints"]
    elif command == "obstacle":
        document.pop("obstacle", None)
        if body["obstacle"] is not None:
            document["obstacle"] = body["obstacle"]
    else:
        document["mode"] = body["mode"]
    try:
        task = accept(document, base)
    except ConfigError as error:
        reason = reason_of(error).name.lower()
        raise RefusedError(
            reason, error.field, str(error).removeprefix(f"{error.field}: ")
        ) from None
    return task
