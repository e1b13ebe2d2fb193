"""``scara-sim``: run a scenario in-process in both coordination modes and compare them.

Prints the measures side by side, writes the figure (top view, 3D view, joints, k_T and
k_C) and the measures as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from controller.task_rules import load_task
from protocol.cli import add_verbosity, configure_logging, quiet_on_closed_pipe
from protocol.errors import ScaraError
from protocol.scenario import SCENARIO_DIR, Mode
from sim.measures import format_table
from sim.simulation import SimulationRun, simulate


def build_parser() -> argparse.ArgumentParser:
    known = ", ".join(sorted(p.stem for p in SCENARIO_DIR.glob("*.toml")))
    parser = argparse.ArgumentParser(
        prog="scara-sim",
        description="Run a scenario in the in-process simulation (control law + plant model, "
        "fixed step, deterministic) and compare fuzzy and conventional coordination.",
    )
    parser.add_argument(
        "scenario",
        nargs="?",
        default="reference",
        help=f"a scenario TOML file, or the name of a packaged one ({known}); default: reference",
    )
    parser.add_argument(
        "--mode",
        choices=["both", *(mode.value for mode in Mode)],
        default="both",
        help="which coordination to run (default: both, side by side)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("out"),
        help="folder for the figure and JSON (default: out)",
    )
    parser.add_argument("--no-figure", action="store_true", help="skip writing the figure")
    add_verbosity(parser)
    return parser


@quiet_on_closed_pipe
def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose)
    try:
        scenario = load_task(args.scenario)
    except ScaraError as error:
        print(f"scara-sim: bad scenario: {error}", file=sys.stderr)
        return 2
    modes = list(Mode) if args.mode == "both" else [Mode(args.mode)]
    runs: dict[str, SimulationRun] = {}
    for mode in modes:
        started = time.perf_counter()
        run = runs[mode.value] = simulate(scenario, mode)
        wall = time.perf_counter() - started
        simulated = run.log["clock"][-1] - run.log["clock"][0]  # to the run's end, not the plan's
        print(
            f"{scenario.name} [{mode.value}]: {simulated:.2f} s simulated in {wall:.3f} s "
            f"({simulated / wall:.0f}x real time, {len(run.log)} ticks)"
        )
    print()
    print(format_table({name: run.measures for name, run in runs.items()}))
    args.out.mkdir(parents=True, exist_ok=True)
    measures_path = args.out / f"{scenario.name}_measures.json"
    measures_path.write_text(
        json.dumps({name: run.measures.as_dict() for name, run in runs.items()}, indent=2) + "\n"
    )
    print(f"\nmeasures: {measures_path}")
    if not args.no_figure:
        from sim.figure import comparison_figure  # matplotlib only when drawing

        figure_path = comparison_figure(runs, args.out / f"{scenario.name}.png")
        print(f"figure:   {figure_path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
