"""``scara-plot run.mcap``: the figure of a recorded run, and its report with the measures.

A recording made by ``scara-run`` carries the run's results and the controller's log as
attachments (one run, one file). They are unpacked to a temporary folder and read exactly
as ``scara-report`` reads a run folder, so the measures printed are the ones printed live.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from protocol.cli import add_verbosity, configure_logging, quiet_on_closed_pipe
from protocol.errors import ScaraError
from protocol.scenario import parse_scenario
from recorder.mcap_can import RecordingError, read_attachments
from recorder.node import RUN_FILES
from sim.figure import comparison_figure
from sim.report import format_report, read_run
from sim.simulation import SimulationRun


def unpack_run(path: Path, folder: Path) -> None:
    """The run's results and log, from the recording's attachments into ``folder``."""
    attachments = read_attachments(path)
    needed = ("controller.json", "controller_log.npz")
    missing = [name for name in needed if name not in attachments]
    if missing:
        raise RecordingError(
            f"{path}: no {' or '.join(missing)} attached: record with scara-run, which "
            "attaches the run's results when it ends"
        )
    for name in RUN_FILES:
        if name in attachments:
            (folder / name).write_bytes(attachments[name])


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-plot",
        description="Draw the figure of a recorded run and print its report and measures.",
    )
    parser.add_argument("file", type=Path, help="a recording made by scara-run (run.mcap)")
    parser.add_argument(
        "--out", type=Path, help="figure file (default: FILE with .png instead of .mcap)"
    )
    add_verbosity(parser)
    return parser


@quiet_on_closed_pipe
def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose)
    figure = args.out or args.file.with_suffix(".png")
    with tempfile.TemporaryDirectory() as folder:
        try:
            unpack_run(args.file, Path(folder))
            report = read_run(Path(folder))
        except (RecordingError, ScaraError, OSError, ValueError, KeyError) as error:
            print(f"scara-plot: {error}", file=sys.stderr)
            return 2
    print(format_report(report))
    if report.measures is None:
        print("scara-plot: the run logged too little to draw", file=sys.stderr)
        return 1
    scenario = parse_scenario(report.controller["scenario_document"])
    scenario_run = SimulationRun(scenario, report.log, report.measures)
    comparison_figure({report.controller["mode"]: scenario_run}, figure)
    print(f"figure: {figure}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
