"""Shared fixtures for the tests that run the controller and the plant as OS processes.

- ``port``: a TCP port free on 127.0.0.1 right now (bound to 127.0.0.1:0, then released).
- ``transport``: the CAN transport a co-simulation test runs on: CAN-over-Zenoh on loopback
  (its own channel and port per test), or SocketCAN ``vcan0``, marked ``hil`` and skipped
  where that device does not exist.
- ``processes``: starts ``sys.executable -m MODULE ...`` in its own process group, output
  to files; whatever is still running at the end of the test is killed.
- ``observer``: a bus opened from the test process that records every frame it sees (and
  can send), closed at the end of the test.

Network rules (DESIGN.md section 6): Zenoh only through the project's ZenohBus, on
127.0.0.1, with an explicit port; nothing here opens a Zenoh session of its own.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import settings

# Shared machines are noisy: no per-example deadlines. In CI the examples are derived from
# the test itself, so a run is repeatable and a red CI is never a roll of the dice; locally
# they stay random, which is how new counterexamples are found.
settings.register_profile("local", deadline=None)
settings.register_profile("ci", deadline=None, derandomize=True)
settings.load_profile("ci" if os.environ.get("CI") else "local")

ROOT = Path(__file__).resolve().parent.parent
VCAN0 = Path("/sys/class/net/vcan0")
SETTLE = 0.5
"""s a freshly opened Zenoh bus is given to join the mesh before it is relied on."""


def free_port() -> int:
    """A TCP port nobody holds right now on 127.0.0.1."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@pytest.fixture
def port() -> int:
    return free_port()


# --------------------------------------------------------------------------- transports


@dataclass(frozen=True)
class Transport:
    """A python-can interface + channel (+ bus keyword arguments) the nodes share."""

    interface: str
    channel: str
    options: dict[str, Any] = field(default_factory=dict)

    def cli(self) -> list[str]:
        """The node / launcher command-line flags that select this transport."""
        args = ["--interface", self.interface, "--channel", self.channel]
        for key, value in self.options.items():
            args += ["--bus-option", f"{key}={value}"]
        return args

    def open_bus(self) -> can.BusABC:
        return can.Bus(interface=self.interface, channel=self.channel, **self.options)


@pytest.fixture(
    params=[
        pytest.param("zenoh", id="zenoh"),
        pytest.param(
            "socketcan",
            id="socketcan",
            marks=[
                pytest.mark.hil,
                pytest.mark.skipif(
                    not VCAN0.exists(),
                    reason="no SocketCAN vcan0 here (see README: run -m hil in a VM)",
                ),
            ],
        ),
    ]
)
def transport(request: pytest.FixtureRequest) -> Transport:
    if request.param == "socketcan":
        return Transport("socketcan", "vcan0")
    bus_port = free_port()
    return Transport("zenoh", f"cosim{bus_port}", {"port": bus_port})


# --------------------------------------------------------------------------- processes


class Process:
    """One child process started by :class:`Processes`; output goes to a file."""

    def __init__(self, name: str, argv: Sequence[str], log: Path) -> None:
        self.name = name
        self.argv = list(argv)
        self.log = log
        self._log_file = log.open("wb")
        self.started = time.time()
        self.popen = subprocess.Popen(
            self.argv,
            cwd=ROOT,
            stdin=subprocess.DEVNULL,
            stdout=self._log_file,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # its own process group: children die with it
        )

    @property
    def pid(self) -> int:
        return self.popen.pid

    def poll(self) -> int | None:
        return self.popen.poll()

    def wait(self, timeout: float) -> int:
        """The exit code; fails the test (after killing it) if it runs past ``timeout``."""
        try:
            return self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            self.kill()
            pytest.fail(f"{self.name} still running after {timeout} s\n{self.output()}")

    def interrupt(self, grace: float = 5.0) -> int:
        """SIGINT (a node's clean stop), SIGKILL if it has not exited after ``grace`` s."""
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGINT)
            try:
                self.popen.wait(grace)
            except subprocess.TimeoutExpired:
                self.kill()
        return self.popen.returncode

    def kill(self) -> None:
        """SIGKILL to this process's group (the process itself and any children it started)."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.popen.pid, signal.SIGKILL)
        self.popen.wait(10)

    def output(self, tail: int = 4000) -> str:
        self._log_file.flush()
        text = self.log.read_text(errors="replace")
        return f"--- {self.name} (exit {self.popen.returncode}) output ---\n{text[-tail:]}"

    def close(self) -> None:
        if self.popen.poll() is None:
            self.kill()
        else:  # the group may still hold children of an exited launcher
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.popen.pid, signal.SIGKILL)
        self._log_file.close()


class Processes:
    """Starts ``python -m MODULE ARGS`` children; :meth:`close` kills what is left."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.started: list[Process] = []

    def start(self, module: str, *args: str, name: str | None = None) -> Process:
        name = name or f"{module}#{len(self.started)}"
        log = self.folder / f"{name.replace('/', '_')}.log"
        process = Process(name, [sys.executable, "-m", module, *args], log)
        self.started.append(process)
        return process

    def outputs(self) -> str:
        return "\n".join(process.output() for process in self.started)

    def close(self) -> None:
        for process in reversed(self.started):
            process.close()


@pytest.fixture
def processes(tmp_path: Path) -> Iterator[Processes]:
    folder = tmp_path / "processes"
    folder.mkdir()
    started = Processes(folder)
    try:
        yield started
    finally:
        started.close()


# --------------------------------------------------------------------------- observing


class Observer:
    """A bus of the test's own: records every frame it receives, in a background thread."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self._frames: list[can.Message] = []
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="observer", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                message = self.bus.recv(0.05)
            except can.CanError:
                return
            if message is None:
                continue
            with self._changed:
                self._frames.append(message)
                self._changed.notify_all()

    def frames(self) -> list[can.Message]:
        """Every frame received so far, in arrival order."""
        with self._lock:
            return list(self._frames)

    def wait_for(
        self, predicate: Callable[[can.Message], bool], timeout: float, start: int = 0
    ) -> can.Message | None:
        """The first frame (from index ``start`` on) satisfying ``predicate``; None on timeout."""
        deadline = time.monotonic() + timeout
        index = start
        with self._changed:
            while True:
                while index < len(self._frames):
                    if predicate(self._frames[index]):
                        return self._frames[index]
                    index += 1
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._changed.wait(min(left, 0.1))

    def send(self, frame_id: int, data: bytes) -> float:
        """Send one standard frame; return the wall-clock time it was sent."""
        sent = time.time()
        self.bus.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))
        return sent

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.bus.shutdown()


@pytest.fixture
def observer_on() -> Iterator[Callable[[Any], Observer]]:
    """``observer_on(transport)`` opens an observing bus (before the nodes start, so that on
    Zenoh it holds the well-known port and sees every frame either node sends)."""
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
