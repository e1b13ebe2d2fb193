"""The robots on a Zenoh network, as the bridges publish them, and their commands.

One client session (the user's credentials, no scouting, one explicit router endpoint:
``bridge/session.py``) subscribes key by key to ``scara/*/<key>``, as the secure router's
rules name them, so every robot on the network is heard; the bridges' liveliness tokens
(``scara/*/alive/bridge``) say which robots are there now. Each state key's queryable is
asked at start and again whenever a robot's bridge appears, so the pages show every robot at
once, before its next sample (the task and the status are published only when they change).
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from gui.state import RobotState
from protocol.keys import COMMANDS, STATE_KEYS, check_robot, command_key
from protocol.scenario import Scenario

COMMAND_TIMEOUT = 5.0
"""s a command may wait for its reply (the bridge waits 2 s for the controller)."""
QUERY_TIMEOUT = 2.0
"""s the first look at the state keys may take."""


def robot_of(key: str) -> str:
    """``arm1`` of ``scara/arm1/joints`` or ``scara/arm1/alive/bridge``."""
    return key.split("/")[1]


class Fleet:
    """Every robot heard on the network, by name; whether its bridge is alive."""

    def __init__(self, session: zenoh.Session, base: Scenario) -> None:
        self.session = session
        self.base = base
        self.robots: dict[str, RobotState] = {}
        self.online: dict[str, bool] = {}
        self._lock = threading.Lock()
        self._entities: list[Any] = [
            session.declare_subscriber(f"scara/*/{name}", self._handler(name))
            for name in STATE_KEYS
        ]
        self._entities.append(
            session.liveliness().declare_subscriber(
                "scara/*/alive/bridge", self._on_liveliness, history=True
            )
        )
        self._look_at("*")

    def robot(self, name: str) -> RobotState:
        """The state of robot ``name`` (an empty one until it is heard)."""
        with self._lock:
            if name not in self.robots:
                self.robots[name] = RobotState(self.base)
                self.online.setdefault(name, False)
            return self.robots[name]

    def listing(self) -> list[dict[str, Any]]:
        """The robots heard, by name, and whether each one's bridge is alive now."""
        with self._lock:
            return [{"name": name, "online": self.online[name]} for name in sorted(self.online)]

    def _handler(self, name: str) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                robot = check_robot(robot_of(str(sample.key_expr)))
                payload = json.loads(sample.payload.to_bytes())
            except ValueError:
                return  # not a robot's key, or not the bridge's JSON: nothing to show
            self.robot(robot).on_sample(name, payload)

        return on_sample

    def _look_at(self, robot: str) -> None:
        """Ask the state keys of ``robot`` (``*``: every robot) for their present values:
        the bridge publishes some only when they change (``scenario``, ``status``), and a
        page must not wait for the next change to learn them."""
        for name in STATE_KEYS:
            if name == "events":
                continue  # past events are not kept: the queryable has none
            for reply in self.session.get(f"scara/{robot}/{name}", timeout=QUERY_TIMEOUT):
                if reply.ok is not None:
                    self._handler(name)(reply.ok)

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        robot = robot_of(str(sample.key_expr))
        self.robot(robot)
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            self.online[robot] = alive
        if alive:  # a bridge (re)started after this server: what it holds now, off Zenoh's thread
            threading.Thread(target=self._look_at, args=(robot,), daemon=True).start()

    def close(self) -> None:
        for entity in self._entities:
            entity.undeclare()


def send_command(session: zenoh.Session, robot: str, name: str, body: Any) -> dict[str, Any]:
    """The bridge's reply to a command: ``{"reply": ...}`` (accepted or refused, with its
    reason) or ``{"error": ...}`` (malformed, or none came: a read-only user's commands reach
    nothing). Blocking: call it off the event loop."""
    if name not in COMMANDS:
        return {"error": {"error": "malformed", "field": "name", "message": f"no command {name}"}}
    payload = None if body is None else json.dumps(body)
    replies = list(
        session.get(command_key(check_robot(robot), name), payload=payload, timeout=COMMAND_TIMEOUT)
    )
    if not replies:
        message = "no reply: this user may not command, or no bridge serves this robot"
        return {"error": {"error": "no_reply", "field": "", "message": message}}
    reply = replies[0]
    if reply.ok is not None:
        return {"reply": json.loads(reply.ok.payload.to_bytes())}
    return {"error": json.loads(reply.err.payload.to_bytes()) if reply.err else {}}
