"""Helpers the tests share (the fixtures built on them are in ``conftest.py``).

- :func:`free_port`: a TCP port free on 127.0.0.1 right now.
- :class:`Transport`: a python-can interface + channel (+ bus keyword arguments).
- :class:`Processes`: children started as ``python -m MODULE ...`` in their own process
  groups, output to files; whatever still runs at the end is killed.
- :class:`Observer`: a bus of the test's own that records every frame it receives.
- :func:`wait_until`: a bounded wait for a condition.
- :func:`hil_marks`: the marks of a test on SocketCAN ``vcan0`` (the ``hil`` tier).
- :func:`stretch_lockstep_waits`: the product's lockstep waits stretched by SLOWDOWN.
- :func:`wait_while_growing`: a wait that fails only once progress has stopped.
- :data:`NUMPY_IS_LIBM`: whether numpy's transcendental functions give libm's bits here, and
  :data:`NOT_LIBM_TOLERANCE` where they do not.
- :func:`read_foxglove`: a Foxglove protobuf message read with the schema that came with it,
  checked to read the same with Foxglove's published schemas (``foxglove-schemas-protobuf``);
  :func:`quill_in_world`: where its transforms put the arm's quill.

Network rules (``docs/design.md``): Zenoh only through the project's own configuration, on
127.0.0.1, with an explicit port.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import importlib
import json
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from google.protobuf import descriptor_pb2, descriptor_pool, json_format, message_factory

from bridge.scene import QUILL, WORLD
from controller.node import (
    GIVE_UP_VARIABLE,
    LOCKSTEP_GIVE_UP,
    LOCKSTEP_STARTUP,
    STARTUP_VARIABLE,
)
from protocol.bus import enlarge_receive_buffer
from protocol.zenoh_can.config import free_port as free_port

ROOT = Path(__file__).resolve().parent.parent
LATE_DETOUR = ROOT / "tests" / "late_detour.toml"
"""A scenario whose detour costs more than its settling time: its run ends after the plan's
end, its task done (or, given a timeout as short as the plan, in TASK_TIMEOUT)."""
UNSAFE_WITHIN = 0.02
"""m: how near the inflated obstacle the fixture ``no_safe_motion_near`` (``conftest.py``)
lets the arm come, about."""
VCAN0 = Path("/sys/class/net/vcan0")
HIL_REQUIRED = os.environ.get("SCARA_HIL_REQUIRED") == "1"
"""Set where the ``hil`` tier must run (``.ci/run`` in its VM): no vcan0 then fails the
tests instead of skipping them, so a broken VM cannot pass as a green run."""


SLOWDOWN = float(os.environ.get("SCARA_TEST_SLOWDOWN", "1"))
"""How many times slower than an ordinary host this machine runs the processes: every bound
on waiting (for a process, a frame, a condition, a test) is stretched by it, and so is the
lateness a test allows a measured pace. ``.ci/run`` sets it in the software-emulated VM, where
python runs about 30 times slower; a bound on waiting only decides how long a failure takes to
show, never whether a test passes."""


EMULATED = SLOWDOWN > 1.0
"""The nodes run far slower than real time asks here (the software-emulated VM of
``.ci/run``)."""


def _numpy_agrees_with_libm() -> bool:
    """Whether numpy's atan2, acos and exp give libm's bits on this CPU (a sample). Where the
    CPU has AVX-512, numpy runs code of its own for them, an ulp off libm's in a few per cent
    of calls."""
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-7.0, 7.0, 5000), rng.uniform(-2.0, 2.0, 5000)
    unit = rng.uniform(-1.0, 1.0, 5000)
    return bool(
        np.arctan2(y, x).tolist() == list(map(math.atan2, y.tolist(), x.tolist()))
        and np.arccos(unit).tolist() == list(map(math.acos, unit.tolist()))
        and np.exp(-np.abs(x)).tolist() == [math.exp(-abs(v)) for v in x.tolist()]
    )


NUMPY_IS_LIBM = _numpy_agrees_with_libm()
"""The law over arrays gives the scalar law's bits here; elsewhere the tests that compare
them allow :data:`NOT_LIBM_TOLERANCE`."""
NOT_LIBM_TOLERANCE = 1e-9
"""Relative and absolute: how far the law over arrays may be from the scalar law where numpy's
transcendental functions are an ulp off libm's."""


LOCKSTEP_WAITS = {GIVE_UP_VARIABLE: LOCKSTEP_GIVE_UP, STARTUP_VARIABLE: LOCKSTEP_STARTUP}
"""The product's own bounds on waiting for the plant in lockstep, by the environment variable
that sets each (``controller/node.py``)."""


