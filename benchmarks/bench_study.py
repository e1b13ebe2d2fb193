"""Study benchmark: the batch simulator over generated scenarios in both modes, side by side
with the scalar simulation in the same run.

Measures:

1. generating the scenarios (``sim.generator``, on the same worker processes; not timed
   against a target: the study's own cost is the simulation);
2. the batch simulator (``sim.batch``) on every scenario in both modes, in batches spread over
   a pool of worker processes as ``scara-compare`` runs them: wall time and microseconds per
   scenario-step (wall time over the ticks of every run);
3. the scalar simulation (``sim.simulation.simulate``) on a sample of the same scenarios in
   both modes, microseconds per step, and the speed ratio; the sample's measures are also
   compared with the batch's (they must agree to 1e-9).

Prints a Markdown table with each target and PASS/FAIL; ``--json PATH`` also writes the numbers.
Run from the project root: ``python benchmarks/bench_study.py [--count N] [--quick] [--json PATH]``;
``--before REV [--rounds N]`` runs it on revision REV's code and on this tree's, in turns, and
prints both side by side.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import random
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
from against import add_against_arguments, side_by_side

from protocol.scenario import Mode, Scenario
from sim.measures import Measures
from sim.simulation import simulate
from sim.study.jobs import (
    DEFAULT_BATCH,
    GENERATE_CHUNK,
    Outcome,
    generate_chunk,
    plan_jobs,
    run_job,
)
from sim.study.pool import Processes
from sim.study.variants import BASELINE

FULL_COUNT = 10_000
QUICK_COUNT = 1_000
SEED = 2026
SCALAR_SAMPLE = 3
"""Scenarios per mode run in the scalar simulation."""

TARGET_WALL_S = 120.0
"""For FULL_COUNT scenarios in both modes (scaled to the count run)."""
TARGET_STEP_US = 1.2
TARGET_RATIO = 50.0
TARGET_AGREEMENT = 1e-9
"""The batch and the scalar simulation run one law: their measures agree to round-off."""


@dataclass(slots=True)
class Row:
    """One line of the result table."""

    key: str
    label: str
    value: float
    unit: str
    target: str = ""
    passed: bool | None = None


def generate(count: int, executor: Processes) -> list[Scenario]:
    indices = list(range(count))
    chunks = [(SEED, indices[i : i + GENERATE_CHUNK]) for i in indices[::GENERATE_CHUNK]]
    generated: dict[int, Scenario] = {}
    for chunk in executor.map(generate_chunk, chunks):
        generated.update((index, scenario) for index, scenario, _ in chunk)
    return [generated[index] for index in indices]


def ticks(scenario: Scenario) -> int:
    return round(scenario.duration / scenario.controller.period) + 1


def largest_difference(batch: Measures, scalar: Measures) -> float:
    """Largest relative difference over the measures (0 where both are equal or NaN; infinite
    where the runs' outcomes differ)."""
    if batch.outcome != scalar.outcome:
        return math.inf
    worst = 0.0
    for spec in fields(Measures):
        if spec.name == "outcome":
            continue
        first, second = getattr(batch, spec.name), getattr(scalar, spec.name)
        for a, b in zip(np.atleast_1d(first), np.atleast_1d(second), strict=True):
            a, b = float(a), float(b)
            if a == b or (math.isnan(a) and math.isnan(b)):
                continue
            worst = max(worst, abs(a - b) / max(abs(a), abs(b), 1e-12))
    return worst


def run(count: int, workers: int, say: Callable[[str], None]) -> tuple[list[Row], list[str]]:
    """All measurements; the table rows and notes to print under it."""
    rows: list[Row] = []
    notes: list[str] = []
    executor = Processes(workers, lambda _: None)
    try:
        say(f"[1/3] generating {count} scenarios on {workers} workers")
        started = time.perf_counter()
        scenarios = generate(count, executor)
        generation = time.perf_counter() - started
        rows.append(Row("generate_s", f"1. Generate {count} scenarios", generation, "s"))

        jobs = plan_jobs(scenarios, [BASELINE], DEFAULT_BATCH, workers)
        steps = 2 * sum(ticks(s) for s in scenarios)
        say(f"[2/3] batch simulator: {len(jobs)} batches, {steps:,} scenario-steps")
        started = time.perf_counter()
        outcomes: dict[tuple[Mode, int], Outcome] = {}
        for result in executor.map(run_job, [(job,) for job in jobs]):
            outcomes.update(((o.mode, o.index), o) for o in result)
        wall = time.perf_counter() - started
    finally:
        executor.close()
    target_wall = TARGET_WALL_S * count / FULL_COUNT
    rows.append(
        Row(
            "batch_wall_s",
            f"2. Batch simulator, {count} scenarios x 2 modes, {workers} workers: wall time",
            wall,
            "s",
            f"<= {target_wall:g} s",
            wall <= target_wall,
        )
    )
    batch_us = wall / steps * 1e6
    rows.append(
        Row(
            "batch_us_per_step",
            f"2. Batch simulator: wall time per scenario-step ({steps:,} steps)",
            batch_us,
            "us",
            f"<= {TARGET_STEP_US:g} us",
            batch_us <= TARGET_STEP_US,
        )
    )
    rows.append(
        Row(
            "batch_core_us_per_step",
            f"2. Batch simulator: core time per scenario-step (wall x {workers} workers)",
            batch_us * workers,
            "us",
        )
    )

    sample = random.Random(SEED).sample(range(count), SCALAR_SAMPLE * 2)
    scalar_wall = 0.0
    scalar_steps = 0
    difference = 0.0
    for number, index in enumerate(sample):
        mode = list(Mode)[number % 2]
        say(f"[3/3] scalar simulation {number + 1}/{len(sample)}: #{index} {mode.value}")
        started = time.perf_counter()
        run_ = simulate(scenarios[index], mode)
        scalar_wall += time.perf_counter() - started
        scalar_steps += len(run_.log)
        difference = max(
            difference, largest_difference(outcomes[(mode, index)].run.measures, run_.measures)
        )
    scalar_us = scalar_wall / scalar_steps * 1e6
    rows.append(
        Row(
            "scalar_us_per_step",
            f"3. Scalar simulation: time per step ({len(sample)} runs, {scalar_steps:,} steps)",
            scalar_us,
            "us",
        )
    )
    ratio = scalar_us / batch_us
    rows.append(
        Row(
            "ratio",
            "3. Speed ratio per scenario-step, scalar / batch (wall)",
            ratio,
            "x",
            f">= {TARGET_RATIO:g}x",
            ratio >= TARGET_RATIO,
        )
    )
    rows.append(
        Row(
            "ratio_per_core",
            "3. Speed ratio per scenario-step, scalar / batch (core time)",
            scalar_us / (batch_us * workers),
            "x",
        )
    )
    notes.append(
        f"Scenarios: sim.generator seed {SEED}, mean duration "
        f"{np.mean([s.duration for s in scenarios]):.1f} s at "
        f"{scenarios[0].controller.rate_hz:g} Hz; {len(jobs)} batches of both modes' runs "
        f"(at most {DEFAULT_BATCH} each) sorted by duration and cut where their costs come "
        "out even, on a spawn process pool; generation is not in the batch wall time."
    )
    rows.append(
        Row(
            "agreement",
            "3. Largest relative difference, sampled scalar runs' measures vs the batch's",
            difference,
            "relative",
            f"<= {TARGET_AGREEMENT:g}",
            difference <= TARGET_AGREEMENT,
        )
    )
    if count != FULL_COUNT:
        notes.append(f"The wall-time target is the issue's {TARGET_WALL_S:g} s scaled to {count}.")
    return rows, notes


def fmt(value: float, unit: str) -> str:
    if unit == "x":
        return f"{value:.0f}x"
    if unit == "us":
        return f"{value:.2f} us"
    if unit == "relative":
        return f"{value:.1e}"
    return f"{value:.1f} s"


def markdown(rows: Sequence[Row]) -> str:
    lines = ["| Measurement | Value | Target | Result |", "|---|---:|---|:---:|"]
    for row in rows:
        verdict = "-" if row.passed is None else "PASS" if row.passed else "FAIL"
        lines.append(
            f"| {row.label} | {fmt(row.value, row.unit)} | {row.target or '-'} | {verdict} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark; 0 if every target passes, 1 otherwise."""
    parser = argparse.ArgumentParser(
        description=(
            "Benchmark the batch simulator on generated scenarios in both modes against the "
            "scalar simulation; print a Markdown table with targets and PASS/FAIL. Exit "
            "status 1 if any target fails."
        )
    )
    parser.add_argument(
        "--count", type=int, help=f"scenarios (default {FULL_COUNT}; {QUICK_COUNT} with --quick)"
    )
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_COUNT} scenarios")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument("--json", type=Path, metavar="PATH", help="also write the numbers here")
    add_against_arguments(parser)
    args = parser.parse_args(argv)
    count = args.count or (QUICK_COUNT if args.quick else FULL_COUNT)
    if count < SCALAR_SAMPLE * 2 or args.workers < 1:
        parser.error(f"--count must be at least {SCALAR_SAMPLE * 2} and --workers at least 1")

    def say(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    if args.before:
        passed_on = ["--count", str(count), "--workers", str(args.workers)]
        print(side_by_side(Path(__file__).name, args.before, passed_on, args.rounds, say))
        return 0

    started = time.perf_counter()
    rows, notes = run(count, args.workers, say)
    elapsed = time.perf_counter() - started
    env = {
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpus": str(os.cpu_count()),
        "numpy": np.__version__,
    }
    print(f"## Study benchmark ({count} scenarios)")
    print()
    print(", ".join(f"{key} {value}" for key, value in env.items()) + f"; total {elapsed:.1f} s")
    print()
    print(markdown(rows))
    print()
    for note in notes:
        print(f"- {note}")
    if args.json is not None:
        document = {
            "count": count,
            "workers": args.workers,
            "environment": env,
            "elapsed_s": elapsed,
            "results": [asdict(row) for row in rows],
            "notes": notes,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(document, indent=2) + "\n")
        print(f"\nWrote {args.json}")
    return 0 if all(row.passed is not False for row in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
