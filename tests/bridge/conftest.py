"""Fixtures of the bridge's tests (the helpers they use are in ``robot_stack``).

- ``make_stack(*bridge_args, secure=False, on_vcan=False)`` / ``stack``: router(s), plant,
  controller (service mode) and bridge as real processes, started.
- ``client(port, user=None, password=None)``: a plain Zenoh client session, closed after.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest
import zenoh
from robot_stack import COMMS, PASSWORDS, SECURE_CONFIG, Stack, open_client, start_router
from support import Processes


@pytest.fixture
def make_stack(processes: Processes) -> Callable[..., Stack]:
    """``make_stack(*bridge_args, secure=False, on_vcan=False)``: the stack on its own
    routers (on vcan0: the nodes' frames go there), started."""

    def make(*bridge_args: str, secure: bool = False, on_vcan: bool = False) -> Stack:
        can_port = start_router(processes, name="can-router")
        zenoh_port = can_port
        args = list(bridge_args)
        if secure:
            zenoh_port = start_router(
                processes, "--config", str(SECURE_CONFIG), name="secure-router", user="bridge"
            )
            password = processes.folder / "bridge.password"
            password.write_text(PASSWORDS["bridge"])
            args += ["--user", "bridge", "--password-file", str(password)]
        stack = Stack(processes, can_port, zenoh_port, args, on_vcan)
        stack.plant = processes.start("plant_sim.node", *stack.bus, name="plant")
        stack.controller = processes.start("controller.cli", *stack.bus, *COMMS, name="controller")
        stack.start_bridge()
        return stack

    return make


@pytest.fixture
def stack(make_stack: Callable[..., Stack]) -> Stack:
    return make_stack()


@pytest.fixture
def client() -> Iterator[Callable[..., zenoh.Session]]:
    opened: list[zenoh.Session] = []

    def open_one(port: int, user: str | None = None, password: str | None = None) -> zenoh.Session:
        session = open_client(port, user, password)
        opened.append(session)
        return session

    yield open_one
    for session in opened:
        session.close()
