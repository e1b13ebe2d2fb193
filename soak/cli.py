"""``scara-soak``: the robot as a service, disturbed at random while it runs task after
task, then its recordings checked; ``scara-soak check RUN_DIR`` checks recordings alone.

Exit 0 when every invariant held, every disturbance was recovered from within the bound, no
process ended by itself and the long-lived ones kept their memory and file handles flat; 1
otherwise (the report names what, with the seed and the moment); 2 on bad arguments; 130 on
Ctrl-C (every child stopped, the report still written).
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from types import FrameType

from protocol.cli import add_verbosity, configure_logging, interruptible, number
from protocol.errors import ScaraError
from recorder.mcap_can import RecordingError
from recorder.recover import recover
from soak import schedule as plan
from soak.check import INVARIANTS, check
from soak.disturb import Disturber
from soak.drive import Driver, Operator, Tally, Watch, is_up
from soak.health import Health
from soak.report import Report, format_report
from soak.stack import Stack

READY_WITHIN = 90.0
"""s the stack may take to come up on a loaded 2-core machine."""
SETTLE = 15.0
"""s the soak waits at its end for the system to be back before it stops it."""
STEP = 0.1
"""s between the driver's decisions."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-soak",
        description="Run the robot as a service (routers, plant, controller, bridge, "
        "recorder) task after task while disturbing it at random (processes paused and "
        "killed, frames lost, corrupted, duplicated and reordered, foreign IDs, commands at "
        "the worst times), then check its recordings. 'scara-soak check RUN_DIR' checks "
        "the recordings of a soak, or any run.mcap, alone.",
    )
    parser.add_argument(
        "--minutes", type=number(0.0, low_open=True), default=10.0, help="(default %(default)g)"
    )
    parser.add_argument(
        "--seed",
        type=number(0, 2**31 - 1, integer=True),
        default=0,
        help="the schedule of disturbances and tasks is a function of it (default %(default)s)",
    )
    parser.add_argument(
        "--out", type=Path, help="the soak's folder (default out/soak/seed-SEED; emptied first)"
    )
    add_verbosity(parser)
    return parser


def build_check_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-soak check",
        description="Check the invariants on a soak's recordings (its folder) or on one "
        f"recording: {', '.join(INVARIANTS)}. Exit 1 on any violation.",
    )
    parser.add_argument("target", type=Path, help="a soak's folder, or an .mcap file")
    add_verbosity(parser)
    return parser


def main_check(argv: Sequence[str]) -> int:
    args = build_check_parser().parse_args(argv)
    configure_logging(args.verbose)
    if not args.target.exists():
        print(f"scara-soak check: {args.target}: no such file or folder", file=sys.stderr)
        return 2
    verdict = check(args.target)
    if verdict.recordings == 0 and not verdict.violations:
        print(f"scara-soak check: {args.target}: no recordings", file=sys.stderr)
        return 2
    counts = verdict.counts()
    print(
        f"{verdict.recordings} recordings, {verdict.frames} frames, {verdict.states} joint "
        f"states, {verdict.commands} commands ({verdict.unjudged_states} states of an "
        "unrecorded world not judged)"
    )
    for name in INVARIANTS:
        print(f"  {name:<16} {counts[name]} violations")
    for v in verdict.violations:
        print(f"  VIOLATION {v.invariant} at {v.t:.6f} ({v.recording}): {v.detail}")
    return 1 if verdict.violations else 0


def _interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def _thread(target: object, name: str) -> threading.Thread:
    thread = threading.Thread(target=target, name=name, daemon=True)  # type: ignore[arg-type]
    thread.start()
    return thread


