"""The operator's side of a soak: Zenoh sessions as the ``operator`` and the read-only
``monitor`` user, a watch on the robot's status, and the driver that runs task after task
through the paper's five buttons and resets what faults.

Everything goes through the bridge's keys on the secure router, as any operator's would; the
key names are ``protocol/keys.py``'s.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import zenoh

from bridge.session import ZenohEndpoint
from protocol.keys import DEFAULT_ROBOT, command_key, state_key
from protocol.scenario import Scenario, obstacle_document
from protocol.zenoh_can.config import DEFAULT_HOST, close
from soak.check import UP

STABLE = 1.0
"""s the system must stay up to count as back after a disturbance."""
WATCH_PERIOD = 0.1
"""s between two looks at the robot's status."""
ANSWER_TIME = 5.0
"""s a command's reply may take: the bridge waits 2 s for the controller, a world 1 s."""
AWAY_FROM_HOME = ("approach_blocked", "inside_obstacle")
"""Refusals a reset cures: the arm (where the last run left it) is in the way of the task's
start or under its obstacle, and a reset brings it home, where every soak task can start."""
RETRIES = 3
"""Runs of one task that may end otherwise than done before the driver moves on."""
RESET_EVERY = 1.0
"""s between two resets of a system that stays faulted."""
START_SEEN = 5.0
"""s after a run was accepted within which the status must show it running (else it ended
before the watch saw it: counted as ended otherwise)."""


class Operator:
    """Zenoh client sessions on the robot's keys: one per user."""

    def __init__(self, port: int, users: dict[str, str], robot: str = DEFAULT_ROBOT) -> None:
        self.robot = robot
        self.session = ZenohEndpoint(DEFAULT_HOST, port, "operator", users["operator"]).open()
        self.reader = ZenohEndpoint(DEFAULT_HOST, port, "monitor", users["monitor"]).open()

    def command(
        self, name: str, body: Any = None, *, read_only: bool = False, timeout: float = ANSWER_TIME
    ) -> dict[str, Any] | None:
        """Send a command; its reply (an error reply's body too), or None if none came."""
        session = self.reader if read_only else self.session
        payload = None if body is None else json.dumps(body)
        for reply in session.get(command_key(self.robot, name), payload=payload, timeout=timeout):
            sample = reply.ok if reply.ok is not None else reply.err
            if sample is not None:
                loaded: dict[str, Any] = json.loads(sample.payload.to_bytes())
                return loaded
        return None

    def status(self) -> dict[str, Any] | None:
        """The bridge's latest status; None if no bridge answers."""
        for reply in self.session.get(state_key(self.robot, "status"), timeout=0.5):
            if reply.ok is not None:
                loaded: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
                return loaded
        return None

    def close(self) -> None:
        for session in (self.session, self.reader):
            close(session)


def is_up(status: dict[str, Any] | None) -> bool:
    """Both nodes heard, and each ready or running."""
    if status is None:
        return False
    controller, plant = status["controller"], status["plant"]
    return bool(
        controller["alive"]
        and plant["alive"]
        and controller["state"] in UP
        and plant["state"] in UP
    )


@dataclass
class Watch:
    """The robot's status every :data:`WATCH_PERIOD`: when it was up, and the faults it
    raised and cleared (a node entering fault or e-stop, and leaving it)."""

    operator: Operator
    latest: dict[str, Any] | None = None
    ups: list[tuple[float, bool]] = field(default_factory=list)
    raised: dict[str, int] = field(default_factory=dict)
    cleared: dict[str, int] = field(default_factory=dict)
    _states: dict[str, str] = field(default_factory=dict)
    _stop: threading.Event = field(default_factory=threading.Event)

    def run(self) -> None:
        while not self._stop.is_set():
            try:
                status = self.operator.status()
            except zenoh.ZError:
                status = None
            self.latest = status
            self.ups.append((time.monotonic(), is_up(status)))
            if status is not None:
                for node in ("controller", "plant"):
                    self._count(node, status[node]["state"], status[node]["faults"])
            self._stop.wait(WATCH_PERIOD)

    def _count(self, node: str, state: str, faults: list[str]) -> None:
        before = self._states.get(node)
        self._states[node] = state
        latched = ("fault", "estop")
        if state in latched and before not in latched:
            for fault in faults or [state]:
                key = f"{node}.{fault}"
                self.raised[key] = self.raised.get(key, 0) + 1
        elif before in latched and state not in latched:
            self.cleared[node] = self.cleared.get(node, 0) + 1

    def back_after(self, moment: float) -> float | None:
        """s from ``moment`` until the system was up to stay (for :data:`STABLE` s): a
        disturbance may show only after it ended (a paused plant's fault comes once the
        controller has waited its comms timeout); None if it never was."""
        since: float | None = None
        for when, up in self.ups:
            if when < moment:
                continue
            if not up:
                since = None
            elif since is None:
                since = when
            elif when - since >= STABLE:
                return since - moment
        return None

    def stop(self) -> None:
        self._stop.set()


