"""What a page shows of one robot, fed sample by sample, read by each page at its own pace.

A :class:`RobotState` keeps the latest payload of every state key, the path the tool has
travelled since the last run started, the coordination weights of the last seconds, the
recent events and the planned path of the task in force. Each page holds a :class:`Cursor`
into it: :meth:`RobotState.since` gives that page what is new since its last look, or the
whole state when it has none yet (a page opened late, a robot switched to, a page fallen so
far behind that the path it missed is gone). No page ever waits for another.

Fed from Zenoh's threads (live) or from a recording's player (one per page); read from the
web server's event loop: every method takes the lock.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

from controller.planner import plan_of
from protocol.config import RobotConfig
from protocol.kinematics import reach_radii
from protocol.scenario import Scenario, parse_task

PATH_POINTS = 20_000
"""Tool positions kept for the path travelled (200 s at the bridge's 100 Hz)."""
TRACE_SECONDS = 10.0
"""s of k_T and k_C kept for the plot."""
EVENTS_KEPT = 50
PLAN_STEP = 0.02
"""s between two points of the planned path sent to the page."""
RESTART_EVENTS = ("run_started", "reset")
"""Events after which the path travelled starts again."""
MOTION_KEYS = ("joints", "tcp")
"""State keys of the arm's motion: what the page draws a frame for at once (the rest waits
for the motion's next frame), and what :data:`gui.server.SEND_RATE` paces."""
STAMPS = ("t", "seq")
"""Fields of a sample that do not show: two samples alike but for these are a repeat."""


def geometry(robot: RobotConfig) -> dict[str, float]:
    """The arm's sizes the page draws with, and the reachable annulus of the top view."""
    r_min, r_max = reach_radii(robot)
    return {
        "a1": robot.a1,
        "a2": robot.a2,
        "d0": robot.d0,
        "d3_max": robot.d3_max,
        "r_min": r_min,
        "r_max": r_max,
    }


def planned_path(task: dict[str, Any], base: Scenario) -> list[list[float]]:
    """The cubic reference through the task's waypoints (the controller's own plan, before
    the approach from wherever the arm stands), as points every :data:`PLAN_STEP`."""
    try:
        plan = plan_of(parse_task(task, base))
    except Exception:  # a task the controller took is plannable; anything else: no plan shown
        return []
    steps = max(1, math.ceil(plan.duration / PLAN_STEP))
    start = plan.times[0]
    return [list(plan.evaluate(start + plan.duration * i / steps)[0]) for i in range(steps + 1)]


@dataclass(frozen=True, slots=True)
class Cursor:
    """How far one page has read a :class:`RobotState`."""

    epoch: int
    """The path's restart count when read: a newer one sends the path again."""
    path_end: int
    trace_end: int
    events_end: int
    version: int


class Numbered:
    """A bounded list whose items keep their absolute index once older ones are gone."""

    def __init__(self, maxlen: int | None = None) -> None:
        self.items: deque[Any] = deque(maxlen=maxlen)
        self.start = 0

    @property
    def end(self) -> int:
        return self.start + len(self.items)

    def append(self, item: Any) -> None:
        if self.items.maxlen is not None and len(self.items) == self.items.maxlen:
            self.start += 1
        self.items.append(item)

    def popleft(self) -> None:
        self.items.popleft()
        self.start += 1

    def clear(self) -> None:
        self.start = self.end
        self.items.clear()

    def after(self, index: int) -> list[Any]:
        """The items from absolute ``index`` on (all kept, if older ones are gone)."""
        skip = max(0, index - self.start)
        return [item for position, item in enumerate(self.items) if position >= skip]


def _alike(first: dict[str, Any], second: dict[str, Any]) -> bool:
    """Whether two samples of a key differ at most by their :data:`STAMPS`."""
    return first.keys() == second.keys() and all(
        first[field] == second[field] for field in first if field not in STAMPS
    )


class RobotState:
    """One robot as the pages see it (see the module docstring)."""

    def __init__(self, base: Scenario) -> None:
        self.base = base
        self._lock = threading.Lock()
        self._latest: dict[str, dict[str, Any]] = {}
        self._changed: dict[str, int] = {}
        self._version = 0
        self._epoch = 0
        self._path = Numbered(PATH_POINTS)
        self._trace = Numbered()
        self._events = Numbered(EVENTS_KEPT)
        self._plan: list[list[float]] = []

    def on_sample(self, name: str, payload: dict[str, Any]) -> None:
        """One state key's sample (``joints``, ``tcp`` ..., ``scenario``)."""
        plan = planned_path(payload, self.base) if name == "scenario" else None
        with self._lock:
            previous = self._latest.get(name)
            self._latest[name] = payload
            if previous is None or not _alike(previous, payload):  # a repeat: nothing to send
                self._version += 1
                self._changed[name] = self._version
            if plan is not None:
                self._plan = plan
            if name == "tcp":
                point = [payload["x"], payload["y"], payload["z"]]
                if not self._path.items or self._path.items[-1] != point:  # not at rest
                    self._path.append(point)
            elif name == "coordination":
                self._trace.append([payload["t"], payload["k_t"], payload["k_c"]])
                while self._trace.items and self._trace.items[0][0] < payload["t"] - TRACE_SECONDS:
                    self._trace.popleft()
            elif name == "events":
                self._events.append(payload)
                if payload["event"] in RESTART_EVENTS:
                    self._path.clear()
                    self._epoch += 1

    def changed_since(self, cursor: Cursor | None) -> bool:
        """Whether :meth:`since` has anything for a page at ``cursor`` (cheap: no copy)."""
        with self._lock:
            return cursor is None or cursor != self._cursor()

    def moved_since(self, cursor: Cursor | None) -> bool:
        """Whether :meth:`since` has the arm's motion for a page at ``cursor``: the whole
        state, or a new sample of one of :data:`MOTION_KEYS` (cheap: no copy)."""
        with self._lock:
            return cursor is None or any(
                self._changed.get(name, 0) > cursor.version for name in MOTION_KEYS
            )

    def _cursor(self) -> Cursor:
        return Cursor(self._epoch, self._path.end, self._trace.end, self._events.end, self._version)

    def since(self, cursor: Cursor | None) -> tuple[dict[str, Any] | None, Cursor]:
        """What is new for a page at ``cursor``, None if nothing is; and its new cursor.

        ``full``: the whole state, for a page with no cursor or one that missed part of the
        path. ``restarted``: a run started (or a reset) since the page's look: the path it
        is sent is the new one, whole; the rest is only what changed. A new run is not sent
        whole: the page would redraw its whole task just as the arm starts to move."""
        with self._lock:
            now = self._cursor()
            if cursor is not None and cursor == now:
                return None, now
            if cursor is None or (
                cursor.epoch == self._epoch and cursor.path_end < self._path.start
            ):
                update = {
                    "full": True,
                    "restarted": False,
                    "latest": dict(self._latest),
                    "path": list(self._path.items),
                    "trace": list(self._trace.items),
                    "events": list(self._events.items),
                    "plan": self._plan,
                }
                return update, now
            restarted = cursor.epoch != self._epoch
            latest = {
                name: self._latest[name]
                for name, version in self._changed.items()
                if version > cursor.version
            }
            update = {
                "full": False,
                "restarted": restarted,
                "latest": latest,
                "path": list(self._path.items) if restarted else self._path.after(cursor.path_end),
                "trace": self._trace.after(cursor.trace_end),
                "events": self._events.after(cursor.events_end),
            }
            if "scenario" in latest:
                update["plan"] = self._plan
            return update, now

    def latest(self, name: str) -> dict[str, Any] | None:
        with self._lock:
            return self._latest.get(name)