def soak(args: argparse.Namespace) -> Report:
    """Run the soak of ``args``; its report (also in OUT/report.json and OUT/report.txt)."""
    schedule = plan.make_schedule(args.seed, args.minutes)
    kills = {
        node: sum(1 for d in schedule.disturbances if d.kind is plan.Kind.KILL and d.target == node)
        for node in plan.NODES
    }
    wire = {
        node: [plan.wire_faults(args.seed, node, start) for start in range(kills[node] + 1)]
        for node in plan.NODES
    }
    out: Path = args.out
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    (out / "schedule.json").write_text(
        json.dumps(
            {
                "seed": args.seed,
                "minutes": args.minutes,
                "disturbances": [{"at": d.at, "what": d.describe()} for d in schedule.disturbances],
                "wire": {node: [s.text() for s in specs] for node, specs in wire.items()},
            },
            indent=1,
        )
    )
    home = plan.home()
    began = time.monotonic()
    stack = Stack(out, wire)
    operator: Operator | None = None
    watch: Watch | None = None
    health = Health(stack.pids)
    disturber: Disturber | None = None
    driver: Driver | None = None
    start, started_epoch = time.monotonic(), time.time()
    interrupted = False
    try:
        stack.start_all()
        _thread(health.run, "health")
        operator = Operator(stack.keys_port, stack.users)
        watch = Watch(operator)
        _thread(watch.run, "watch")
        deadline = time.monotonic() + READY_WITHIN
        while not is_up(watch.latest):
            if time.monotonic() > deadline or stack.ended():
                raise ScaraError(f"the stack did not come up: see {out / 'logs'}")
            time.sleep(STEP)
        driver = Driver(operator, watch, lambda n: plan.task(args.seed, n, home))
        disturber = Disturber(stack, operator, driver, args.seed)
        start, started_epoch = time.monotonic(), time.time()
        _thread(lambda: disturber.run(schedule.disturbances, start), "disturber")
        end = start + args.minutes * 60.0
        while time.monotonic() < end:
            driver.step()
            time.sleep(STEP)
        disturber.stop()
        settle = time.monotonic() + SETTLE
        while not is_up(watch.latest) and time.monotonic() < settle:
            time.sleep(STEP)
    except KeyboardInterrupt:
        interrupted = True
        print("\nscara-soak: interrupted, stopping every process", file=sys.stderr)
    finally:
        if disturber is not None:
            disturber.stop()
        ended = stack.ended()
        if watch is not None:
            watch.stop()
        health.stop()
        stack.close()
        if operator is not None:
            operator.close()
    for path in stack.killed_recordings:
        try:
            recover(path, path.with_suffix(".recovered.mcap"))
        except RecordingError as error:
            print(f"scara-soak: {path}: {error}", file=sys.stderr)
    done = [] if disturber is None else disturber.done
    back = [None if watch is None else watch.back_after(d.ended or d.began) for d in done]
    report = Report(
        seed=args.seed,
        minutes=args.minutes,
        wall=time.monotonic() - began,
        started_epoch=started_epoch,
        done=done,
        back=back,
        tally=driver.tally if driver is not None else Tally(),
        raised=watch.raised if watch is not None else {},
        cleared=watch.cleared if watch is not None else {},
        verdict=check(out),
        growths=health.growths(),
        ended=ended,
        interrupted=interrupted,
    )
    health.write_csv(out / "health.csv")
    (out / "report.json").write_text(json.dumps(report.as_json(), indent=1))
    (out / "report.txt").write_text(format_report(report) + "\n")
    return report


def main(argv: Sequence[str] | None = None) -> int:
    arguments = list(sys.argv[1:] if argv is None else argv)
    if arguments[:1] == ["check"]:
        return main_check(arguments[1:])
    parser = build_parser()
    args = parser.parse_args(arguments)
    configure_logging(args.verbose)
    interruptible()
    signal.signal(signal.SIGTERM, _interrupt)
    args.out = args.out or Path("out/soak") / f"seed-{args.seed}"
    try:
        report = soak(args)
    except ScaraError as error:
        print(f"scara-soak: {error}", file=sys.stderr)
        return 1
    print(format_report(report))
    print(f"(in {args.out}: report.txt, report.json, schedule.json, recordings/, logs/)")
    if report.interrupted:
        return 130
    return 0 if report.passed else 1


if __name__ == "__main__":
    raise SystemExit(main())