@dataclass
class Tally:
    """What the driver did."""

    started: int = 0
    completed: int = 0
    ended_otherwise: int = 0
    skipped: int = 0
    refusals: dict[str, int] = field(default_factory=dict)
    resets: int = 0

    def refused(self, reason: str) -> None:
        self.refusals[reason] = self.refusals.get(reason, 0) + 1


class Driver:
    """Task after task: set waypoints, obstacle and mode, run, wait for the run's end; a
    faulted or e-stopped system is reset; a run that ended otherwise than done is run again
    (at most :data:`RETRIES` times)."""

    def __init__(self, operator: Operator, watch: Watch, tasks: Any) -> None:
        self.operator = operator
        self.watch = watch
        self.tasks = tasks
        """Callable: the number of a task -> its scenario."""
        self.tally = Tally()
        self.number = 0
        self.task: Scenario = tasks(0)
        self._tries = 0
        self._pressing: list[tuple[str, Any]] = []
        """The buttons of the task under way not yet accepted."""
        self._running = False
        self._seen_running = False
        self._accepted_at = 0.0
        self._last_reset = -float("inf")

    def step(self) -> None:
        """One decision on the latest status."""
        status = self.watch.latest
        if status is None:
            return
        controller, plant = status["controller"], status["plant"]
        states = (controller["state"], plant["state"])
        if "fault" in states or "estop" in states:
            self._run_ended(done=False)
            if time.monotonic() - self._last_reset > RESET_EVERY:
                self._last_reset = time.monotonic()
                self.tally.resets += 1
                self.operator.command("reset")
            return
        if not is_up(status):
            return
        if controller["state"] == "running":
            self._seen_running = self._running
            return
        if self._running:
            if self._seen_running:
                self._run_ended(done=controller["progress"] >= 100)
            elif time.monotonic() - self._accepted_at > START_SEEN:
                self._run_ended(done=False)
            return
        self._start()

    def _run_ended(self, done: bool) -> None:
        if not self._running:
            return
        self._running = False
        if done:
            self.tally.completed += 1
            self._next()
            return
        self.tally.ended_otherwise += 1
        self._tries += 1
        if self._tries >= RETRIES:
            self.tally.skipped += 1
            self._next()

    def _next(self) -> None:
        self.number += 1
        self.task = self.tasks(self.number)
        self._tries = 0
        self._pressing = []

    def current_obstacle(self) -> dict[str, Any]:
        """The obstacle command's body of the task under way."""
        task = self.task
        obstacle = (
            None if task.obstacle is None else obstacle_document(task.obstacle, task.tool_radius)
        )
        return {"obstacle": obstacle}

    def _buttons(self) -> list[tuple[str, Any]]:
        """The five buttons for the task under way: no obstacle (the new waypoints may stand
        in the old one), waypoints, obstacle, mode, run."""
        task = self.task
        waypoints = [{"t": w.t, "x": w.x, "y": w.y, "z": w.z} for w in task.waypoints]
        return [
            ("obstacle", {"obstacle": None}),
            ("waypoints", {"waypoints": waypoints}),
            ("obstacle", self.current_obstacle()),
            ("mode", {"mode": task.mode.value}),
            ("run", None),
        ]

    def _start(self) -> None:
        """Press the task's next button; one refused or unanswered is pressed again at the
        next step (the controller answers once the plant holds the world, a frame of the
        transfer may be lost), after a reset if the arm is where the task cannot start or
        its obstacle stands."""
        if not self._pressing:
            self._pressing = self._buttons()
        name, body = self._pressing[0]
        reply = self.operator.command(name, body)
        first = len(self._pressing) == len(self._buttons())
        if first and reply is not None and reply.get("reason") == "no_scenario":
            reply = {"accepted": True}  # no task yet: no obstacle to take away
        if reply is None or not reply.get("accepted"):
            reason = "no_reply" if reply is None else str(reply.get("reason", "error"))
            self.tally.refused(f"{name}:{reason}")
            if reason in AWAY_FROM_HOME:
                self.operator.command("reset")
                self.tally.resets += 1
            return
        self._pressing.pop(0)
        if self._pressing:
            return
        self.tally.started += 1
        self._running = True
        self._seen_running = False
        self._accepted_at = time.monotonic()
