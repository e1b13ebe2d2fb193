"""The web side: one page (``static/index.html``) and one WebSocket per open page.

Kept thin: state goes out as the pages' JSON (:meth:`gui.state.RobotState.since`, the arm's
motion at :data:`SEND_RATE` per page), commands come in and go out as the bridge's queries,
its reply going back to the page that asked. Each page has a sending loop of its own, so a
slow page gets larger updates, and never holds the others up.

Messages to the page: ``hello`` (once: live or recording, read-only or not, the arm's
geometry), ``robots`` (the fleet, on change), ``state`` (``full`` or what is new, the
``time`` it is at), ``reply`` (a command's answer), ``playback`` (recording: position,
playing, speed). From the page: ``select`` (a robot), ``command`` (``name``, ``body``,
``id``), and for a recording ``seek``, ``play``, ``speed``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
from starlette.applications import Starlette
from starlette.responses import FileResponse
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket, WebSocketDisconnect

from gui.access import guards
from gui.live import Fleet, send_command
from gui.recording import SPEEDS, Player, Recording
from gui.state import Cursor, RobotState, geometry
from protocol.config import RobotConfig

log = logging.getLogger("scara.gui")

STATIC = Path(__file__).resolve().parent / "static"
SEND_RATE = 40.0
"""Updates of the arm's motion (:data:`gui.state.MOTION_KEYS`) per second to each page at
most, over time (:data:`BURST` may go back to back after a pause; the bridge publishes the
joints at 100 Hz). Every such update is a frame the browser draws: without a GPU (software
WebGL and compositing), two pages of a recording playing drew 47 frames a second each at 50
updates and took 1.3 cores of a 2-core machine; at 40 updates, 38 frames and 1.1 cores. Still
above the 30 frames a second a page must show (``benchmarks/bench_gui.py``)."""
BURST = 2
"""Updates of the motion that may go back to back after a pause: the arm's first move after
a rest goes out at once, and over a run the pages still get SEND_RATE."""
POLL = 0.002
"""s between two looks for a change, once a page is up to date."""
MAX_MESSAGE = 256 * 1024
"""Bytes a page's message may take (the bridge refuses a command over 64 KiB)."""


class SendBudget:
    """When a page's next update may go: a token bucket, ``rate`` a second over time and
    ``burst`` back to back after a pause. The clock is the caller's."""

    def __init__(self, rate: float, burst: int, now: float) -> None:
        self.rate = rate
        self.burst = float(burst)
        self._tokens = self.burst
        self._at = now

    def wait(self, now: float) -> float:
        """s until an update may go (0: it may go now)."""
        self._refill(now)
        return max(0.0, (1.0 - self._tokens) / self.rate)

    def spend(self, now: float) -> None:
        """An update went at ``now``."""
        self._refill(now)
        self._tokens -= 1.0

    def _refill(self, now: float) -> None:
        self._tokens = min(self.burst, self._tokens + (now - self._at) * self.rate)
        self._at = now


@dataclass
class Gui:
    """What every page shares: live (a Zenoh session and its fleet) or a recording."""

    robot: str
    """The robot a new page shows first."""
    read_only: bool
    user: str | None = None
    session: zenoh.Session | None = None
    fleet: Fleet | None = None
    recording: Recording | None = None

    @property
    def robot_config(self) -> RobotConfig:
        if self.recording is not None:
            return self.recording.scenario.robot
        assert self.fleet is not None
        return self.fleet.base.robot


