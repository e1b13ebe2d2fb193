"""What the ``controller`` and ``plant_sim`` processes share: the clock modes, the flags they
both take, opening the scenario and the bus, and stopping cleanly on SIGINT or SIGTERM."""

from __future__ import annotations

import argparse
import gc
import signal
import sys
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from types import FrameType

import can

from controller.scenario import Scenario, load_scenario
from protocol.bus import (
    add_bus_arguments,
    add_priority_argument,
    apply_priority,
    open_bus_from_args,
)
from protocol.errors import ScaraError
from protocol.faults import FaultInjector, FaultSpec, add_fault_arguments


class ClockMode(Enum):
    REALTIME = "realtime"
    LOCKSTEP = "lockstep"


@dataclass(frozen=True, slots=True)
class NodeSetup:
    scenario: Scenario
    bus: can.BusABC
    injector: FaultInjector | None


def add_node_arguments(parser: argparse.ArgumentParser, clock_help: str) -> None:
    parser.add_argument("scenario", nargs="?", default="reference", help="scenario file or name")
    parser.add_argument(
        "--clock",
        choices=[mode.value for mode in ClockMode],
        default=ClockMode.REALTIME.value,
        help=clock_help,
    )
    parser.add_argument("--rate", type=float, help="control rate in Hz (default: the scenario's)")
    add_bus_arguments(parser)
    add_fault_arguments(parser)
    add_priority_argument(parser)


def open_node(args: argparse.Namespace, prog: str) -> NodeSetup | None:
    """The scenario and the bus for ``args``; None (after saying why) if either is bad."""
    apply_priority(args.realtime_priority, prog)
    try:
        scenario = load_scenario(args.scenario)
        if args.rate:
            scenario = scenario.with_rate(args.rate)
        bus = open_bus_from_args(args)
    except (ScaraError, can.CanError, ValueError) as error:
        print(f"{prog}: {error}", file=sys.stderr)
        return None
    if not args.inject_faults:
        return NodeSetup(scenario, bus, None)
    try:
        injector = FaultInjector(bus, FaultSpec.parse(args.inject_faults))
    except ScaraError as error:
        bus.shutdown()
        print(f"{prog}: {error}", file=sys.stderr)
        return None
    return NodeSetup(scenario, injector, injector)


def settle_memory() -> None:
    """Collect once, then freeze what start-up allocated, so that later garbage collections
    scan only the objects the loop makes (a full collection over every module took
    milliseconds here, long enough to starve the other process at 1 kHz)."""
    gc.collect()
    gc.freeze()


def stop_on_signals(stop: Callable[[], None]) -> None:
    """SIGINT and SIGTERM end the node's loop; it then shuts its bus down itself."""

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
