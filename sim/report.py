"""The report of a co-simulation run, read back from the folder its nodes wrote.

``controller.json`` and ``plant_sim.json`` are the nodes' results and ``controller_log.npz``
the controller's log (after ``scara-run``, only inside the run's recording ``run.mcap``,
which holds the whole run); the measures are computed here from that log, by the same
:func:`~sim.measures.compute_measures` as the in-process simulation's. ``scara-report RUN``
prints it for a run whose nodes were started by hand; ``scara-run`` prints it at the end.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.reader import make_reader

from controller.run_end import RunOutcome
from controller.runlog import COLUMNS, RunLog
from protocol.cli import add_verbosity, configure_logging, quiet_on_closed_pipe
from protocol.errors import ScaraError
from protocol.scenario import parse_scenario
from sim.measures import Measures, compute_measures, format_table

LOG_FILE = "controller_log.npz"
RECORDING = "run.mcap"
"""The recording ``scara-run`` makes of a run; the log's copy in it is the one kept."""
MIN_ROWS = 20
"""Fewer logged control steps than this give no measures (nothing ran)."""


@dataclass(frozen=True, slots=True)
class RunReport:
    """What a run folder holds: the nodes' results, the log and the measures of the log."""

    controller: dict[str, Any]
    plant: dict[str, Any] | None
    log: RunLog
    measures: Measures | None


def read_log(path: Path | IO[bytes]) -> RunLog:
    """The controller's log as written by the controller node."""
    with np.load(path) as saved:
        columns = tuple(saved["columns"].tolist())
        if columns != COLUMNS:
            raise ScaraError(f"{path}: columns {columns} are not this version's {COLUMNS}")
        return RunLog.from_array(saved["data"])


def _log_source(out: Path) -> Path | IO[bytes]:
    """The log file, or the copy inside the run's recording (``scara-run`` keeps only that)."""
    path = out / LOG_FILE
    recording = out / RECORDING
    if path.exists() or not recording.exists():
        return path
    with recording.open("rb") as stream:
        for attachment in make_reader(stream).iter_attachments():
            if attachment.name == LOG_FILE:
                return io.BytesIO(attachment.data)
    raise ScaraError(f"{out}: no {LOG_FILE}, in the folder or attached to {RECORDING}")


def read_run(out: Path) -> RunReport:
    """The report of the run in ``out``, measured against the scenario the controller ran
    (its result carries it whole)."""
    controller: dict[str, Any] = json.loads((out / "controller.json").read_text())
    plant_file = out / "plant_sim.json"
    plant = json.loads(plant_file.read_text()) if plant_file.exists() else None
    log = read_log(_log_source(out))
    scenario = parse_scenario(controller["scenario_document"])
    measures = None
    if len(log) >= MIN_ROWS:
        measures = compute_measures(scenario, log, RunOutcome(controller["outcome"]))
    return RunReport(controller, plant, log, measures)


def format_report(report: RunReport) -> str:
    """The measures, the loop statistics and what each side received, as text."""
    result = report.controller
    loop = result["loop"]
    lines = [
        f"{result['scenario']} [{result['mode']}, {result['clock']}, {result['rate_hz']:g} Hz]: "
        f"{'completed' if result['completed'] else 'NOT completed'}, state {result['state']}"
        + (f", faults {', '.join(result['faults'])}" if result["faults"] else "")
    ]
    if report.measures is not None:
        lines += ["", format_table({result["mode"]: report.measures})]
    lines += [""] + (_lockstep(loop) if result["clock"] == "lockstep" else _realtime(loop))
    lines.append(
        f"wall time {result['wall_time_s']:.2f} s for {loop['ticks']} ticks: "
        f"{result['realtime_factor']:.1f}x real time"
    )
    lines.append(_received("controller received:", result["e2e"]) + " (none acted on)")
    if report.plant:
        plant = report.plant
        lines.append(
            _received("plant received:", plant["e2e"])
            + f"; collisions {plant['stats']['collisions']}, state {plant['state']}"
        )
    return "\n".join(lines)


def _realtime(loop: dict[str, Any]) -> list[str]:
    """How the loop kept its deadlines: ``loops`` counts every period, ``ticks`` those that
    commanded the run (none while holding, or idle)."""
    lines = [
        f"loop: {loop['ticks']} control ticks in {loop['loops']} periods; lateness p50 "
        f"{loop['lateness_p50_us']:.0f} us, p99 {loop['lateness_p99_us']:.0f} us, max "
        f"{loop['lateness_max_us']:.0f} us; deadline misses {loop['deadline_misses']} "
        f"({100 * loop['deadline_miss_fraction']:.2f} %), overruns {loop['overruns']}",
        f"holds (no fresh joint state for 3 ticks): {loop['holds']}, "
        f"{1e3 * loop['hold_time_s']:.1f} ms in all, longest {1e3 * loop['longest_hold_s']:.1f} ms",
    ]
    if loop["answered_within_tick_fraction"] is not None:
        lines.append(
            f"answer to a command within one tick: "
            f"{100 * loop['answered_within_tick_fraction']:.2f} % (round trip p50 "
            f"{loop['answer_delay_p50_us']:.0f} us, p99 {loop['answer_delay_p99_us']:.0f} us)"
        )
    return lines


def _lockstep(loop: dict[str, Any]) -> list[str]:
    """Lockstep has no periods, so no deadlines, lateness or holds: each tick waits for the
    plant's step (``loops``, the real-time loop's periods, stays 0)."""
    return [
        f"loop: {loop['ticks']} control ticks in lockstep, each answered by one plant step "
        f"(no deadlines); retries (a tick's command and StepSync sent again for want of "
        f"an answer): {loop['lockstep_retries']}"
    ]


def _received(label: str, e2e: dict[str, int]) -> str:
    return (
        f"{label:<21}{e2e['ok']} ok, {e2e['lost']} lost, {e2e['repeated']} repeated, "
        f"{e2e['stale']} stale, {e2e['corrupt']} corrupt, {e2e.get('unknown', 0)} unknown ID"
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-report",
        description="Print the measures and statistics of a co-simulation run from the folder "
        "its nodes wrote (--out of controller and plant_sim).",
    )
    parser.add_argument("run", type=Path, help="the run folder, e.g. out/run")
    add_verbosity(parser)
    return parser


@quiet_on_closed_pipe
def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose)
    try:
        report = read_run(args.run)
    except (OSError, ValueError, KeyError, ScaraError) as error:
        print(f"scara-report: cannot read the run in {args.run}: {error}", file=sys.stderr)
        return 2
    print(format_report(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
