"""What each page is sent (``gui/state.py``), the command line's refusals and the server's
own refusal of a read-only page's command: no browser, no process."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

import pytest
from robot_stack import REFERENCE

from gui.cli import main
from gui.recording import Recording
from gui.server import Gui, PageSocket
from gui.state import PATH_POINTS, RobotState
from protocol.scenario import Scenario

BASE = Scenario("test", (), None)
PAUSED = 2.0
"""s a recording stands paused in the test of pausing (a stall of the machine shorter than
this cannot fail it)."""


def tcp(t: float) -> dict[str, Any]:
    return {"t": t, "seq": 0, "x": 0.3, "y": t, "z": 0.2}


def test_a_page_gets_everything_first_then_only_what_is_new() -> None:
    state = RobotState(BASE)
    state.on_sample("tcp", tcp(0.0))
    full, cursor = state.since(None)
    assert full is not None and full["full"] and full["path"] == [[0.3, 0.0, 0.2]]
    assert state.since(cursor) == (None, cursor)
    state.on_sample("tcp", tcp(1.0))
    update, cursor = state.since(cursor)
    assert update is not None and not update["full"]
    assert update["path"] == [[0.3, 1.0, 0.2]] and list(update["latest"]) == ["tcp"]


def test_a_new_run_sends_its_path_whole_and_the_rest_only_as_it_changes() -> None:
    """Not the whole state: the page would rebuild its task just as the arm starts to move."""
    state = RobotState(BASE)
    state.on_sample("tcp", tcp(0.0))
    state.on_sample("scenario", {"t": 0.0, "seq": 0, "name": "task"})
    _, cursor = state.since(None)
    state.on_sample("events", {"t": 1.0, "seq": 0, "event": "run_started", "detail": {}})
    state.on_sample("tcp", tcp(1.0))
    update, cursor = state.since(cursor)
    assert update is not None and not update["full"] and update["restarted"]
    assert update["path"] == [[0.3, 1.0, 0.2]] and set(update["latest"]) == {"events", "tcp"}
    assert [event["event"] for event in update["events"]] == ["run_started"]
    state.on_sample("tcp", tcp(2.0))
    update, _ = state.since(cursor)
    assert update is not None and not update["restarted"] and update["path"] == [[0.3, 2.0, 0.2]]


def test_a_page_that_missed_part_of_the_path_gets_it_whole() -> None:
    state = RobotState(BASE)
    state.on_sample("tcp", tcp(0.0))
    _, cursor = state.since(None)
    for i in range(1, PATH_POINTS + 2):
        state.on_sample("tcp", tcp(float(i)))
    update, _ = state.since(cursor)
    assert update is not None and update["full"] and len(update["path"]) == PATH_POINTS


def test_an_arm_at_rest_neither_grows_the_path_nor_is_sent_again() -> None:
    """The bridge sends the same tool position and joints 100 times a second at rest: the
    path keeps one point (200 s at rest would have pushed the run's whole path out), and a
    sample that differs from the last only by its time stamp and count is not sent again (a
    page has nothing new to draw); the first one and any real change are."""
    state = RobotState(BASE)
    state.on_sample("tcp", tcp(0.0))
    state.on_sample("joints", {"t": 0.0, "seq": 0, "position": [0.1, 0.2, 0.0]})
    _, cursor = state.since(None)
    for seq, t in enumerate((0.01, 0.02, 0.03), start=1):
        state.on_sample("tcp", tcp(0.0) | {"t": t, "seq": seq})
        state.on_sample("joints", {"t": t, "seq": seq, "position": [0.1, 0.2, 0.0]})
    assert not state.changed_since(cursor)
    assert state.since(cursor) == (None, cursor)
    state.on_sample("joints", {"t": 0.04, "seq": 4, "position": [0.1, 0.2001, 0.0]})
    update, cursor = state.since(cursor)
    assert update is not None and update["path"] == [] and list(update["latest"]) == ["joints"]
    assert update["latest"]["joints"]["t"] == 0.04
    assert state.latest("tcp") == tcp(0.0) | {"t": 0.03, "seq": 3}  # kept, not sent


def test_a_task_comes_with_its_planned_path() -> None:
    state = RobotState(BASE)
    task = {"name": "t", "mode": "fuzzy", "elbow": "down", "settle_time": 1.0}
    state.on_sample("scenario", task | {"waypoints": REFERENCE["waypoints"]})
    update, _ = state.since(None)
    assert update is not None
    first, last = REFERENCE["waypoints"][0], REFERENCE["waypoints"][-1]
    assert update["plan"][0] == pytest.approx([first["x"], first["y"], first["z"]])
    assert update["plan"][-1] == pytest.approx([last["x"], last["y"], last["z"]])


@pytest.mark.parametrize("host", ["0.0.0.0", "192.0.2.7"])
def test_the_server_listens_on_loopback_unless_told(
    host: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["--host", host]) == 2
    assert "--host" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["--https-cert", "server.pem"], "--https-cert and --https-key go together"),
        (["--https-cert", "nowhere.pem", "--https-key", "key.pem"], "--https-cert nowhere.pem"),
    ],
)
def test_https_needs_a_certificate_and_its_key_that_are_there(
    args: list[str], said: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(args) == 2
    assert said in capsys.readouterr().err


@pytest.mark.parametrize(
    ("content", "said"),
    [
        (b"", "empty"),
        (b"\x89MCAP0\r\n" + bytes(40), "scara-record recover"),  # a writer killed early
    ],
)
def test_a_file_that_is_not_a_whole_recording_is_refused_saying_why(
    content: bytes, said: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recording = tmp_path / "run.mcap"
    recording.write_bytes(content)
    assert main([str(recording)]) == 2
    error = capsys.readouterr().err
    assert error.startswith("scara-gui: ") and str(recording) in error and said in error, error


class Sent:
    """A WebSocket that keeps what the server sends."""

    def __init__(self) -> None:
        self.sent: list[str] = []

    async def send_text(self, text: str) -> None:
        self.sent.append(text)


def test_a_read_only_server_refuses_a_command_without_sending_it() -> None:
    socket = Sent()
    page = PageSocket(socket, Gui("arm1", read_only=True, user="monitor"))  # type: ignore[arg-type]
    asyncio.run(page._command({"type": "command", "id": 3, "name": "run"}))
    assert len(socket.sent) == 1
    assert '"read_only"' in socket.sent[0] and "monitor" in socket.sent[0]


def test_a_recording_paused_then_played_goes_on_from_where_it_was_paused() -> None:
    """The time a page's recording stood paused is not played when play is pressed."""
    joints = {"t": 0.0, "seq": 0, "position": [0.0, 0.0, 0.0], "velocity": [0.0, 0.0, 0.0]}
    recording = Recording([0.0, 60.0], [("joints", joints), ("joints", joints)], BASE)
    page = PageSocket(Sent(), Gui("arm1", read_only=True, recording=recording))  # type: ignore[arg-type]

    async def pause_then_play() -> float:
        sending = asyncio.create_task(page._send_loop())
        await asyncio.sleep(PAUSED)
        assert page.player is not None and page.player.position == 0.0
        page.player.playing = True
        await asyncio.sleep(0.1)
        sending.cancel()
        return page.player.position

    position = asyncio.run(pause_then_play())
    assert 0.0 < position < PAUSED, position  # about 0.1 s played, not the pause as well


def test_only_the_arms_motion_waits_for_a_pages_send_budget(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """As a run starts, the status and the weights change just before the arm moves: they go
    to the page at once and spend nothing (the page draws them in the motion's next frame),
    so they leave the burst to the arm's first move; the motion is paced. The budget here
    refills once in 1000 s: nothing paced can go in the test's time, however slow the host."""
    monkeypatch.setattr("gui.server.SEND_RATE", 0.001)
    joints = {"t": 0.0, "seq": 0, "position": [0.0, 0.0, 0.0], "velocity": [0.0, 0.0, 0.0]}
    recording = Recording([0.0, 60.0], [("joints", joints), ("joints", joints)], BASE)
    socket = Sent()
    page = PageSocket(socket, Gui("arm1", read_only=True, recording=recording))  # type: ignore[arg-type]
    assert page.player is not None
    state = page.player.state

    def moved(angle: float) -> dict[str, Any]:
        return joints | {"position": [angle, 0.0, 0.0]}

    async def sent_after(name: str, payload: dict[str, Any], within: float) -> list[str]:
        """The keys of what is sent for ``name`` (waited for up to ``within`` s)."""
        before = len(socket.sent)
        state.on_sample(name, payload)
        deadline = time.monotonic() + within
        while len(socket.sent) == before and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.05)  # and anything sent just after it
        return [",".join(json.loads(text)["latest"]) for text in socket.sent[before:]]

    async def scenario() -> list[list[str]]:
        sending = asyncio.create_task(page._send_loop())
        await asyncio.sleep(0.5)  # the whole state: the burst's first update
        assert len(socket.sent) == 1 and json.loads(socket.sent[0])["full"]
        seen = [
            await sent_after("joints", moved(0.1), 0.5),  # the burst's second
            await sent_after("status", {"t": 0.0, "state": "running"}, 5.0),  # not paced
            await sent_after("joints", moved(0.2), 0.5),  # paced: the budget is spent
        ]
        sending.cancel()
        return seen

    assert asyncio.run(scenario()) == [["joints"], ["status"], []]
