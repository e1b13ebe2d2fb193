"""A fleet in one page: two robots served beside each other on one machine (``scara-run
--serve --secure --robot NAME`` twice, sharing the routers), one ``scara-gui`` logged in as
the operator. The page lists both, switches between them, shows the one chosen and commands
it, not the other: checked on each robot's own Zenoh keys. The GUI's server listens on
loopback only."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import zenoh
from gui_stack import start_gui
from robot_stack import COMMS
from support import VIEWPORT, Processes, free_port, listening_sockets, open_client, wait_until

pytestmark = [pytest.mark.browser, pytest.mark.timeout(240)]

ROBOTS = ("arm1", "arm2")
USERS = {"bridge": "b-5d21", "operator": "o-c8e0", "monitor": "m-94b7"}
START = 30.0
"""s a robot may take to come up on a loaded 2-core machine (imports, joins)."""


def latest(session: zenoh.Session, robot: str, name: str) -> dict[str, Any] | None:
    for reply in session.get(f"scara/{robot}/{name}", timeout=2.0):
        if reply.ok is not None:
            loaded: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
            return loaded
    return None


def state(session: zenoh.Session, robot: str) -> str | None:
    status = latest(session, robot, "status")
    return None if status is None else str(status["controller"]["state"])


def test_two_robots_served_side_by_side_one_page_switches_and_commands_the_one_shown(
    browser: Any, processes: Processes, tmp_path: Path
) -> None:
    credentials = tmp_path / "users.txt"
    credentials.write_text("".join(f"{user}:{word}\n" for user, word in USERS.items()))
    credentials.chmod(0o600)
    can_port, secure_port = free_port(), free_port()
    session: zenoh.Session | None = None
    for robot in ROBOTS:  # the second joins the routers the first started
        launcher = processes.start(
            "sim.launch", "reference", "--serve", "--secure", "--credentials", str(credentials),
            "--secure-port", str(secure_port), "--robot", robot, "--out", str(tmp_path / robot),
            *COMMS,
            "--interface", "zenoh", "--bus-option", f"port={can_port}", name=f"scara-run-{robot}",
        )  # fmt: skip

        def ready(robot: str = robot, launcher: Any = launcher) -> bool:
            nonlocal session
            assert launcher.poll() is None, processes.outputs()
            if session is None:
                try:
                    session = open_client(secure_port, "operator", USERS["operator"])
                except zenoh.ZError:
                    return False
            return state(session, robot) == "ready"

        wait_until(ready, START, f"{robot} to be ready")
    assert session is not None
    password = tmp_path / "operator.password"
    password.write_text(USERS["operator"])
    url = start_gui(
        processes, "--zenoh-port", str(secure_port), "--user", "operator",
        "--password-file", str(password), name="gui",
    )  # fmt: skip
    listening = listening_sockets(processes.started[-1].pid)
    if listening is not None:  # the kernel agrees: one web server on loopback, nothing else
        assert listening == [("127.0.0.1", int(url.rstrip("/").rsplit(":", 1)[1]))], listening
    page = browser.new_page(viewport=VIEWPORT)
    try:
        page.goto(url)

        def listed() -> list[str]:
            return list(page.eval_on_selector_all("#robot option", "o => o.map(x => x.text)"))

        wait_until(lambda: listed() == list(ROBOTS), 10.0, f"both robots listed online: {ROBOTS}")
        assert page.evaluate("window.scara.robot") == "arm1"  # the default robot first
        page.select_option("#robot", "arm2")

        def shows(robot: str) -> bool:
            joints = latest(session, robot, "joints")
            shown = page.evaluate("(window.scara.latest.joints || {}).position")
            return joints is not None and shown == joints["position"]

        wait_until(lambda: page.evaluate("window.scara.robot") == "arm2" and shows("arm2"),
                   10.0, "the page to show arm2")  # fmt: skip
        still = latest(session, "arm1", "joints")
        page.click("[data-command=run]")
        wait_until(
            lambda: page.inner_text("#answer-run") == "accepted", 10.0, "arm2's run accepted"
        )
        wait_until(lambda: state(session, "arm2") in ("running", "hold"), 10.0, "arm2 to run")
        moving = page.evaluate("window.scara.latest.joints.position")
        wait_until(
            lambda: page.evaluate("window.scara.latest.joints.position") != moving,
            10.0,
            "the page to show arm2 moving",
        )
        page.screenshot(path=tmp_path / "arm2-running.png")
        assert state(session, "arm1") == "ready"
        arm1 = latest(session, "arm1", "joints")
        assert still is not None and arm1 is not None and arm1["position"] == still["position"]
        page.click("[data-command=stop]")
        wait_until(lambda: state(session, "arm2") not in ("running", "hold"), 10.0, "arm2 to stop")
        assert state(session, "arm1") == "ready"  # the stop went to arm2 alone
        page.select_option("#robot", "arm1")
        wait_until(lambda: page.evaluate("window.scara.robot") == "arm1" and shows("arm1"),
                   10.0, "the page to show arm1 again")  # fmt: skip
    finally:
        page.close()
        session.close()  # type: ignore[no-untyped-call]
