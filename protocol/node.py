"""The base every bus participant stands on, and the ``main()`` plumbing of a node process.

A :class:`Node` owns what every participant does the same way: it accepts frames through the
E2E checks (bad ones are counted and never acted on) and dispatches the good ones, sends
frames with their alive counters, sends its status frame on the DBC's cycle time, latches an
EmergencyStop and obeys the NodeCommand addressed to it, and reports what it did.
A subclass keeps only what is its own: which frames it acts on, its state machine, its loop.

:func:`node_main` is the process around a node: the flags every node takes, logging,
timing (:mod:`protocol.realtime`), opening the scenario and the bus, signals, the result
file and the exit status. A bad flag, scenario or transport exits with status 2 and a
message naming it, before anything is sent.
"""

from __future__ import annotations

import argparse
import faulthandler
import json
import logging
import signal
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from enum import Enum
from pathlib import Path
from types import FrameType
from typing import Any, ClassVar, TypeVar

import can

from protocol.bus import add_bus_arguments, open_bus_from_args, send_frames
from protocol.cli import add_verbosity, configure_logging, number
from protocol.codec import WIRE, MessageCodec
from protocol.config import MAX_RATE_HZ, MIN_RATE_HZ
from protocol.e2e import E2EMonitor
from protocol.errors import EncodeError, ScaraError
from protocol.faults import FaultInjector, FaultSpec, add_fault_arguments
from protocol.isotp_link import IsoTpLink
from protocol.messages import NODE_COMMAND, STOP, Counter, NodeId, NodeState, Request
from protocol.realtime import settle_memory, tune_process
from protocol.scenario import Scenario

DRAIN_LIMIT = 256
"""Frames one :meth:`Node.drain` handles at most (a few ms of reading): on a bus that never ran
dry (other systems' frames coming faster than a node reads them) the controller read for ever
instead of taking the lockstep answer it had already read. Its callers loop; what is left
waits in the socket's queue."""


class ClockMode(Enum):
    REALTIME = "realtime"
    LOCKSTEP = "lockstep"