class PageSocket:
    """One open page: its robot, its cursor, its player (for a recording)."""

    def __init__(self, websocket: WebSocket, gui: Gui) -> None:
        self.websocket = websocket
        self.gui = gui
        self.robot = gui.robot
        self.cursor: Cursor | None = None
        self.player = Player(gui.recording) if gui.recording is not None else None
        self._send_lock = asyncio.Lock()
        self._tasks: set[asyncio.Task[None]] = set()

    async def send(self, message: dict[str, Any]) -> None:
        async with self._send_lock:
            await self.websocket.send_text(json.dumps(message))

    async def serve(self) -> None:
        gui = self.gui
        hello: dict[str, Any] = {
            "type": "hello",
            "mode": "recording" if gui.recording is not None else "live",
            "read_only": gui.read_only,
            "user": gui.user,
            "robot": self.robot,
            "geometry": geometry(gui.robot_config),
        }
        if gui.recording is not None:
            hello |= {"duration": gui.recording.duration, "speeds": SPEEDS}
        await self.send(hello)
        sending = asyncio.create_task(self._send_loop())
        try:
            while True:
                received = await self.websocket.receive()
                if received["type"] == "websocket.disconnect":
                    raise WebSocketDisconnect(received.get("code", 1000))
                try:
                    message = json.loads(received["text"])
                    kind = message["type"]
                except (ValueError, KeyError, TypeError):  # not text, not JSON, no type
                    await self.send({"type": "error", "message": "not a JSON object with a type"})
                    continue
                await self._on_message(kind, message)
        except WebSocketDisconnect:
            pass
        finally:
            sending.cancel()
            for task in self._tasks:
                task.cancel()

    def _state(self) -> RobotState:
        if self.player is not None:
            return self.player.state
        assert self.gui.fleet is not None
        return self.gui.fleet.robot(self.robot)

    async def _send_loop(self) -> None:
        listing: list[dict[str, Any]] = []
        last = time.monotonic()
        budget = SendBudget(SEND_RATE, BURST, last)
        while True:
            while not self._pending(listing):
                await asyncio.sleep(POLL)
                last = time.monotonic()  # time spent waiting is not time a recording played
            now = time.monotonic()
            if self._draws_at_once():
                if wait := budget.wait(now):
                    await asyncio.sleep(wait)
                    continue
                budget.spend(now)
            elapsed, last = now - last, now
            if self.gui.fleet is not None and (fleet := self.gui.fleet.listing()) != listing:
                listing = fleet
                await self.send({"type": "robots", "robots": listing})
            if self.player is not None:
                was_playing = self.player.playing
                self.player.advance(elapsed)
                if was_playing:
                    await self.send(self._playback())
            update, self.cursor = self._state().since(self.cursor)
            if update is not None:
                clock = self.player.time if self.player is not None else time.time()
                await self.send(update | {"type": "state", "robot": self.robot, "time": clock})

    def _pending(self, listing: list[dict[str, Any]]) -> bool:
        """Something to send: the robot's state or the fleet changed, or a recording plays."""
        if self.player is not None and self.player.playing:
            return True
        if self.gui.fleet is not None and self.gui.fleet.listing() != listing:
            return True
        return self._state().changed_since(self.cursor)

    def _draws_at_once(self) -> bool:
        """Whether what is to send makes the page draw a frame at once: the arm's motion, or a
        recording playing. Only that spends the budget; a status, events or the weights go at
        once (the page draws them in the motion's next frame). As a run started those spent
        the burst, and the arm's first move then waited 11-18 ms for the budget."""
        if self.player is not None and self.player.playing:
            return True
        return self._state().moved_since(self.cursor)

    def _playback(self) -> dict[str, Any]:
        assert self.player is not None
        player = self.player
        return {
            "type": "playback",
            "position": player.position,
            "playing": player.playing,
            "speed": player.speed,
        }

    async def _on_message(self, kind: str, message: dict[str, Any]) -> None:
        if kind == "select" and self.gui.fleet is not None:
            self.robot = str(message.get("robot", self.robot))
            self.cursor = None  # the whole state of the robot switched to
        elif kind == "command":
            task = asyncio.create_task(self._command(message))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        elif self.player is not None and kind in ("seek", "play", "speed"):
            self._on_playback(kind, message)
            await self.send(self._playback())

    def _on_playback(self, kind: str, message: dict[str, Any]) -> None:
        assert self.player is not None
        value = message.get("value")
        if kind == "seek" and isinstance(value, int | float):
            self.player.seek(float(value))
            self.cursor = None
        elif kind == "play":
            if self.player.position >= self.player.recording.duration:
                self.player.seek(0.0)
                self.cursor = None
            self.player.playing = bool(value)
        elif kind == "speed" and value in SPEEDS:
            self.player.speed = float(value)

    async def _command(self, message: dict[str, Any]) -> None:
        """The bridge's answer to a page's command, or this server's refusal."""
        name = str(message.get("name"))
        answer = {"type": "reply", "id": message.get("id"), "name": name, "robot": self.robot}
        refusal = self._refusal()
        if refusal is not None:
            await self.send(answer | {"error": {"error": "read_only", "message": refusal}})
            return
        assert self.gui.session is not None
        try:
            result = await asyncio.to_thread(
                send_command, self.gui.session, self.robot, name, message.get("body")
            )
        except (ValueError, zenoh.ZError) as error:
            result = {"error": {"error": "malformed", "message": str(error)}}
        log.info("%s %s: %s", self.robot, name, result)
        await self.send(answer | result)

    def _refusal(self) -> str | None:
        """Why this server sends no command, if it does not."""
        if self.gui.recording is not None:
            return "a recording takes no commands"
        if self.gui.read_only:
            return f"read-only: this scara-gui joined as {self.gui.user or 'a reader'}"
        return None


def build_app(gui: Gui, hosts: Sequence[str]) -> Starlette:
    """The page, its files and its WebSocket, for requests that name one of ``hosts`` and
    come from this server's own page (:mod:`gui.access`)."""

    async def index(request: Any) -> FileResponse:
        return FileResponse(STATIC / "index.html")

    async def page_socket(websocket: WebSocket) -> None:
        await websocket.accept()
        with contextlib.suppress(WebSocketDisconnect, RuntimeError):  # a page closed mid-send
            await PageSocket(websocket, gui).serve()

    return Starlette(
        routes=[
            Route("/", index),
            WebSocketRoute("/ws", page_socket),
            Mount("/static", StaticFiles(directory=STATIC), name="static"),
        ],
        middleware=guards(hosts),
    )
