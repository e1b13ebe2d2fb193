"""The robot as a service for the bridge's tests: router, plant, controller (service mode)
and bridge as real processes on CAN-over-Zenoh through the test's router on 127.0.0.1 (or
on SocketCAN vcan0, the router then carrying only the bridge's keys).

- :class:`Stack` holds them; :func:`start_router` starts a router and waits for it.
- :func:`latest` and :func:`command` query through a plain Zenoh client session
  (``support.open_client``).
"""

from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
from support import SLOWDOWN, Process, Processes, free_port, open_client, wait_until

from protocol.zenoh_can.config import router_reachable

ROBOT = "arm1"
START = 30.0
"""s the stack may take to come up on a loaded 2-core machine (imports, joins)."""
COMMS = ("--comms-timeout", "0.5")
"""The controller's comms-loss timeout in these tests: 0.5 s, so that a stall of the machine
holds the arm instead of latching a fault (the 0.1 s default is the co-simulation tests')."""
REPO = Path(__file__).resolve().parents[2]
SECURE_CONFIG = REPO / "config" / "zenoh" / "secure-router.json5"
PASSWORDS = dict(
    line.split(":", 1)
    for line in (REPO / "config" / "zenoh" / "credentials.txt").read_text().split()
)

STATE_KEYS = ("joints", "tcp", "coordination", "status", "events", "scenario")
RUN_TIME = 40.0
"""s a reference run may take from `run` to its end on a loaded machine (6.5 s unloaded)."""

REFERENCE = {
    "waypoints": [
        {"t": 0.0, "x": 0.30, "y": -0.25, "z": 0.25},
        {"t": 1.5, "x": 0.45, "y": -0.15, "z": 0.22},
        {"t": 4.0, "x": 0.43, "y": 0.20, "z": 0.22},
        {"t": 5.5, "x": 0.25, "y": 0.32, "z": 0.26},
    ],
    "obstacle": {
        "x": 0.455, "y": -0.01, "long_diameter": 0.10, "short_diameter": 0.06,
        "height": 0.30, "yaw_deg": 30.0, "tool_radius": 0.01, "margin": 0.01,
    },
}  # fmt: skip


class Recorder:
    """Every sample of the state keys: (key, receive time, payload).

    One subscriber per key, as a monitor on the secure router must: its rules name the keys
    a reader may subscribe to, and ``scara/<robot>/**`` (which covers ``cmd/**``) is not one.
    """

    def __init__(self, session: zenoh.Session) -> None:
        self.samples: list[tuple[str, float, dict[str, Any]]] = []
        self._lock = threading.Lock()
        self._subscribers = [
            session.declare_subscriber(f"scara/{ROBOT}/{name}", self._on_sample)
            for name in STATE_KEYS
        ]

    def _on_sample(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).removeprefix(f"scara/{ROBOT}/")
        payload = json.loads(sample.payload.to_bytes())
        with self._lock:
            self.samples.append((name, time.time(), payload))

    def of(self, name: str) -> list[tuple[float, dict[str, Any]]]:
        with self._lock:
            return [(received, payload) for key, received, payload in self.samples if key == name]

    def events(self) -> list[dict[str, Any]]:
        return [payload for _, payload in self.of("events")]

    def event(self, name: str) -> dict[str, Any] | None:
        return next((e for e in self.events() if e["event"] == name), None)


def inside_obstacle(x: float, y: float) -> bool:
    obstacle = REFERENCE["obstacle"]
    yaw = math.radians(obstacle["yaw_deg"])
    dx, dy = x - obstacle["x"], y - obstacle["y"]
    u = dx * math.cos(yaw) + dy * math.sin(yaw)
    v = -dx * math.sin(yaw) + dy * math.cos(yaw)
    return (u / (obstacle["long_diameter"] / 2)) ** 2 + (
        v / (obstacle["short_diameter"] / 2)
    ) ** 2 <= 1