class Node:
    """One participant on the bus (see the module docstring).

    Subclasses set the class attributes and implement :meth:`on_frame`, :meth:`on_reset` and
    :meth:`statuses`; ``Fault`` is their fault-bit enumeration from the DBC, which has an
    ``ESTOP`` bit.
    """

    name: ClassVar[str]
    node_id: ClassVar[Any]
    status: ClassVar[MessageCodec]
    listens: ClassVar[tuple[MessageCodec, ...]]
    Fault: ClassVar[Any]

    def __init__(self, bus: can.BusABC, clock: Callable[[], float] = time.monotonic) -> None:
        self.bus = bus
        self.clock = clock
        self.log = logging.getLogger(f"scara.{self.name}")
        self.monitor = E2EMonitor()
        self._counters = {codec.frame_id: Counter() for codec in WIRE.messages.values()}
        self._accepted = {codec.frame_id for codec in (*self.listens, STOP, NODE_COMMAND)}
        self.running = True
        self.node_state = NodeState.READY
        self.fault = self.Fault(0)
        self.send_failures = 0
        self._links: dict[int, IsoTpLink] = {}
        """ISO-TP links by receive ID: their frames go to them, not through the E2E checks."""
        self._next_status = -float("inf")
        self._reported: tuple[Any, ...] | None = None

    # --- frames in ----------------------------------------------------------------------

    def drain(self, timeout: float = 0.0) -> None:
        """Handle the frames waiting on the bus (waiting up to ``timeout`` for the first), at
        most DRAIN_LIMIT of them: on a bus busier than this process can read, it would
        otherwise read for ever and never get back to its own work."""
        message = self.bus.recv(timeout=timeout)
        handled = 0
        while message is not None:
            self.handle(message)
            handled += 1
            if handled == DRAIN_LIMIT:
                return
            message = self.bus.recv(timeout=0.0)

    def handle(self, message: can.Message) -> None:
        """Act on one received frame, or count it and drop it."""
        link = self._links.get(message.arbitration_id)
        if link is not None and not (
            message.is_error_frame or message.is_remote_frame or message.is_extended_id
        ):  # ISO-TP rides on standard data frames only
            link.feed(message)
            return
        accepted = self.monitor.accept(message, self._accepted)
        if accepted is None:
            return
        codec, counter, record = accepted
        if codec is STOP:
            self.emergency_stop()
        elif codec is NODE_COMMAND:
            if record.Target in (self.node_id, NodeId.ALL):
                self.on_request(Request(record.Command), record.Ticket)
        else:
            self.on_frame(codec, counter, record, message)

    def add_link(
        self, txid: int, rxid: int, what: str, asked: Callable[[], bool] | None = None
    ) -> IsoTpLink:
        """An ISO-TP link on this node's bus, sending on ``txid``; the frames of ``rxid`` go to
        it from now on (this node's reader is the bus's only one). A broken transfer is
        logged as ``what``'s; ``asked`` as :class:`IsoTpLink` takes it (an operator's)."""
        link = IsoTpLink(
            lambda message: self._transmit([message]),
            txid,
            rxid,
            asked=asked,
            on_error=lambda error: self.log.warning("%s transfer broken: %s", what, error),
        )
        self._links[rxid] = link
        return link

    def on_frame(
        self, codec: MessageCodec, counter: int, record: Any, message: can.Message
    ) -> None:
        """A valid frame of one of :attr:`listens`."""
        raise NotImplementedError

    def on_request(self, request: Any, ticket: int) -> None:
        """A NodeCommand for this node: reset or stop (``run`` and ``describe`` are the
        controller's service's; ``ticket`` is the sender's, for an answer)."""
        if request == Request.RESET:
            self.log.info("reset")
            self.on_reset()
        elif request == Request.STOP:
            self.log.info("stop requested")
            self.stop()

    def on_reset(self) -> None:
        raise NotImplementedError

    def emergency_stop(self) -> None:
        """Latch e-stop until a reset (a subclass also brings its outputs to zero)."""
        if self.node_state is not NodeState.ESTOP:
            self.log.warning("emergency stop")
        self.fault |= self.Fault.ESTOP
        self.node_state = NodeState.ESTOP

    def enter_fault(self, reason: Any) -> None:
        """Latch ``reason`` until a reset; e-stop stays e-stop."""
        if reason not in self.fault:
            self.log.warning("fault: %s", reason.name)
        self.fault |= reason
        if self.node_state is not NodeState.ESTOP:
            self.node_state = NodeState.FAULT

    # --- frames out ---------------------------------------------------------------------

    def next_counter(self, codec: MessageCodec) -> int:
        """The next alive counter of ``codec``'s frame ID (each ID counts on its own)."""
        return self._counters[codec.frame_id].next()

    def send(self, codec: MessageCodec, record: Any) -> int:
        """Encode ``record`` with the next alive counter of its ID and send it; the counter.

        :class:`EncodeError` is the caller's to handle (it means a value is out of range).
        """
        counter = self.next_counter(codec)
        self.send_together([(codec, record, counter)])
        return counter

    def send_together(self, frames: Sequence[tuple[MessageCodec, Any, int]]) -> None:
        """Frames that belong together (a joint state, a lockstep command and its StepSync),
        each ``(codec, record, alive counter)``, sent as one unit where the transport can
        (:func:`protocol.bus.send_frames`). Nothing is sent if one does not encode."""
        self._transmit([self._frame(codec, record, counter) for codec, record, counter in frames])

    @staticmethod
    def _frame(codec: MessageCodec, record: Any, counter: int) -> can.Message:
        data = codec.encode(record, counter)
        return can.Message(arbitration_id=codec.frame_id, data=data, is_extended_id=False)

    def _transmit(self, messages: list[can.Message]) -> None:
        try:
            send_frames(self.bus, messages)
        except can.CanError as error:  # the next tick sends again; say so, count it, go on
            self.send_failures += 1
            self.log.warning("send failed: %s", error)

    def send_status_if_due(self, now: float) -> None:
        """The status frames, together, once per the status frame's DBC cycle time, and at
        once when the node's state or faults change (so a listener sees every transition)."""
        reported = self.reported()
        if now >= self._next_status or reported != self._reported:
            self._reported = reported
            frames = [
                (codec, record, self.next_counter(codec)) for codec, record in self.statuses()
            ]
            try:
                self.send_together(frames)
            except EncodeError as error:
                self.log.error("status not sent: %s", error)
            self._next_status = now + (self.status.cycle_time or 0.1)

    def reported(self) -> tuple[Any, ...]:
        """What a listener must hear of at once when it changes: the state and the faults."""
        return (self.node_state, self.fault)

    def statuses(self) -> list[tuple[MessageCodec, Any]]:
        """The cyclic status frames of this node, :attr:`status` among them, sent together
        in this order."""
        raise NotImplementedError

    # --- life cycle ---------------------------------------------------------------------

    def stop(self) -> None:
        self.running = False

    def finish(self) -> None:
        """The node's last words before its bus closes (nothing by default)."""

    def save(self, out: Path, result: dict[str, Any]) -> None:
        """Write ``result`` to ``out/<name>.json`` (a subclass may add files)."""
        (out / f"{self.name}.json").write_text(json.dumps(result, indent=2) + "\n")

    def result(self) -> dict[str, Any]:
        """What the node reports when it ends (written as JSON by :func:`node_main`)."""
        return {
            "node": self.name,
            "state": self.node_state.name,
            "faults": [flag.name for flag in self.Fault if flag in self.fault],
            "e2e": asdict(self.monitor.counts),
            "send_failures": self.send_failures,
        }

    @property
    def exit_code(self) -> int:
        return 0


