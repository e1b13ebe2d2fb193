"""The robot as a service, as ``scara-run --serve --secure`` starts it, plus a recorder, with
each process under the soak's hand: started, paused, killed and started again.

The command lines are ``sim/launch.py``'s (one place for how a process is started); the
soak adds the wire faults of each node's start, a file per recorder start, and its own
ports. Every process is a child in its own process group, its output in ``logs/``.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from protocol.errors import ScaraError
from protocol.faults import FaultSpec
from protocol.zenoh_can.config import DEFAULT_HOST, free_port, router_reachable
from sim import launch
from soak.schedule import HOME_SCENARIO, PROCESSES

COMMS_TIMEOUT = 0.5
"""s the controller goes without a fresh joint state before it latches a fault: the bridge
tests' (a stall of a loaded 2-core machine holds the arm rather than faulting it; a pause of
the plant up to 500 ms does fault it, now and then)."""
ROUTER_START = 20.0
"""s a router may take to answer after it was started (a loaded machine)."""
RECORDINGS = "recordings"
"""The folder of a soak's recordings (one file per recorder start)."""


@dataclass
class Child:
    """One process of the stack and its starts."""

    name: str
    starts: int = 0
    popen: subprocess.Popen[bytes] | None = None
    started_at: float = 0.0
    lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def pid(self) -> int | None:
        return None if self.popen is None or self.popen.poll() is not None else self.popen.pid


class Stack:
    """Routers, plant, controller service, bridge and recorder on ports of their own."""

    def __init__(self, folder: Path, wire: dict[str, list[FaultSpec]] | None = None) -> None:
        self.folder = folder
        self.can_port = free_port()
        self.keys_port = free_port()
        self.args = launch.build_parser().parse_args(
            [
                HOME_SCENARIO, "--serve", "--secure", "--secure-port", str(self.keys_port),
                "--interface", "zenoh", "--channel", f"soak{self.can_port}",
                "--bus-option", f"port={self.can_port}", "--out", str(folder / "nodes"),
                "--comms-timeout", str(COMMS_TIMEOUT),
            ]
        )  # fmt: skip
        self.users = launch.read_credentials(launch.CREDENTIALS)
        self.wire = wire or {}
        """The wire faults of each node's every start (the last one repeats)."""
        self.children = {name: Child(name) for name in PROCESSES}
        self.recordings: list[Path] = []
        self.killed_recordings: list[Path] = []
        (folder / "logs").mkdir(parents=True, exist_ok=True)
        (folder / RECORDINGS).mkdir(exist_ok=True)
        self._config = folder / "config"
        self._config.mkdir(exist_ok=True)

    def command(self, name: str) -> list[str]:
        """The command line of ``name``'s next start."""
        child = self.children[name]
        if name == "can_router":
            command = launch.router_command(self.args)
            if command is None:
                raise ScaraError(f"a router already answers on port {self.can_port}")
            return command
        if name == "keys_router":
            return launch.secure_router_command(self.args, self._config)
        if name == "bridge":
            return launch.bridge_command(self.args)
        if name == "recorder":
            command = launch.recorder_command(self.args)
            path = self.folder / RECORDINGS / f"run-{len(self.recordings):03d}.mcap"
            self.recordings.append(path)
            command[command.index("--out") + 1] = str(path)
            return command
        plant, controller = launch.node_commands(self.args, 0.0)
        command = plant if name == "plant" else controller
        specs = self.wire.get(name)
        if specs:
            spec = specs[min(child.starts, len(specs) - 1)]
            command += ["--inject-faults", spec.text()]
        return command

    def start(self, name: str) -> None:
        """Start ``name`` (again); a router is waited for until it answers."""
        child = self.children[name]
        with child.lock:
            command = self.command(name)
            log = self.folder / "logs" / f"{name}-{child.starts}.log"
            environment = None
            if name == "bridge":
                environment = os.environ | {
                    launch.PASSWORD_VARIABLE: self.users[launch.BRIDGE_USER]
                }
            with log.open("wb") as output:
                child.popen = subprocess.Popen(
                    command,
                    stdin=subprocess.DEVNULL,
                    stdout=output,
                    stderr=subprocess.STDOUT,
                    env=environment,
                    start_new_session=True,
                )
            child.starts += 1
            child.started_at = time.monotonic()
        if name.endswith("router"):
            user = None if name == "can_router" else launch.BRIDGE_USER
            password = None if user is None else self.users[user]
            port = self.can_port if user is None else self.keys_port
            deadline = time.monotonic() + ROUTER_START
            while not router_reachable(DEFAULT_HOST, port, user, password):
                if time.monotonic() > deadline or child.popen.poll() is not None:
                    raise ScaraError(f"{name} did not come up: see {log}")
                time.sleep(0.05)

    def start_all(self) -> None:
        for name in ("can_router", "keys_router", "recorder", "plant", "controller", "bridge"):
            self.start(name)

    def pause(self, name: str, seconds: float) -> None:
        """SIGSTOP ``name`` for ``seconds``, then SIGCONT (a killed process: nothing)."""
        child = self.children[name]
        with child.lock:
            pid = child.pid
            if pid is None:
                return
            with contextlib.suppress(ProcessLookupError):
                os.killpg(pid, signal.SIGSTOP)
            time.sleep(seconds)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(pid, signal.SIGCONT)

    def kill(self, name: str) -> None:
        """SIGKILL ``name``'s process group and wait for it; its recording is left cut."""
        child = self.children[name]
        with child.lock:
            if child.popen is None:
                return
            with contextlib.suppress(ProcessLookupError):
                os.killpg(child.popen.pid, signal.SIGKILL)
            child.popen.wait()
            if name == "recorder":
                self.killed_recordings.append(self.recordings[-1])

    def restart(self, name: str) -> None:
        self.kill(name)
        self.start(name)

    def pids(self) -> dict[str, tuple[int, int]]:
        """The live processes: name -> (pid, which start)."""
        found = {}
        for name, child in self.children.items():
            pid = child.pid
            if pid is not None:
                found[name] = (pid, child.starts - 1)
        return found

    def ended(self) -> list[str]:
        """The processes that ended by themselves (not killed by the soak)."""
        return [
            name
            for name, child in self.children.items()
            if child.popen is not None and child.popen.poll() not in (None, -signal.SIGKILL)
        ]

    def close(self) -> None:
        """Stop every process: SIGCONT (a paused one), SIGINT, SIGKILL after a grace; the
        recorder last, so that it records the others stopping."""
        order = ("bridge", "controller", "plant", "recorder", "keys_router", "can_router")
        for name in order:
            child = self.children[name]
            if child.popen is None:
                continue
            with contextlib.suppress(ProcessLookupError):
                os.killpg(child.popen.pid, signal.SIGCONT)
            launch.stop(child.popen)
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(child.popen.pid, signal.SIGKILL)  # anything it left behind