def latest(session: zenoh.Session, key: str, timeout: float = 2.0) -> dict[str, Any] | None:
    """The latest value of a state key from the bridge's queryable (None if no answer within
    ``timeout`` s, times SLOWDOWN)."""
    for reply in session.get(key, timeout=timeout * SLOWDOWN):
        if reply.ok is not None:
            loaded: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
            return loaded
    return None


def command(
    session: zenoh.Session, name: str, body: Any = None, timeout: float = 5.0
) -> tuple[bool, dict[str, Any]]:
    """Send a command; ``(ok, reply)``: ok is False for an error reply (malformed). The reply
    is waited for ``timeout`` s (times SLOWDOWN)."""
    payload = None if body is None else json.dumps(body)
    key = f"scara/{ROBOT}/cmd/{name}"
    replies = list(session.get(key, payload=payload, timeout=timeout * SLOWDOWN))
    assert len(replies) == 1, f"{name}: {len(replies)} replies"
    reply = replies[0]
    if reply.ok is not None:
        return True, json.loads(reply.ok.payload.to_bytes())
    return False, json.loads(reply.err.payload.to_bytes())


@dataclass
class Stack:
    processes: Processes
    can_port: int
    zenoh_port: int
    """The port where the robot's keys live (the CAN router's, or the secure router's)."""
    bridge_args: list[str]
    on_vcan: bool = False
    """The nodes and the bridge on SocketCAN vcan0 (the ``hil`` tier), not on CAN over Zenoh."""
    plant: Process | None = None
    controller: Process | None = None
    bridge: Process | None = None

    @property
    def bus(self) -> list[str]:
        if self.on_vcan:
            return ["--interface", "socketcan", "--channel", "vcan0"]
        return [
            "--interface", "zenoh", "--channel", f"robot{self.can_port}",
            "--bus-option", f"port={self.can_port}",
        ]  # fmt: skip

    def start_bridge(self, *extra: str) -> Process:
        self.bridge = self.processes.start(
            "bridge.node",
            "--zenoh-port", str(self.zenoh_port), *self.bridge_args, *self.bus, *extra,
            name=f"bridge#{len(self.processes.started)}",
        )  # fmt: skip
        return self.bridge

    def wait_ready(self, session: zenoh.Session) -> dict[str, Any]:
        """The bridge's status once it hears both nodes ready (the first one that does)."""
        found: dict[str, Any] = {}

        def ready() -> bool:
            for process in (self.plant, self.controller, self.bridge):
                assert process is None or process.poll() is None, self.processes.outputs()
            status = latest(session, f"scara/{ROBOT}/status", timeout=1.0)
            if status is None:
                return False
            found.update(status)
            return bool(
                status["controller"]["alive"]
                and status["plant"]["alive"]
                and status["controller"]["state"] == "ready"
            )

        wait_until(ready, START, "the bridge to hear a ready controller and plant")
        return found


def start_router(
    processes: Processes,
    *args: str,
    name: str,
    user: str | None = None,
    ca: Path | None = None,
    client: Path | None = None,
) -> int:
    """Start a router on a free port; wait until it answers (as ``user``, if it needs one;
    over TLS with the CA ``ca``, showing the client certificate of the ``scara-certs`` set
    ``client`` to a router that asks for one)."""
    port = free_port()
    router = processes.start("protocol.zenoh_can.router", "--port", str(port), *args, name=name)
    shown: dict[str, Path] = {}
    if client is not None:
        shown = {"certificate": client / "client.pem", "key": client / "client-key.pem"}

    def answers() -> bool:
        if user is None and ca is None:
            return router_reachable("127.0.0.1", port)
        password = None if user is None else PASSWORDS[user]
        try:
            session = open_client(port, user, password, ca=ca, **shown)
        except zenoh.ZError:
            return False
        try:
            return bool(session.info.routers_zid())
        finally:
            session.close()  # type: ignore[no-untyped-call]

    wait_until(lambda: router.poll() is not None or answers(), START, f"{name} to answer")
    assert router.poll() is None, router.output()
    return port