@dataclass(frozen=True, slots=True)
class NodeSetup:
    """What :func:`node_main` hands to the factory of a node."""

    args: argparse.Namespace
    scenario: Scenario
    bus: can.BusABC
    clock_mode: ClockMode


def add_node_arguments(
    parser: argparse.ArgumentParser, clock_help: str, scenario_help: str = "scenario file or name"
) -> None:
    """The flags every node process takes."""
    parser.add_argument("scenario", nargs="?", default="reference", help=scenario_help)
    parser.add_argument(
        "--clock",
        choices=[mode.value for mode in ClockMode],
        default=ClockMode.REALTIME.value,
        help=clock_help,
    )
    parser.add_argument("--out", type=Path, help="folder for the node's result JSON (and log)")
    add_timing_arguments(parser)
    add_bus_arguments(parser)
    add_fault_arguments(parser)
    add_verbosity(parser)


def add_timing_arguments(parser: argparse.ArgumentParser) -> None:
    """The control rate and the process timing flags (the nodes', and the launcher's for both)."""
    parser.add_argument(
        "--rate",
        type=number(MIN_RATE_HZ, MAX_RATE_HZ),
        metavar="HZ",
        help=f"control rate in Hz, {MIN_RATE_HZ:g}-{MAX_RATE_HZ:g} (default: the scenario's)",
    )
    parser.add_argument(
        "--realtime-priority",
        type=number(1, 99, integer=True),
        metavar="N",
        help="run under SCHED_FIFO at priority N (1-99; needs root or CAP_SYS_NICE)",
    )
    parser.add_argument(
        "--plain-scheduling",
        action="store_true",
        help="do not ask the kernel for precise wake-ups (1 ns timer slack, short slice); "
        "for measuring what they bring",
    )


NodeT = TypeVar("NodeT", bound=Node)


def node_main(
    parser: argparse.ArgumentParser,
    argv: Sequence[str] | None,
    load: Callable[[str], Scenario],
    make: Callable[[NodeSetup], NodeT],
    run: Callable[[NodeT, argparse.Namespace], None],
) -> int:
    """The life of a node process: set up, run, report, close (see the module docstring).

    ``load`` reads the scenario with the node's own checks; ``make`` builds the node;
    ``run`` runs its loop until it is done or stopped (SIGINT, SIGTERM, NodeCommand stop).
    """
    args = parser.parse_args(argv)
    configure_logging(args.verbose)
    prog = parser.prog
    tune_process(args.realtime_priority, plain=args.plain_scheduling)
    try:
        spec = FaultSpec.parse(args.inject_faults) if args.inject_faults else None
        scenario = load(args.scenario)
        if args.rate:
            scenario = scenario.with_rate(args.rate)
        bus = open_bus_from_args(args)
    except (ScaraError, can.CanError, ValueError) as error:
        print(f"{prog}: {error}", file=sys.stderr)
        return 2
    if spec is not None:
        bus = FaultInjector(bus, spec)
    try:
        node = make(NodeSetup(args, scenario, bus, ClockMode(args.clock)))
    except ScaraError as error:
        bus.shutdown()
        print(f"{prog}: {error}", file=sys.stderr)
        return 2
    stop_on_signals(node.stop)
    settle_memory()
    started = time.monotonic()
    try:
        run(node, args)
        node.finish()
        result = node.result()
        result["wall_time_s"] = time.monotonic() - started
        result["injected"] = asdict(bus.counts) if isinstance(bus, FaultInjector) else None
        if args.out:  # before closing the bus, which may take a while to flush
            args.out.mkdir(parents=True, exist_ok=True)
            node.save(args.out, result)
        else:
            print(json.dumps(result, indent=2))
    finally:
        bus.shutdown()
    return node.exit_code


def stop_on_signals(stop: Callable[[], None]) -> None:
    """SIGINT and SIGTERM call ``stop`` (the process then closes its bus itself); SIGUSR1
    prints every thread's stack. For every process that owns a bus loop."""

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    faulthandler.register(signal.SIGUSR1, all_threads=True)  # kill -USR1: where is it?
