"""``scara-replay``: a recording back onto a CAN transport, at its recorded pace or faster.

Reads an MCAP recording (``scara-record``, ``can.logger -f x.mcap``) or any log python-can
reads (``.blf``, ``.asc``, ``.csv``, ``.log`` ...) and sends its frames onto the bus chosen
as every command chooses one. Frame ``i`` goes out at ``start + (t_i - t_0) / rate``, slept
to as an absolute deadline, so errors do not add up. While it runs, the space bar pauses and
resumes (when the terminal is interactive); Ctrl-C stops it cleanly.

Before it closes, a replay waits until what it sent has been taken (:data:`DELIVERY_TIMEOUT`):
closing a Zenoh session drops whatever is still in flight to a slow or stalled receiver, and
a replay as fast as possible always has frames in flight at its end. It says so, and exits 1,
if that was not confirmed.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import termios
import threading
import time
import tty
from collections.abc import Callable, Generator, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import can
import zenoh
from mcap.reader import make_reader
from tqdm import tqdm

from bridge.session import add_zenoh_arguments, endpoint_from_args
from controller.task_rules import load_task
from protocol.bus import add_bus_arguments, open_bus_from_args
from protocol.cli import (
    add_verbosity,
    configure_logging,
    interruptible,
    number,
    quiet_on_closed_pipe,
)
from protocol.errors import ScaraError
from protocol.keys import STATE_KEYS, check_robot, state_key
from protocol.realtime import tune_process
from protocol.scenario import parse_scenario
from recorder.mcap_can import (
    DBC_NAMES,
    READ_ERRORS,
    RecordingError,
    check_mcap,
    frames,
    read_attachments,
)
from recorder.node import STATE_PREFIX
from recorder.regression import regress

log = logging.getLogger("scara.replay")

TOGETHER = 2e-4
"""s: frames due within this of each other go out in one call (a tick's frames, together)."""
BATCH = 256
"""Frames sent in one call when there is no pace to keep (``--as-fast-as-possible``)."""
DELIVERY_TIMEOUT = 60.0
"""s a replay waits at its end for its receivers to confirm they have taken all it sent: a
stalled receiver (a busy machine) holds a replay as fast as possible this long at most."""


def read_frames(path: Path) -> Generator[can.Message, None, None]:
    """The frames of ``path``, in order: MCAP by our reader, anything else by python-can's."""
    if path.suffix == ".mcap":
        check_mcap(path)
        with path.open("rb") as stream:
            yield from frames(stream)
        return
    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    try:
        with can.LogReader(path) as reader:
            yield from reader
    except ValueError as error:  # python-can: an unknown suffix
        raise RecordingError(f"{path}: {error}") from None


def frame_filter(names: Sequence[str]) -> set[int] | None:
    """The IDs ``--only`` names (DBC message names or IDs such as 0x110); None: all."""
    if not names:
        return None
    by_name = {name: frame_id for frame_id, name in DBC_NAMES.items()}
    wanted: set[int] = set()
    for name in names:
        if name in by_name:
            wanted.add(by_name[name])
            continue
        try:
            wanted.add(int(name, 0))
        except ValueError:
            known = ", ".join(sorted(by_name))
            raise RecordingError(
                f"--only {name!r}: neither a frame ID nor a DBC message ({known})"
            ) from None
    return wanted


def selected(
    messages: Iterable[Timed],
    wanted: set[int] | None,
    start_offset: float,
    until: float | None,
) -> Iterator[Timed]:
    """The frames between ``start_offset`` and ``until`` s into the recording, filtered."""
    first: float | None = None
    for message in messages:
        if first is None:
            first = message.timestamp
        offset = message.timestamp - first
        if offset < start_offset:
            continue
        if until is not None and offset > until:
            return
        if wanted is None or getattr(message, "arbitration_id", None) in wanted:
            yield message


class Pause:
    """The space bar pauses and resumes (a thread reads the terminal, one key at a time)."""

    def __init__(self) -> None:
        self.running = threading.Event()
        self.running.set()
        self.paused_for = 0.0
        self._saved: Any = None

    def listen(self) -> None:
        """Start listening if the terminal is interactive; :meth:`close` gives it back."""
        if not sys.stdin.isatty():
            return
        self._saved = termios.tcgetattr(sys.stdin)
        tty.setcbreak(sys.stdin)  # keys as they are pressed, Ctrl-C still a signal
        print("space pauses and resumes, Ctrl-C stops", file=sys.stderr)
        threading.Thread(target=self._read, name="keyboard", daemon=True).start()

    def close(self) -> None:
        if self._saved is not None:
            termios.tcsetattr(sys.stdin, termios.TCSADRAIN, self._saved)
            self._saved = None

    def _read(self) -> None:
        while key := sys.stdin.read(1):
            if key != " ":
                continue
            if self.running.is_set():
                self.running.clear()
                print("\npaused: space resumes", file=sys.stderr)
            else:
                self.running.set()

    def wait(self) -> None:
        if not self.running.is_set():
            began = time.monotonic()
            self.running.wait()
            self.paused_for += time.monotonic() - began


class Timed(Protocol):
    """A frame, or a decoded sample: anything with the time it was recorded at."""

    @property
    def timestamp(self) -> float: ...


@dataclass(frozen=True, slots=True)
class StateSample:
    """A decoded-state message of a recording (``scara/joints`` ...): its key and JSON."""

    timestamp: float
    name: str
    data: bytes


def read_state(path: Path) -> Iterator[StateSample]:
    """The decoded-state messages of an MCAP recording, in the order they were written."""
    check_mcap(path)
    try:
        with path.open("rb") as stream:
            for _, channel, message in make_reader(stream).iter_messages(log_time_order=False):
                if channel.topic.startswith(STATE_PREFIX) and channel.message_encoding == "json":
                    name = channel.topic.removeprefix(STATE_PREFIX)
                    yield StateSample(message.log_time / 1e9, name, message.data)
    except READ_ERRORS as error:
        raise RecordingError(
            f"{path}: not a readable MCAP recording ({error}); if its writer was killed, "
            "'scara-record recover FILE' rewrites it"
        ) from None


class ZenohStateSink:
    """Puts decoded samples on the robot's state keys, as the bridge would, but with
    congestion control BLOCK on every key: the live bridge drops telemetry rather than hold
    up the robot, a replay has nothing to keep pace with and must not lose a sample."""

    def __init__(self, session: zenoh.Session, robot: str) -> None:
        self._session = session
        self._barrier_key = state_key(robot, STATE_KEYS[0])
        self._publishers = {
            name: session.declare_publisher(
                state_key(robot, name), congestion_control=zenoh.CongestionControl.BLOCK
            )
            for name in STATE_KEYS
        }

    def send_many(self, samples: Sequence[StateSample]) -> None:
        for sample in samples:
            publisher = self._publishers.get(sample.name)
            if publisher is not None:
                publisher.put(sample.data)

    def deliver(self, timeout: float) -> Delivery:
        """Wait until the router has routed every sample put so far: a query travels behind
        them on the same link, and the router answers it (with its final reply, queryable or
        not) only after it has queued each of them for every subscriber (BLOCK). Subscribers
        answer nothing, so this is as far as a replay can confirm; the router forwards the
        rest on its own after the replay has gone."""
        began = time.monotonic()
        replies = self._session.get(
            self._barrier_key,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            congestion_control=zenoh.CongestionControl.BLOCK,
            timeout=timeout,
        )
        for _ in replies:  # ends with the router's final reply, or at the timeout
            pass
        return Delivery(time.monotonic() - began < timeout, "the router", timeout)


@dataclass(frozen=True, slots=True)
class Delivery:
    """Whether what a replay sent was confirmed taken before it closed, and by whom."""

    confirmed: bool
    by: str
    within: float
    """s it waited at most."""

    def summary(self) -> str:
        if self.confirmed:
            return f"taken by {self.by}"
        return (
            f"NOT confirmed taken by {self.by} within {self.within:g} s: what was still in "
            "flight (a stalled receiver) is lost"
        )


def deliver_frames(bus: can.BusABC, timeout: float) -> Delivery | None:
    """Wait until every bus on the channel has taken every frame sent: CAN over Zenoh's flush
    barrier, which returns before its timeout only once every bus has answered (a bus
    answers once it holds every frame sent before the question). None for other buses,
    whose ``send`` hands a frame to the kernel or the driver, which outlives the replay."""
    flush = getattr(bus, "flush", None)
    if flush is None:
        return None
    began = time.monotonic()
    answered = flush(timeout)
    confirmed = time.monotonic() - began < timeout
    listening = f"the {answered} bus{'es' if answered != 1 else ''} listening"
    return Delivery(confirmed, listening, timeout)


def replay(
    bus: Any,
    messages: Iterable[Timed],
    rate: float | None,
    pause: Pause | None = None,
    progress: tqdm | None = None,
) -> int:
    """Send ``messages`` at ``rate`` times their recorded pace (None: at once); the count."""
    sent = 0
    if rate is None:
        batch: list[Timed] = []
        for message in messages:
            batch.append(message)
            if len(batch) == BATCH:
                sent += _send(bus, batch, progress)
                batch = []
        return sent + _send(bus, batch, progress)
    start = first = 0.0
    due: list[Timed] = []
    for message in messages:
        if not due and not sent:  # the clock starts with the first frame, once it is read
            start, first = time.monotonic(), message.timestamp
        paused = pause.paused_for if pause is not None else 0.0
        deadline = start + paused + (message.timestamp - first) / rate
        if deadline - time.monotonic() > TOGETHER:  # not due yet: send what is, then wait
            sent += _send(bus, due, progress)
            due = []
            if pause is not None:
                pause.wait()
                deadline += pause.paused_for - paused
            remaining = deadline - time.monotonic()
            if remaining > 0:
                time.sleep(remaining)
        due.append(message)
    return sent + _send(bus, due, progress)


def _send(bus: Any, batch: Sequence[Timed], progress: tqdm | None) -> int:
    """``bus.send_many`` if it has one (ours, the Zenoh sink), else frame by frame."""
    if not batch:
        return 0
    send_many = getattr(bus, "send_many", None)
    if send_many is not None:
        send_many(batch)
    else:
        for message in batch:
            bus.send(message)
    if progress is not None:
        progress.update(len(batch))
    return len(batch)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-replay",
        description="Send a recording's CAN frames (MCAP or any python-can log) onto a bus at "
        "the recorded pace. Space pauses and resumes; Ctrl-C stops. At the end it waits (up to "
        f"{DELIVERY_TIMEOUT:g} s) until its receivers have taken all it sent, and exits 1 if "
        "that is not confirmed.",
    )
    parser.add_argument("file", type=Path, help="the recording (.mcap, .blf, .asc, .log ...)")
    pace = parser.add_mutually_exclusive_group()
    pace.add_argument(
        "--rate",
        type=number(0.0, 1000.0, low_open=True),
        default=1.0,
        help="times the recorded pace (default 1)",
    )
    pace.add_argument(
        "--as-fast-as-possible", action="store_true", help="no pace: as fast as the bus takes"
    )
    parser.add_argument(
        "--loop",
        type=number(1, 10**9, integer=True),
        nargs="?",
        const=10**9,
        default=1,
        metavar="N",
        help="play it N times (no N: until Ctrl-C)",
    )
    parser.add_argument(
        "--start-offset",
        type=number(0.0),
        default=0.0,
        metavar="S",
        help="skip the first S s of the recording",
    )
    parser.add_argument(
        "--until", type=number(0.0), metavar="S", help="stop S s into the recording"
    )
    parser.add_argument(
        "--only",
        action="append",
        default=[],
        metavar="FRAME",
        help="only this frame (DBC name, e.g. JointState1, or ID, e.g. 0x110); repeatable",
    )
    parser.add_argument(
        "--to",
        choices=("can", "zenoh"),
        default="can",
        help="can: the frames onto a CAN transport (default); zenoh: the decoded state of an "
        "MCAP recording onto the robot's Zenoh keys, as a bridge would publish it",
    )
    add_zenoh_arguments(parser)
    regression = parser.add_argument_group("regression replay (no bus: the control law, here)")
    regression.add_argument(
        "--regress",
        action="store_true",
        help="feed a lockstep recording's joint states to the control law and compare its "
        "commands with the recorded ones; exit 1 at a difference",
    )
    regression.add_argument(
        "--scenario",
        help="with --regress: scenario file or name to run instead of the recording's own",
    )
    add_bus_arguments(parser)
    add_verbosity(parser)
    return parser


