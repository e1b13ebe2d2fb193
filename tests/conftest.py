"""Fixtures shared by the tests (helpers in ``support.py``).

- ``port``: a TCP port free on 127.0.0.1 right now.
- ``router``: a ``scara-router`` process of the test's own on a free port (its port).
- ``transport``: the CAN transport a co-simulation test runs on: CAN-over-Zenoh through the
  test's router, or SocketCAN ``vcan0``, marked ``hil`` and skipped where that device does
  not exist.
- ``processes``: children started as ``python -m MODULE ...``, killed at the end.
- ``observer_on``: a bus of the test's own that records every frame, closed at the end.
- ``virtual_pair``: a node's bus and the test's bus on a fresh python-can ``virtual`` channel.
"""

from __future__ import annotations

import itertools
import os
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import settings
from support import (
    SLOWDOWN,
    UNSAFE_WITHIN,
    Observer,
    Processes,
    Transport,
    free_port,
    hil_marks,
    stretch_lockstep_waits,
    wait_until,
)

from controller.safety import Filtered, filtered
from protocol.zenoh_can.config import router_reachable

# Shared machines are noisy: no per-example deadlines. In CI the examples are derived from
# the test itself, so a run is repeatable and a red CI is never a roll of the dice; locally
# they stay random, which is how new counterexamples are found.
settings.register_profile("local", deadline=None)
settings.register_profile("ci", deadline=None, derandomize=True)
settings.load_profile("ci" if os.environ.get("CI") else "local")


def pytest_configure(config: pytest.Config) -> None:
    """SIGINT back to Python's own handler here, so that the processes the tests start and
    stop with SIGINT (python-can's tools among them) do not inherit it ignored from a shell
    without job control that started the tests in the background (a script's ``cmd &``);
    our own commands stop on SIGINT either way (``protocol.cli.interruptible``). And the
    product's lockstep waits stretched by SLOWDOWN for every process the tests start
    (``support.stretch_lockstep_waits``)."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    stretch_lockstep_waits()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Stretch each test's time limit (pytest-timeout's) by SLOWDOWN."""
    if SLOWDOWN == 1.0:
        return
    default = float(config.getini("timeout") or 0)
    for item in items:
        marker = item.get_closest_marker("timeout")
        limit = float(marker.args[0]) if marker is not None and marker.args else default
        if limit > 0:
            item.add_marker(pytest.mark.timeout(limit * SLOWDOWN), append=False)


ROUTER_START = 15.0
"""s a router process may take to import and listen (a loaded 2-core machine)."""


@pytest.fixture
def port() -> int:
    return free_port()


@pytest.fixture
def processes(tmp_path: Path) -> Iterator[Processes]:
    folder = tmp_path / "processes"
    folder.mkdir()
    started = Processes(folder)
    try:
        yield started
    finally:
        started.close()


@pytest.fixture
def router(processes: Processes) -> int:
    """A router process on a free port, up and answering; its port."""
    router_port = free_port()
    process = processes.start(
        "protocol.zenoh_can.router", "--port", str(router_port), name="router"
    )
    wait_until(
        lambda: process.poll() is not None or router_reachable("127.0.0.1", router_port),
        ROUTER_START,
        "the router to answer",
    )
    assert process.poll() is None, process.output()
    return router_port


@pytest.fixture(
    params=[
        pytest.param("zenoh", id="zenoh"),
        pytest.param("socketcan", id="socketcan", marks=hil_marks()),
    ]
)
def transport(request: pytest.FixtureRequest) -> Transport:
    if request.param == "socketcan":
        return Transport("socketcan", "vcan0")
    router_port: int = request.getfixturevalue("router")
    return Transport("zenoh", f"cosim{router_port}", {"port": router_port})


SETTLE = 0.3
"""s an observing bus gets for its subscription to spread before the nodes start."""


@pytest.fixture
def observer_on() -> Iterator[Callable[[Any], Observer]]:
    """``observer_on(transport)`` opens an observing bus before the nodes start."""
    opened: list[Observer] = []

    def open_observer(transport: Any) -> Observer:
        observer = Observer(transport.open_bus())
        opened.append(observer)
        time.sleep(SETTLE)
        return observer

    try:
        yield open_observer
    finally:
        for observer in opened:
            observer.close()


_channels = itertools.count()


@pytest.fixture
def virtual_pair() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    """A node's bus and the test's bus on a fresh in-process ``virtual`` channel."""
    channel = f"pair-{next(_channels)}"
    node_bus = can.Bus(interface="virtual", channel=channel)
    peer = can.Bus(interface="virtual", channel=channel)
    yield node_bus, peer
    node_bus.shutdown()
    peer.shutdown()


@pytest.fixture
def no_safe_motion_near(monkeypatch: pytest.MonkeyPatch) -> None:
    """The safety filter, its commands unchanged, reporting no safe motion wherever its
    barrier lets the clearance fall, but at less than 0.2 m/s: within about UNSAFE_WITHIN of
    an obstacle, at the default safety_rate (with none, the barrier's bound is 0). A feasible
    task never leaves the real filter without a safe command, so the tests of what follows
    stand this in for it."""

    def unsafe(ops: Any, wanted: Any, box: Any, barrier: Any) -> Filtered:
        command, verdict = filtered(ops, wanted, box, barrier)
        near = (barrier.b > -10.0 * UNSAFE_WITHIN) & (barrier.b < 0.0)
        return Filtered(command, verdict | near)

    monkeypatch.setattr("controller.control_law.filtered", unsafe)