def stretch_lockstep_waits() -> None:
    """Where SLOWDOWN is above 1, every lockstep controller the tests start (the environment
    passes to it through any launcher) waits SLOWDOWN times longer for the plant than the
    product's defaults, as a user must set them on a host that stalls as long: these bounds
    decide whether a run faults, not only how long a failure takes to show. In the emulated
    VM on a loaded host the whole guest stopped for 1.25 s and runs faulted at the 1 s default
    (``docs/hil.md``); lockstep stays exact however long the plant takes."""
    if SLOWDOWN == 1.0:
        return
    for variable, default in LOCKSTEP_WAITS.items():
        os.environ.setdefault(variable, f"{default * SLOWDOWN:g}")


def real_time_needed() -> None:
    """Skip a test that closes a real-time loop where the nodes cannot keep time."""
    if EMULATED:
        pytest.skip(
            "closes a real-time loop: the software-emulated VM cannot (measured there at 100 Hz: "
            "command-to-state round trip p50 265 ms, the arm driven into a joint limit); runs "
            "on a host with vcan0 (docs/hil.md)"
        )


def hil_marks() -> list[pytest.MarkDecorator]:
    """The marks of a test that needs SocketCAN ``vcan0``: ``hil``, skipped where absent."""
    return [
        pytest.mark.hil,
        pytest.mark.skipif(
            not VCAN0.exists() and not HIL_REQUIRED,
            reason="no SocketCAN vcan0 here (sudo tools/vcan-setup, or run in tools/vcan-vm)",
        ),
    ]


