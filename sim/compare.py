"""``scara-compare``: fuzzy against conventional coordination over many generated scenarios.

The scenarios come from the generator (``sim.generator``, by seed); each mode runs them in
the batch simulator (:mod:`sim.batch`), in batches of similar durations spread over a pool
of worker processes, or over a Dask cluster with ``--scheduler``. Prints a table of both
modes side by side, and writes every run's measures as CSV, a figure of their distributions
and the worst case of each mode drawn like the paper's Figs. 8 and 9 (re-run in the scalar
simulation for its log). ``--sweep`` repeats the study for other gains or fuzzy rule bases.
``--family`` picks the scenarios (the tuned-on mix by default); the held-out part is refused
unless ``--held-out`` is given, so that nobody tunes on it by accident.

This module is the command line only; the study's jobs are the modules of :mod:`sim.study`.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from protocol.cli import add_verbosity, configure_logging, interruptible, quiet_on_closed_pipe
from protocol.errors import ConfigError
from protocol.scenario import Mode, Scenario
from sim.generator import HELD_OUT_SEEDS, Family, is_held_out
from sim.study.jobs import (
    DEFAULT_BATCH,
    GENERATE_CHUNK,
    Outcome,
    generate_chunk,
    plan_jobs,
    run_job,
    run_ticks,
)
from sim.study.pool import Cluster, Processes
from sim.study.refusals import DEFAULT_CHECKED, refusal_report
from sim.study.results import (
    compare_jerk,
    format_summary,
    jerk_report,
    summary,
    write_csv,
    write_figures,
)
from sim.study.variants import BASELINE, parse_sweep

DEFAULT_COUNT = 1000

log = logging.getLogger("scara.compare")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-compare",
        description="Fuzzy against conventional coordination over generated scenarios, in the "
        "batch simulator: a table of both modes, a CSV of every run, a figure.",
    )
    parser.add_argument(
        "-n",
        "--count",
        type=int,
        default=DEFAULT_COUNT,
        help=f"scenarios (default {DEFAULT_COUNT})",
    )
    parser.add_argument("--seed", type=int, default=0, help="the generator's seed (default 0)")
    parser.add_argument(
        "--family",
        choices=[family.value for family in Family],
        default=Family.MIX.value,
        metavar="NAME",
        help="which scenarios: mix (the seven cases the law was tuned on, the default), inner "
        "or outer (an obstacle at a reach limit), fast (a detour at up to 0.4 m/s), multi "
        "(several detours in one task), user (tasks as users wrote them), wide (obstacles "
        "25-50 cm long at the inner limit: many without a way round, refused), held_out, "
        "edge_obstacle, edge_limit, edge_speed, edge_reach (user's tasks at the edge of a "
        "rule of what a task may ask: half just inside, half just outside, refused)",
    )
    parser.add_argument(
        "--held-out",
        action="store_true",
        help=f"allow the held-out part (family held_out, or a seed from {HELD_OUT_SEEDS}): "
        "only to judge the law once it is tuned, never to tune it",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("out/compare"),
        help="folder for the CSV and the figures (default out/compare)",
    )
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument(
        "--batch",
        type=int,
        default=DEFAULT_BATCH,
        help=f"most runs per batch, a scenario in one mode being one run (default {DEFAULT_BATCH})",
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run the batches on the Dask cluster of this scheduler (tcp://host:port)",
    )
    parser.add_argument(
        "--sweep",
        action="append",
        default=[],
        metavar="NAME=V1,V2,...",
        help="also run each value of a controller gain (switch_distance=0.03,0.07), of a "
        "fuzzy input term (min_distance.near=0:0:0.02:0.05, a:b:c:d) or of the output peaks "
        "(k_C.peaks=0.1:0.5:0.9); repeatable",
    )
    parser.add_argument(
        "--check-refused",
        type=int,
        default=DEFAULT_CHECKED,
        metavar="N",
        help="check N of the tasks the gate refuses by brute force, each rule by a search "
        f"of its own (a way round it missed, ...; default {DEFAULT_CHECKED})",
    )
    parser.add_argument("--no-figure", action="store_true", help="skip the figures")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_verbosity(parser)
    return parser


@quiet_on_closed_pipe
def main(argv: Sequence[str] | None = None) -> int:
    try:
        return _main(argv)
    except KeyboardInterrupt:
        print("scara-compare: interrupted", file=sys.stderr)
        return 130


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.verbose)
    interruptible()
    for flag, value, least in (
        ("--count", args.count, 1),
        ("--workers", args.workers, 1),
        ("--batch", args.batch, 1),
        ("--seed", args.seed, 0),
    ):
        if value < least:
            parser.error(f"{flag} must be at least {least}, got {value}")
    family = Family(args.family)
    if is_held_out(family, args.seed) and not args.held_out:
        parser.error(
            f"family {family.value} with seed {args.seed} is held out for judging the tuned "
            "law; give --held-out to run it"
        )
    variants = [BASELINE]
    for text in args.sweep:
        try:
            variants += parse_sweep(text)
        except ConfigError as error:
            parser.error(f"--sweep {text}: {error}")

    executor: Processes | Cluster | None = None
    outcomes: list[Outcome] = []
    try:
        started = time.perf_counter()
        bar = _bar(args.count, "generating", "scenario", args.quiet)
        executor = (
            Cluster(args.scheduler) if args.scheduler else Processes(args.workers, bar.update)
        )
        indices = list(range(args.count))
        chunks = [
            (args.seed, indices[i : i + GENERATE_CHUNK], family, args.held_out)
            for i in indices[::GENERATE_CHUNK]
        ]
        generated: dict[int, Scenario] = {}
        refusals: dict[int, tuple[Scenario, ConfigError]] = {}
        for chunk in executor.map(generate_chunk, chunks):
            for index, scenario, refusal in chunk:
                if refusal is None:
                    generated[index] = scenario
                else:
                    refusals[index] = (scenario, refusal)
            bar.update(len(chunk))
        bar.close()
        log.info(
            "generated %d scenarios of seed %d in %.1f s (family %s)",
            args.count,
            args.seed,
            time.perf_counter() - started,
            family.value,
        )
        scenarios = [generated[index] for index in indices if index in generated]
        # In the generator's order, not the workers': the refusals checked are drawn from it.
        refused = [refusals[index] for index in indices if index in refusals]
        print(refusal_report(args.count, refused, args.check_refused))
        if not scenarios:
            return 0
        jobs = plan_jobs(scenarios, variants, args.batch, args.workers)
        total = sum(run_ticks(scenario) for job in jobs for scenario in job.scenarios)
        log.info(
            "%d runs of %d variants in %d batches on %s",
            sum(len(job.scenarios) for job in jobs),
            len(variants),
            len(jobs),
            args.scheduler or f"{args.workers} worker processes",
        )
        for job in jobs:
            log.debug(
                "batch of %s: %d runs, %d ticks the longest",
                job.variant,
                len(job.scenarios),
                max(run_ticks(scenario) for scenario in job.scenarios),
            )
        started = time.perf_counter()
        bar = _bar(total, "simulating", "step", args.quiet)
        if isinstance(executor, Processes):
            executor.advance = bar.update
        for result in executor.map(run_job, [(job,) for job in jobs]):
            outcomes += result
            if not executor.streams:
                bar.update(sum(run_ticks(outcome.scenario) for outcome in result))
        bar.close()
        log.info("simulated %d steps in %.1f s", total, time.perf_counter() - started)
    finally:
        if executor is not None:
            executor.close()
    groups: dict[tuple[str, Mode], list[Outcome]] = {}
    for outcome in sorted(outcomes, key=lambda o: o.index):
        groups.setdefault((outcome.variant, outcome.mode), []).append(outcome)
    columns = {
        (mode.value if variant is BASELINE else f"{mode.value} {variant.name}"): summary(
            groups[(variant.name, mode)]
        )
        for variant in variants
        for mode in variant.modes
    }
    print(format_summary(columns))
    baseline = {mode: groups[(BASELINE.name, mode)] for mode in Mode}
    print()
    print(jerk_report(compare_jerk(baseline[Mode.FUZZY], baseline[Mode.CONVENTIONAL])))
    args.out.mkdir(parents=True, exist_ok=True)
    csv_path = args.out / "compare.csv"
    write_csv(csv_path, outcomes)
    print(f"\nmeasures: {csv_path}")
    if not args.no_figure:
        for path in write_figures(args.out, baseline):
            print(f"figure:   {path}")
    return 0


def _bar(total: int, what: str, unit: str, quiet: bool) -> Any:
    return tqdm(total=total, unit=unit, unit_scale=True, desc=what, disable=quiet, file=sys.stderr)


if __name__ == "__main__":
    raise SystemExit(main())
