"""Outside clients of the ``hil`` tier (``test_hil_clients.py``): the tools a user has on a
Linux host with SocketCAN, Debian's can-utils (``candump``, ``cansend``, ``canplayer``,
``cangen``) and cantools' command line, driven as separate processes on ``vcan0``.

- :func:`can_util`: the path of a can-utils program (skip where missing, fail where the tier
  is required).
- :class:`Candump`: ``candump -L vcan0`` into a file, started once its socket is bound;
  :func:`read_capture` parses such a file, :func:`write_capture` writes one.
- :func:`cantools_decode`: ``cantools decode`` of a capture with the project's DBC, parsed.
- :func:`cansend`: frames through ``cansend``, all at once.
- :func:`background`: a tool (``cangen``) running while in use.
"""

from __future__ import annotations

import contextlib
import re
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import pytest
from support import HIL_REQUIRED, ROOT, SLOWDOWN, wait_until

VCAN = "vcan0"
DBC = ROOT / "protocol" / "scara.dbc"
BIND_TIMEOUT = 30.0
"""s a tool may take to start and bind its socket, or to stop (times SLOWDOWN)."""


def can_util(name: str) -> str:
    """The path of the can-utils program ``name``: skip where absent (fail if required)."""
    path = shutil.which(name) or shutil.which(name, path="/usr/bin:/bin:/usr/sbin:/sbin")
    if path is None:
        message = f"{name} (Debian's can-utils) is not installed: apt-get install can-utils"
        if HIL_REQUIRED:
            pytest.fail(message)
        pytest.skip(message)
    return path


def raw_receivers() -> int:
    """How many CAN_RAW receive filters are registered on vcan0 (a bound socket adds one)."""
    text = Path("/proc/net/can/rcvlist_all").read_text()
    return sum(1 for line in text.splitlines() if line.split()[:1] == [VCAN])


@dataclass(frozen=True, slots=True)
class Captured:
    """One frame of a ``candump -L`` capture."""

    timestamp: float
    frame_id: int
    data: bytes
    line: str


_LOG_LINE = re.compile(r"^\((\d+\.\d+)\)\s+(\S+)\s+([0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#([0-9A-Fa-f]*)$")


def read_capture(path: Path) -> list[Captured]:
    """The data frames of a ``candump -L`` file, in order (any other line fails the test)."""
    frames = []
    for line in path.read_text().splitlines():
        match = _LOG_LINE.match(line.strip())
        assert match is not None, f"not a data frame in candump's log format: {line!r}"
        stamp, _, frame_id, data = match.groups()
        frames.append(Captured(float(stamp), int(frame_id, 16), bytes.fromhex(data), line))
    return frames


def write_capture(path: Path, frames: Sequence[Captured]) -> None:
    path.write_text("".join(frame.line + "\n" for frame in frames))


class Candump:
    """``candump -L vcan0`` writing ``path`` while in use (``-d``: it reports its drops)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        before = raw_receivers()
        self._file = path.open("wb")
        self._errors = path.with_suffix(".stderr")
        self.process = subprocess.Popen(
            [can_util("candump"), "-L", "-d", VCAN],
            stdout=self._file,
            stderr=self._errors.open("wb"),
            stdin=subprocess.DEVNULL,
        )
        wait_until(
            lambda: self.process.poll() is not None or raw_receivers() > before,
            BIND_TIMEOUT,
            "candump to bind its socket",
        )
        assert self.process.poll() is None, self._errors.read_text()

    def stop(self) -> list[Captured]:
        """SIGINT (candump flushes and exits); the frames it captured."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
            self.process.wait(BIND_TIMEOUT * SLOWDOWN)
        self._file.close()
        errors = self._errors.read_text(errors="replace")
        assert "DROP" not in errors.upper(), f"candump dropped frames: {errors}"
        return read_capture(self.path)

    def __enter__(self) -> Candump:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(10 * SLOWDOWN)
        self._file.close()


def cansend(frames: Sequence[tuple[int, bytes]]) -> None:
    """Put ``frames`` (standard IDs) on vcan0, one ``cansend`` each, all started at once: they
    go out within about one process start, in no set order."""
    program = can_util("cansend")
    started = [
        subprocess.Popen(
            [program, VCAN, f"{frame_id:03X}#{data.hex().upper()}"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        for frame_id, data in frames
    ]
    for process in started:
        _, errors = process.communicate(timeout=BIND_TIMEOUT * SLOWDOWN)
        assert process.returncode == 0, errors.decode(errors="replace")


@contextlib.contextmanager
def background(argv: Sequence[str]) -> Iterator[subprocess.Popen[bytes]]:
    """A tool running while in use; SIGINT (then SIGKILL) at the end."""
    process = subprocess.Popen(
        list(argv), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    try:
        yield process
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(10 * SLOWDOWN)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(10 * SLOWDOWN)
        if process.stderr is not None:
            process.stderr.close()


@dataclass(frozen=True, slots=True)
class Decoded:
    """One line of ``cantools decode --single-line``: the frame's message and signals."""

    frame_id: int
    message: str
    signals: dict[str, float]


_DECODED = re.compile(
    r"^\((\d+\.\d+)\)\s+\S+\s+([0-9A-Fa-f]+)#([0-9A-Fa-f]*)\s+::\s+(\w+)\((.*)\)$"
)


def cantools_decode(capture: Path) -> list[Decoded]:
    """``cantools decode --single-line --no-decode-choices DBC < capture``, every line parsed
    (a line cantools could not decode fails the test, showing it)."""
    with capture.open("rb") as stdin:
        done = subprocess.run(
            [sys.executable, "-m", "cantools", "decode", "--single-line",
             "--no-decode-choices", str(DBC)],
            stdin=stdin, capture_output=True, text=True, timeout=60 * SLOWDOWN,
        )  # fmt: skip
    assert done.returncode == 0, done.stderr
    decoded = []
    for line in done.stdout.splitlines():
        match = _DECODED.match(line.strip())
        assert match is not None, f"cantools could not decode: {line!r}"
        _, frame_id, _, message, signals = match.groups()
        values = {}
        for item in signals.split(", "):
            name, _, value = item.partition(": ")
            values[name] = float(value.split(" ", 1)[0])
        decoded.append(Decoded(int(frame_id, 16), message, values))
    return decoded