class FakeClock:
    """An injected monotonic clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def frame(frame_id: int, data: bytes) -> can.Message:
    """A standard (11-bit) frame."""
    return can.Message(arbitration_id=frame_id, data=data, is_extended_id=False)


def wait_until(condition: Callable[[], bool], timeout: float, what: str) -> None:
    """Poll ``condition`` until it holds; fail naming ``what`` after ``timeout`` s (times
    SLOWDOWN)."""
    timeout *= SLOWDOWN
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.005)


def wait_while_growing(size: Callable[[], int], target: int, quiet: float, what: str) -> None:
    """Poll ``size()`` until it reaches ``target``; fail naming ``what`` once it has not grown
    for ``quiet`` s (times SLOWDOWN): for a wait whose length depends on how far behind the
    waited-for process is, not only on how slow the machine is."""
    quiet *= SLOWDOWN
    last, since = size(), time.monotonic()
    while last < target:
        time.sleep(0.05)
        now = size()
        if now > last:
            last, since = now, time.monotonic()
        elif time.monotonic() - since > quiet:
            raise AssertionError(f"{what}: {last} of {target}, no progress for {quiet} s")


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


def native_stacks(group: int) -> str:
    """Every thread's native stack in each process of process group ``group``, by gdb if
    this machine has it: what a process that will not stop is waiting in (a Zenoh close, a
    lock), for processes that cannot print their own (python-can's tools)."""
    gdb = shutil.which("gdb")
    if gdb is None:
        return "(no gdb here for the stacks)"
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, ValueError, IndexError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            if int(fields[2]) == group:
                members.append(int(stat.parent.name))
    found = []
    for pid in sorted(members):
        try:
            done = subprocess.run(
                [gdb, "-p", str(pid), "-batch", "-ex", "thread apply all bt 10"],
                capture_output=True, text=True, timeout=30,
            )  # fmt: skip
        except subprocess.TimeoutExpired:
            found.append(f"--- pid {pid}: gdb timed out")
            continue
        frames = [
            line[:160] for line in done.stdout.splitlines() if line.startswith(("Thread", "#"))
        ]
        found.append(f"--- pid {pid} native stacks ---\n" + "\n".join(frames))
    return "\n".join(found)


SIGINT_IGNORED = ("sh", "-c", 'trap "" INT; exec "$0" "$@"')
"""A ``prefix`` for :meth:`Processes.start`: the command starts with SIGINT ignored, as a
shell without job control starts a background job (a script's ``cmd &``)."""


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
        """The exit code; fails the test (after killing it) if it runs past ``timeout``
        (times SLOWDOWN)."""
        timeout *= SLOWDOWN
        try:
            return self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            stacks = native_stacks(self.popen.pid)
            self.kill()
            raise AssertionError(
                f"{self.name} still running after {timeout} s\n{self.output()}\n{stacks}"
            ) from None

    def interrupt(self, grace: float = 5.0) -> int:
        """SIGINT (a node's clean stop), SIGKILL if it has not exited after ``grace`` s
        (times SLOWDOWN)."""
        if self.popen.poll() is None:
            self.popen.send_signal(signal.SIGINT)
            try:
                self.popen.wait(grace * SLOWDOWN)
            except subprocess.TimeoutExpired:
                stacks = native_stacks(self.popen.pid)
                with contextlib.suppress(ProcessLookupError):  # its threads' stacks, if a node
                    os.kill(self.popen.pid, signal.SIGUSR1)
                time.sleep(0.5)
                self.kill()
                with self.log.open("a") as log:
                    log.write(f"\n{self.name} did not stop on SIGINT:\n{stacks}\n")
        return self.popen.returncode

    def signal(self, number: int) -> None:
        """Send ``number`` (SIGSTOP, SIGCONT, ...) to the process."""
        os.kill(self.popen.pid, number)

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

    def start(
        self, module: str, *args: str, name: str | None = None, prefix: Sequence[str] = ()
    ) -> Process:
        """``prefix`` comes before the interpreter, e.g. ``ip netns exec NAME``."""
        name = name or f"{module}#{len(self.started)}"
        log = self.folder / f"{name.replace('/', '_')}.log"
        process = Process(name, [*prefix, sys.executable, "-m", module, *args], log)
        self.started.append(process)
        return process

    def outputs(self) -> str:
        return "\n".join(process.output() for process in self.started)

    def close(self) -> None:
        for process in reversed(self.started):
            process.close()


class Observer:
    """A bus of the test's own: records every frame it receives, in a background thread."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        enlarge_receive_buffer(bus)  # a stalled test process must not lose a frame it checks
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
        """The first frame (from index ``start`` on) satisfying ``predicate``; None after
        ``timeout`` s (times SLOWDOWN)."""
        deadline = time.monotonic() + timeout * SLOWDOWN
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


def frames_with_every_flag() -> list[can.Message]:
    """Standard, extended, remote, error, FD with BRS and ESI, empty and full payloads."""
    t0 = 1_700_000_000.123456
    return [
        can.Message(timestamp=t0, arbitration_id=0x123, is_extended_id=False, data=b"\x01\x02"),
        can.Message(timestamp=t0 + 1, arbitration_id=0x1ABCDEF0, is_extended_id=True, data=b""),
        can.Message(
            timestamp=t0 + 2, arbitration_id=0x7FF, is_extended_id=False, data=bytes(range(8))
        ),
        can.Message(
            timestamp=t0 + 3, arbitration_id=0x10, is_extended_id=False, is_remote_frame=True, dlc=4
        ),
        can.Message(timestamp=t0 + 4, arbitration_id=0x0, is_error_frame=True, data=bytes(8)),
        can.Message(
            timestamp=t0 + 5,
            arbitration_id=0x18FF50E5,
            is_extended_id=True,
            is_fd=True,
            bitrate_switch=True,
            error_state_indicator=True,
            data=bytes(range(64)),
        ),
        can.Message(
            timestamp=t0 + 6, arbitration_id=0x55, is_extended_id=False, is_fd=True, data=b"x" * 12
        ),
    ]


def same_frame(a: can.Message, b: can.Message, *, timestamps: bool = True) -> bool:
    """Equal in every field (and timestamp, unless ``timestamps`` is False: a bus stamps
    its own receive time)."""
    delta = 0.0 if timestamps else None
    return a.equals(b, timestamp_delta=delta, check_channel=False, check_direction=False)


def open_client(
    port: int,
    user: str | None = None,
    password: str | None = None,
    *,
    ca: Path | None = None,
    certificate: Path | None = None,
    key: Path | None = None,
) -> zenoh.Session:
    """A plain Zenoh client session written here from Zenoh's own configuration keys (no
    project code): multicast scouting off, one explicit ``tcp/127.0.0.1`` endpoint (with
    ``ca``, ``tls/127.0.0.1``: the router's certificate checked against it, and this
    client's ``certificate`` and ``key`` shown to a router that asks)."""
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    scheme = "tcp" if ca is None else "tls"
    config.insert_json5("connect/endpoints", json.dumps([f"{scheme}/127.0.0.1:{port}"]))
    tls = {
        "root_ca_certificate": ca,
        "connect_certificate": certificate,
        "connect_private_key": key,
    }
    for name, path in tls.items():
        if path is not None:
            config.insert_json5(f"transport/link/tls/{name}", json.dumps(str(path)))
    if certificate is not None:
        config.insert_json5("transport/link/tls/enable_mtls", "true")
    config.insert_json5("listen/endpoints", "[]")
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("scouting/gossip/enabled", "false")
    if user is not None:
        config.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        config.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return zenoh.open(config)


def read_foxglove(schema_name: str, schema_data: bytes, data: bytes) -> Any:
    """``data`` decoded with the FileDescriptorSet it came with (an MCAP channel's schema, an
    advertised channel's), as Foxglove decodes it; it must decode to the same with Foxglove's
    published schema of that name (``foxglove.SceneUpdate`` ...), which is returned."""
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(schema_data).file:
        pool.Add(file)
    own = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))
    type_name = schema_name.removeprefix("foxglove.")
    module = importlib.import_module(f"foxglove_schemas_protobuf.{type_name}_pb2")
    published = getattr(module, type_name).FromString(data)
    assert json_format.MessageToDict(own.FromString(data)) == json_format.MessageToDict(published)
    return published