def regression_main(args: argparse.Namespace) -> int:
    """``--regress``: the report, and 0 if every command is identical."""
    try:
        if args.scenario:
            scenario = load_task(args.scenario)
        else:
            attached = read_attachments(args.file).get("scenario.json")
            if attached is None:
                raise RecordingError(f"{args.file}: no scenario attached: give --scenario")
            scenario = parse_scenario(json.loads(attached))
        report = regress(read_frames(args.file), scenario)
        if report.ticks == 0:
            raise RecordingError(
                f"{args.file}: no lockstep steps (StepSync frames) in it: regression replay "
                "needs a run recorded with --clock lockstep"
            )
    except (RecordingError, ScaraError, ValueError) as error:
        print(f"scara-replay: {error}", file=sys.stderr)
        return 2
    print(report.summary())
    return 0 if report.passed else 1


@quiet_on_closed_pipe
def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose)
    interruptible()
    if args.regress:
        return regression_main(args)
    tune_process()  # precise wake-ups: the pace is the point
    to_zenoh = args.to == "zenoh"
    source: Callable[[Path], Iterator[Timed]] = read_state if to_zenoh else read_frames
    session: zenoh.Session | None = None
    try:
        wanted = frame_filter(args.only)
        probe = source(args.file)  # a bad file fails here, not midway
        first = next(probe, None)
        probe.close()  # type: ignore[attr-defined]
        if first is None:
            what = "decoded state" if to_zenoh else "CAN frames"
            raise RecordingError(f"{args.file}: no {what} in it")
        if to_zenoh:
            session = endpoint_from_args(args, "scara-replay").open()
            bus: Any = ZenohStateSink(session, check_robot(args.robot))
        else:
            bus = open_bus_from_args(args)
    except (RecordingError, ScaraError, can.CanError, zenoh.ZError, ValueError, OSError) as error:
        print(f"scara-replay: {error}", file=sys.stderr)
        return 2
    rate = None if args.as_fast_as_possible else args.rate
    pause = Pause()
    pause.listen()
    sent = 0
    delivery: Delivery | None = None
    try:
        for round_number in range(args.loop):
            messages = selected(source(args.file), wanted, args.start_offset, args.until)
            label = f"{args.file.name}" + (f" #{round_number + 1}" if args.loop > 1 else "")
            with tqdm(desc=label, unit=" frames", disable=None, file=sys.stderr) as progress:
                sent += replay(bus, messages, rate, pause, progress)
        if to_zenoh:
            delivery = bus.deliver(DELIVERY_TIMEOUT)
        else:
            delivery = deliver_frames(bus, DELIVERY_TIMEOUT)
    except KeyboardInterrupt:
        print("\nscara-replay: interrupted (what was in flight may be lost)", file=sys.stderr)
    except RecordingError as error:
        print(f"scara-replay: {error}", file=sys.stderr)
        return 2
    finally:
        pause.close()
        if session is not None:
            session.close()  # type: ignore[no-untyped-call]
        else:
            bus.shutdown()
    what = f"scara-replay: {sent} {'samples' if to_zenoh else 'frames'} sent"
    if delivery is None:
        print(what, file=sys.stderr)
        return 0
    print(f"{what}, {delivery.summary()}", file=sys.stderr)
    return 0 if delivery.confirmed else 1


if __name__ == "__main__":
    sys.exit(main())
