"""``controller``: the command line of the controller process.

With a scenario it runs that scenario once (real time or lockstep, :class:`ControllerNode`);
without one, or with ``--service``, it is the service that takes tasks over CAN
(:class:`~controller.service.ServiceNode`). The node's life (flags every node takes, bus,
signals, result file, exit status) is :func:`protocol.node.node_main`'s.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from controller.node import COMMS_TIMEOUT, STALE_TICKS, ControllerNode
from controller.service import ServiceNode
from controller.task_rules import load_task
from protocol.cli import add_comms_timeout_argument, number, quiet_on_closed_pipe
from protocol.errors import ConfigError
from protocol.node import ClockMode, NodeSetup, add_node_arguments, node_main
from protocol.scenario import Mode, Scenario


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="controller",
        description="The SCARA controller: runs a scenario at a fixed rate and commands the "
        "plant's joint velocities over CAN.",
    )
    add_node_arguments(
        parser,
        "real time at absolute deadlines, or lockstep with the plant",
        "scenario file or name to run now; without one the controller is a service that "
        "waits for a task and a run request over CAN",
    )
    parser.set_defaults(scenario=None)
    parser.add_argument(
        "--service",
        action="store_true",
        help="be a service even with a scenario: it is the task in force, run on request",
    )
    parser.add_argument(
        "--mode", choices=[m.value for m in Mode], help="coordination (default: the scenario's)"
    )
    parser.add_argument(
        "--max-wall-time",
        type=number(0.0, low_open=True),
        metavar="S",
        help="give up after this many seconds",
    )
    add_comms_timeout_argument(
        parser, COMMS_TIMEOUT, f"default {COMMS_TIMEOUT:g}; must exceed {STALE_TICKS} ticks"
    )
    return parser


def load(source: str | None) -> Scenario:
    """The scenario to run, or without one the service's robot and gains (the defaults)."""
    return load_task(source) if source else Scenario("service", (), None)


def make(setup: NodeSetup) -> ControllerNode:
    """The service, or the one-shot controller of the scenario given."""
    args = setup.args
    scenario = setup.scenario.with_mode(Mode(args.mode)) if args.mode else setup.scenario
    if args.service or not scenario.waypoints:
        if setup.clock_mode is not ClockMode.REALTIME:
            raise ConfigError("--clock", "the service runs in real time only")
        task = scenario if scenario.waypoints else None
        return ServiceNode(setup.bus, scenario, task, args.comms_timeout, args.out)
    return ControllerNode(setup.bus, scenario, setup.clock_mode, args.comms_timeout)


def run(node: ControllerNode, args: argparse.Namespace) -> None:
    if node.clock_mode is ClockMode.LOCKSTEP:
        node.run_lockstep(max_wall_time=args.max_wall_time)
    else:
        node.run_realtime(args.max_wall_time)


@quiet_on_closed_pipe
def main(argv: Sequence[str] | None = None) -> int:
    return node_main(build_parser(), argv, load, make, run)


if __name__ == "__main__":
    raise SystemExit(main())