def quill_in_world(transforms: Any) -> tuple[float, float, float]:
    """Where a decoded ``foxglove.FrameTransforms`` puts the scene's quill frame in its world
    frame, composed along the chain (rotations about z only, as the arm's are)."""
    by_child = {t.child_frame_id: t for t in transforms.transforms}
    x = y = z = 0.0
    frame = QUILL
    while frame != WORLD:
        t = by_child[frame]
        yaw = 2.0 * math.atan2(t.rotation.z, t.rotation.w)
        x, y = math.cos(yaw) * x - math.sin(yaw) * y, math.sin(yaw) * x + math.cos(yaw) * y
        x, y, z = x + t.translation.x, y + t.translation.y, z + t.translation.z
        frame = t.parent_frame_id
    return x, y, z


def listening_sockets(pid: int | str = "self") -> list[tuple[str, int]] | None:
    """(address, port) of each TCP socket in LISTEN state that process ``pid`` holds (Linux;
    None where there is no /proc to read them from)."""
    proc = Path("/proc") / str(pid)
    fd_dir = proc / "fd"
    if not fd_dir.is_dir() or not (proc / "net/tcp").exists():
        return None
    inodes = set()
    for fd in fd_dir.iterdir():
        with_target = os.readlink(fd) if fd.is_symlink() else ""
        if with_target.startswith("socket:["):
            inodes.add(with_target[8:-1])
    found: list[tuple[str, int]] = []
    for table, family in (("tcp", 4), ("tcp6", 6)):
        path = proc / "net" / table
        if not path.exists():
            continue
        for line in path.read_text().splitlines()[1:]:
            fields = line.split()
            local, state, inode = fields[1], fields[3], fields[9]
            if state != "0A" or inode not in inodes:  # 0A = LISTEN
                continue
            hex_address, hex_port = local.split(":")
            if family == 4:
                address = socket.inet_ntoa(bytes.fromhex(hex_address)[::-1])
            else:
                address = f"ipv6:{hex_address}"
            found.append((address, int(hex_port, 16)))
    return found


CHROMIUM = Path("/usr/bin/chromium")
"""Debian's Chromium, which Playwright drives headless (``tools/browser-setup``): Playwright's
own browser download is not reachable from these machines."""
BROWSER_ARGS = ["--no-sandbox", "--enable-unsafe-swiftshader"]
"""No sandbox as root in a container; SwiftShader: WebGL in software, there is no GPU."""
VIEWPORT = {"width": 1280, "height": 760}
"""The pages' size in the browser tests and the GUI benchmark."""


def make_certificates(folder: Path, *names: str) -> Path:
    """A ``scara-certs`` set in ``folder`` (CA, server, client), made by the command itself;
    the server's certificate valid for ``names`` too."""
    given = [part for name in names for part in ("--name", name)]
    subprocess.run(
        [sys.executable, "-m", "protocol.certs", "--out", str(folder), *given],
        check=True,
        capture_output=True,
        cwd=ROOT,
    )
    return folder


def trusting(certificate: Path) -> str:
    """Chromium's flag that trusts the server certificate ``certificate`` (its public key's
    SHA-256, pinned) and no other that its own store does not: how a browser test opens a
    page served with a ``scara-certs`` certificate."""
    loaded = x509.load_pem_x509_certificate(certificate.read_bytes())
    key = loaded.public_key().public_bytes(
        serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo
    )
    pin = base64.b64encode(hashlib.sha256(key).digest()).decode()
    return f"--ignore-certificate-errors-spki-list={pin}"
