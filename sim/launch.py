"""``scara-run``: start the plant and the controller as separate OS processes on one CAN
transport, run a scenario, stop both cleanly (Ctrl-C too) and print the measures and the loop
statistics.
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from types import FrameType
from typing import Any

from tqdm import tqdm

from controller.coordination import Mode
from controller.measures import Measures, format_table
from controller.process import ClockMode
from controller.scenario import load_scenario
from protocol.bus import add_bus_arguments, add_priority_argument, resolve_transport
from protocol.errors import ScaraError

STOP_GRACE = 5.0
"""s a process gets to exit after SIGINT before it is killed."""
REALTIME_SLACK = 10.0
"""s a real-time run may take beyond twice the scenario's duration (start-up, waiting)."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-run",
        description="Co-simulate a scenario: plant_sim and controller as two OS processes "
        "talking CAN frames only; prints the measures and loop statistics.",
    )
    parser.add_argument("scenario", nargs="?", default="reference", help="scenario file or name")
    parser.add_argument("--mode", choices=[m.value for m in Mode], help="coordination mode")
    parser.add_argument(
        "--clock",
        choices=[m.value for m in ClockMode],
        default=ClockMode.REALTIME.value,
        help="real time (each process on its own clock) or lockstep (deterministic)",
    )
    parser.add_argument("--rate", type=float, help="control rate in Hz (default 500)")
    parser.add_argument("--out", type=Path, default=Path("out/run"), help="results folder")
    parser.add_argument(
        "--controller-first", action="store_true", help="start the controller before the plant"
    )
    parser.add_argument(
        "--inject-faults",
        metavar="SPEC",
        help="drop/corrupt frames both nodes send, e.g. drop=0.05,corrupt=0.01 (tests)",
    )
    parser.add_argument("--timeout", type=float, default=600.0, help="give up after this many s")
    add_bus_arguments(parser)
    add_priority_argument(parser)
    return parser


def node_commands(args: argparse.Namespace, duration: float) -> tuple[list[str], list[str]]:
    """The command lines of the plant and the controller for ``args``.

    In real time the controller gets twice the scenario's ``duration`` (plus start-up) at most:
    a controller in fault waits for a reset that nobody here will send.
    """
    interface, channel = resolve_transport(args.interface, args.channel)
    bus = ["--interface", interface, "--channel", channel]
    for option in args.bus_option:
        bus += ["--bus-option", option]
    common = [args.scenario, "--clock", args.clock, *bus]
    if args.rate:
        common += ["--rate", str(args.rate)]
    if args.realtime_priority:
        common += ["--realtime-priority", str(args.realtime_priority)]
    plant = [
        sys.executable,
        "-m",
        "plant_sim.node",
        *common,
        "--stats",
        str(args.out / "plant.json"),
    ]
    controller = [sys.executable, "-m", "controller.node", *common, "--out", str(args.out)]
    wall_time = args.timeout
    if args.clock == ClockMode.REALTIME.value:
        wall_time = min(wall_time, 2.0 * duration + REALTIME_SLACK)
    controller += ["--max-wall-time", f"{wall_time:g}"]
    if args.mode:
        controller += ["--mode", args.mode]
    if args.inject_faults:
        plant += ["--inject-faults", f"{args.inject_faults},seed=2"]
        controller += ["--inject-faults", f"{args.inject_faults},seed=1"]
    return plant, controller


