"""Fixtures of scara-gui's browser tests (marker ``browser``; ``tools/browser-setup``).

- ``browser``: Debian's headless Chromium driven by Playwright (skipped, saying why, where
  ``/usr/bin/chromium`` or Playwright is missing), one per module.
- ``robot``: the robot as a service behind the secure router (``tests/bridge/robot_stack``),
  with two ``scara-gui`` servers on it, one logged in as ``operator``, one as ``monitor``;
  one per module, so its tests leave the robot ready for the next; once on ``http`` and once
  on ``https`` (a ``scara-certs`` set, ``certs``, whose server certificate the browser
  trusts).
- ``open_page(url)``: a new page of the browser on ``url``, once it has its first state.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from gui_stack import Robot, start_gui
from robot_stack import COMMS, PASSWORDS, SECURE_CONFIG, START, Stack, start_router
from support import (
    BROWSER_ARGS,
    CHROMIUM,
    VIEWPORT,
    Processes,
    make_certificates,
    trusting,
    wait_until,
)

TASK = Path(__file__).resolve().parent / "patient_reference.toml"
"""The robot's task at start: the reference with a long timeout (see the file)."""


def browser_missing() -> str | None:
    """Why the browser tests cannot run here, or None."""
    if not CHROMIUM.exists():
        return f"no {CHROMIUM}: install it with tools/browser-setup (apt-get install chromium)"
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "no playwright: pip install -e '.[test]'"
    return None


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Every test here is a browser test, skipped with the reason where it cannot run."""
    reason = browser_missing()
    for item in items:
        here = Path(item.path).parent == Path(__file__).parent
        if reason is not None and here and item.get_closest_marker("browser"):
            item.add_marker(pytest.mark.skip(reason=reason))


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_certificates(tmp_path_factory.mktemp("certs"))


@pytest.fixture(scope="module")
def browser(certs: Path) -> Iterator[Any]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(
            executable_path=str(CHROMIUM), args=[*BROWSER_ARGS, trusting(certs / "server.pem")]
        )
        yield chromium
        chromium.close()


@pytest.fixture(scope="module", params=["http", "https"])
def robot(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory, certs: Path
) -> Iterator[Robot]:
    https = certs if request.param == "https" else None
    from robot_stack import open_client

    processes = Processes(tmp_path_factory.mktemp("processes"))
    try:
        can_port = start_router(processes, name="can-router")
        zenoh_port = start_router(
            processes, "--config", str(SECURE_CONFIG), name="secure-router", user="bridge"
        )
        passwords = {}
        for user in ("bridge", "operator", "monitor"):
            passwords[user] = processes.folder / f"{user}.password"
            passwords[user].write_text(PASSWORDS[user])
        stack = Stack(
            processes,
            can_port,
            zenoh_port,
            ["--user", "bridge", "--password-file", str(passwords["bridge"])],
        )
        stack.plant = processes.start("plant_sim.node", str(TASK), *stack.bus, name="plant")
        stack.controller = processes.start(
            "controller.cli", str(TASK), "--service", *stack.bus, *COMMS, name="controller"
        )
        stack.start_bridge()
        login = ["--zenoh-port", str(zenoh_port)]
        operator = start_gui(
            processes, *login, "--user", "operator", "--password-file", str(passwords["operator"]),
            name="gui-operator", https=https,
        )  # fmt: skip
        monitor = start_gui(
            processes, *login, "--user", "monitor", "--password-file", str(passwords["monitor"]),
            name="gui-monitor", https=https,
        )  # fmt: skip
        session = open_client(zenoh_port, "operator", PASSWORDS["operator"])
        stack.wait_ready(session)
        yield Robot(stack, operator, monitor, session)
        session.close()  # type: ignore[no-untyped-call]
    finally:
        processes.close()


@pytest.fixture
def open_page(browser: Any) -> Iterator[Callable[[str], Any]]:
    pages: list[Any] = []

    def open_one(url: str) -> Any:
        page = browser.new_page(viewport=VIEWPORT)
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.errors = errors
        page.goto(url)
        wait_until(
            lambda: page.evaluate("window.scara.stats.frames") > 0, START, "the page's first frame"
        )
        pages.append(page)
        return page

    yield open_one
    for page in pages:
        assert not page.errors, page.errors
        page.close()