def stop(process: subprocess.Popen[bytes]) -> int:
    """SIGINT, then SIGKILL if it does not exit within STOP_GRACE."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(STOP_GRACE)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    return process.returncode


def report(out: Path) -> dict[str, Any]:
    """The controller's and the plant's results, as they wrote them."""
    result: dict[str, Any] = json.loads((out / "controller_result.json").read_text())
    plant_file = out / "plant.json"
    result["plant"] = json.loads(plant_file.read_text()) if plant_file.exists() else None
    return result


def print_report(result: dict[str, Any]) -> None:
    loop = result["loop"]
    print(
        f"{result['scenario']} [{result['mode']}, {result['clock']}, {result['rate_hz']:g} Hz]: "
        f"{'completed' if result['completed'] else 'NOT completed'}, state {result['state']}"
        + (f", faults {', '.join(result['faults'])}" if result["faults"] else "")
    )
    if result["measures"]:
        values = dict(result["measures"])
        values.pop("max_waypoint_miss")
        values["waypoint_miss"] = tuple(values["waypoint_miss"])
        print()
        print(format_table({result["mode"]: Measures(**values)}))
    print()
    print(
        f"loop: {loop['ticks']} control ticks of {loop['loops']}; lateness p50 "
        f"{loop['lateness_p50_us']:.0f} us, p99 {loop['lateness_p99_us']:.0f} us, max "
        f"{loop['lateness_max_us']:.0f} us; deadline misses {loop['deadline_misses']} "
        f"({100 * loop['deadline_miss_fraction']:.2f} %), overruns {loop['overruns']}"
    )
    if loop["answered_within_tick_fraction"] is not None:
        print(
            f"answer to a command within one tick: "
            f"{100 * loop['answered_within_tick_fraction']:.2f} % (delay p50 "
            f"{loop['answer_delay_p50_us']:.0f} us, p99 {loop['answer_delay_p99_us']:.0f} us)"
        )
    else:
        print(f"lockstep retries: {loop['lockstep_retries']}")
    print(
        f"wall time {result['wall_time_s']:.2f} s for {loop['ticks']} ticks: "
        f"{result['realtime_factor']:.1f}x real time"
    )
    e2e = result["e2e"]
    print(
        f"controller received: {e2e['ok']} ok, {e2e['lost']} lost, {e2e['repeated']} repeated, "
        f"{e2e['stale']} stale, {e2e['corrupt']} corrupt (none acted on)"
    )
    plant = result.get("plant")
    if plant:
        pe = plant["e2e"]
        print(
            f"plant received:      {pe['ok']} ok, {pe['lost']} lost, {pe['repeated']} repeated, "
            f"{pe['stale']} stale, {pe['corrupt']} corrupt; collisions "
            f"{plant['stats']['collisions']}, state {plant['state']}"
        )


def _interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    signal.signal(signal.SIGTERM, _interrupt)  # stop the nodes on SIGTERM as on Ctrl-C
    try:
        scenario = load_scenario(args.scenario)
    except ScaraError as error:
        print(f"scara-run: bad scenario: {error}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    for stale in ("controller_result.json", "plant.json"):
        (args.out / stale).unlink(missing_ok=True)
    plant_command, controller_command = node_commands(args, scenario.duration)
    order = (
        [controller_command, plant_command]
        if args.controller_first
        else [plant_command, controller_command]
    )
    processes: list[subprocess.Popen[bytes]] = []
    interrupted = False
    try:
        processes += [subprocess.Popen(command) for command in order]
        controller = processes[0] if args.controller_first else processes[1]
        started = time.monotonic()
        with tqdm(
            total=round(scenario.duration, 1),
            unit="s",
            desc=f"{scenario.name} ({args.clock})",
            disable=None,
            bar_format="{l_bar}{bar}| {n:.1f}/{total} s wall",
        ) as progress:
            while controller.poll() is None:
                time.sleep(0.1)
                progress.n = min(time.monotonic() - started, progress.total)
                progress.refresh()
    except KeyboardInterrupt:
        interrupted = True
        print("\nscara-run: interrupted, stopping the nodes", file=sys.stderr)
    finally:
        codes = [stop(process) for process in reversed(processes)]
    if interrupted:
        return 130
    if not (args.out / "controller_result.json").exists():
        print(f"scara-run: the controller wrote no result (exit codes {codes})", file=sys.stderr)
        return 1
    print_report(report(args.out))
    return controller.returncode or 0


if __name__ == "__main__":
    raise SystemExit(main())
