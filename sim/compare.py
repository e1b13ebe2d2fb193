"""``scara-compare``: fuzzy against conventional coordination over many generated scenarios.

The scenarios come from the generator (``sim.generator``, by seed); each mode runs them in
the batch simulator (:mod:`sim.batch`), in batches of similar durations spread over a pool
of worker processes, or over a Dask cluster with ``--scheduler``. Prints a table of both
modes side by side, and writes every run's measures as CSV, a figure of their distributions
and the worst case of each mode drawn like the paper's Figs. 8 and 9 (re-run in the scalar
simulation for its log). ``--sweep`` repeats the study for other gains or fuzzy rule bases.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import multiprocessing
import queue
import signal
import sys
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from controller.fuzzy import INPUT_NAMES, OUTPUT_NAMES, OUTPUT_TERMS, RuleBase
from protocol.cli import interruptible, quiet_on_closed_pipe
from protocol.config import ControllerConfig
from protocol.errors import ConfigError
from protocol.scenario import Mode, Scenario
from sim.batch import BatchRun, simulate_batch
from sim.generator import generate_scenario_at
from sim.measures import WAYPOINT_TOLERANCE, Measures

DEFAULT_COUNT = 1000
DEFAULT_BATCH = 20_000
"""Most runs per batch (a scenario in one mode is one run). A batch costs numpy's per-call
overhead on every tick of its longest run, whatever its size, so fewer, larger batches are
faster: by default one per worker, each with both modes of its scenarios."""
TICK_OVERHEAD_STEPS = 600
"""A batch's cost per tick beyond its runs' steps, in scenario-steps: numpy's per-call
overhead, fitted to the times of a batch of short runs and one of long runs on our
machines (500 to 760)."""
ENGAGED_K_C = 0.5
"""A run where k_C reached this has avoided: AO carried at least half of the command."""
NEAR_STOP = 2.0
"""A run whose stop margin is below this came near a stop: it was slower than twice the stop
speed for STOP_MIN_TICKS ticks (how many runs a change of the law may tip into stops)."""


@dataclass(frozen=True, slots=True)
class Variant:
    """One setting of the study: the gains and the rule base, and the modes it concerns."""

    name: str
    modes: tuple[Mode, ...]
    controller: dict[str, float]
    rule_base: RuleBase | None = None


@dataclass(frozen=True, slots=True)
class Job:
    """One batch: scenarios (with the variant's gains), each in its mode, for one worker."""

    variant: str
    modes: tuple[Mode, ...]
    indices: tuple[int, ...]
    scenarios: tuple[Scenario, ...]
    rule_base: RuleBase | None


@dataclass(frozen=True, slots=True)
class Outcome:
    """One scenario's run in one mode and variant."""

    variant: str
    mode: Mode
    index: int
    scenario: Scenario
    run: BatchRun


GENERATE_CHUNK = 25
"""Scenarios generated per task (the generator takes tens of milliseconds for one)."""

_progress: Any = None
"""The worker's queue to the parent's progress bar (set by :func:`_start_worker`)."""


def _start_worker(progress: Any) -> None:
    global _progress
    _progress = progress


def generate_chunk(seed: int, indices: Sequence[int]) -> list[tuple[int, Scenario]]:
    """Scenarios ``indices`` of the study ``seed`` (each depends on its index only)."""
    return [(index, generate_scenario_at(seed, index)) for index in indices]


def run_job(job: Job) -> list[Outcome]:
    """Run one batch (in a worker process or on a Dask worker)."""
    report: Callable[[int], None] | None = None
    if _progress is not None:
        report = _progress.put
    runs = simulate_batch(job.scenarios, job.modes, job.rule_base, on_block=report)
    return [
        Outcome(job.variant, mode, index, scenario, run)
        for mode, index, scenario, run in zip(
            job.modes, job.indices, job.scenarios, runs, strict=True
        )
    ]


def plan_jobs(
    scenarios: Sequence[Scenario], variants: Sequence[Variant], batch_size: int, workers: int
) -> list[Job]:
    """Batches of a variant's runs (both modes of a scenario side by side), sorted by
    duration and cut where the batches' costs come out even: a batch of long runs costs more
    ticks of overhead, so it gets fewer of them. At least one batch per worker."""
    per_variant = math.ceil(workers / len(variants))
    jobs = []
    for variant in variants:
        varied = [
            replace(s, controller=replace(s.controller, **variant.controller)) for s in scenarios
        ]
        runs = sorted(
            ((index, mode) for index in range(len(scenarios)) for mode in variant.modes),
            key=lambda run: (scenarios[run[0]].duration, run[0]),
        )
        ticks = [_run_ticks(scenarios[index]) for index, _ in runs]
        parts = max(math.ceil(len(runs) / batch_size), per_variant)
        for chosen in _even_cuts(ticks, parts, batch_size):
            jobs.append(
                Job(
                    variant.name,
                    tuple(runs[i][1] for i in chosen),
                    tuple(runs[i][0] for i in chosen),
                    tuple(varied[runs[i][0]] for i in chosen),
                    variant.rule_base,
                )
            )
    return jobs


def _even_cuts(ticks: Sequence[int], parts: int, most: int) -> list[range]:
    """Cut runs sorted by ``ticks`` into at most ``parts`` consecutive batches of at most
    ``most`` runs (``parts * most`` being enough), making the largest batch's cost (its
    ticks of overhead and its runs' steps) as small as it can be: a bisection on that cost,
    each cut taken greedily."""

    def cut(limit: float) -> list[range] | None:
        """Batches costing at most ``limit`` each, or None if ``parts`` are not enough."""
        batches, start, steps = [], 0, 0
        for end, run_ticks in enumerate(ticks):
            steps += run_ticks
            if end > start and (
                run_ticks * TICK_OVERHEAD_STEPS + steps > limit or end - start == most
            ):
                batches.append(range(start, end))
                start, steps = end, run_ticks
            if run_ticks * TICK_OVERHEAD_STEPS + steps > limit or len(batches) == parts:
                return None
        return [*batches, range(start, len(ticks))]

    low, high = 0.0, float(max(ticks, default=0) * TICK_OVERHEAD_STEPS + sum(ticks))
    best = cut(high)
    while best is not None and high - low > 1e-4 * high:
        middle = (low + high) / 2.0
        found = cut(middle)
        if found is None:
            low = middle
        else:
            best, high = found, middle
    if best is None:
        raise ValueError(f"{len(ticks)} runs do not fit {parts} batches of {most}")
    return best


class Processes:
    """A pool of worker processes; batches report their progress as they go."""

    streams = True

    def __init__(self, workers: int, advance: Callable[[int], None]) -> None:
        context = multiprocessing.get_context("spawn")
        # Children start with Ctrl-C ignored, which they keep (the parent stops them; one
        # still importing would print a traceback). Blocked meanwhile, a Ctrl-C for the parent
        # stays pending (Linux keeps a blocked signal even while it is ignored) until after.
        self._pool: Any = None
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            try:
                self._progress = context.Queue()
                self._pool = context.Pool(
                    workers, initializer=_start_worker, initargs=(self._progress,)
                )
            finally:
                signal.signal(signal.SIGINT, handler)
                signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        except BaseException:
            self.close()
            raise
        self.advance = advance

    def map(self, function: Callable[..., Any], items: Sequence[Any]) -> Iterator[Any]:
        """``function(*item)`` for each item, in the order they finish."""
        pending = self._pool.imap_unordered(_star, [(function, item) for item in items])
        for _ in items:
            while True:
                try:
                    result = pending.next(timeout=0.2)
                except multiprocessing.TimeoutError:
                    continue
                finally:
                    self._drain()
                break
            yield result

    def _drain(self) -> None:
        """Pass on the progress the workers reported."""
        try:
            while True:
                self.advance(self._progress.get_nowait())
        except queue.Empty:
            pass

    def close(self) -> None:
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()


class Cluster:
    """The Dask cluster of a scheduler; progress by finished tasks."""

    streams = False

    def __init__(self, address: str) -> None:
        from distributed import Client  # only with --scheduler

        self._client = Client(address)

    def map(self, function: Callable[..., Any], items: Sequence[Any]) -> Iterator[Any]:
        from distributed import as_completed

        futures = [self._client.submit(function, *item, pure=False) for item in items]
        try:
            for future in as_completed(futures):
                yield future.result()
        finally:
            self._client.cancel(futures)

    def close(self) -> None:
        self._client.close()


def _star(task: tuple[Callable[..., Any], tuple[Any, ...]]) -> Any:
    function, arguments = task
    return function(*arguments)


def _run_ticks(scenario: Scenario) -> int:
    """Ticks of a scenario's run (the unit of the progress bar)."""
    return round(scenario.duration / scenario.controller.period) + 1


# --- sweeps ----------------------------------------------------------------------------


def parse_sweep(text: str) -> list[Variant]:
    """``NAME=V1,V2,...``: one variant per value; a ConfigError names what is wrong.

    NAME is a controller gain (``switch_distance``, ``sensing_range``, ...: a number each),
    a term of a fuzzy input (``min_distance.near``, ``beta.small``, ...: ``a:b:c:d``) or the
    output peaks (``k_T.peaks``, ``k_C.peaks``: ``small:medium:big``).
    """
    name, equals, values = text.partition("=")
    if not equals or not values:
        raise ConfigError("--sweep", f"expected NAME=V1,V2,..., got {text!r}")
    gains = {spec.name for spec in fields(ControllerConfig)}
    variants = []
    for value in values.split(","):
        label = f"{name}={value}"
        if name in gains:
            number = _number(value, label)
            replace(ControllerConfig(), **{name: number})  # checked as a scenario's gains are
            modes = (Mode.CONVENTIONAL,) if name == "switch_distance" else tuple(Mode)
            variants.append(Variant(label, modes, {name: number}))
        else:
            variants.append(Variant(label, (Mode.FUZZY,), {}, _rule_base(name, value, label)))
    return variants


def _rule_base(name: str, value: str, label: str) -> RuleBase:
    """Table 2 with one term's points or one output's peaks replaced."""
    from importlib import resources

    document = json.loads(
        resources.files("controller").joinpath("data/fuzzy_rules.json").read_text()
    )
    part, _, term = name.partition(".")
    numbers = [_number(v, label) for v in value.split(":")]
    if part in INPUT_NAMES and term in document["inputs"][part]["terms"]:
        document["inputs"][part]["terms"][term] = numbers
    elif part in OUTPUT_NAMES and term == "peaks":
        if len(numbers) != len(OUTPUT_TERMS):
            raise ConfigError(label, "peaks are small:medium:big (three numbers)")
        document["outputs"][part]["peaks"] = dict(zip(OUTPUT_TERMS, numbers, strict=True))
    else:
        terms = [f"{i}.{t}" for i in INPUT_NAMES for t in document["inputs"][i]["terms"]]
        known = ", ".join([*sorted(f.name for f in fields(ControllerConfig)), *terms])
        raise ConfigError(
            "--sweep", f"unknown parameter {name!r}; known: {known}, k_T.peaks, k_C.peaks"
        )
    try:
        return RuleBase.from_mapping(document)
    except ConfigError as error:
        raise ConfigError(label, str(error)) from error


def _number(text: str, label: str) -> float:
    """The number ``text`` (whether it fits is for the schema of what it sets to say)."""
    try:
        return float(text)
    except ValueError:
        raise ConfigError(label, f"{text!r} is not a number") from None


# --- results ---------------------------------------------------------------------------


def summary(outcomes: Sequence[Outcome]) -> dict[str, str]:
    """The table's column for the runs of one variant and mode."""
    measures = [outcome.run.measures for outcome in outcomes]
    count = len(measures)
    collisions = sum(not m.collision_free for m in measures)
    misses = [sum(miss > WAYPOINT_TOLERANCE for miss in m.waypoint_miss) for m in measures]
    peak = np.array([m.peak_jerk for m in measures])
    rms = np.array([m.rms_jerk for m in measures])
    completion = np.array([m.completion_time for m in measures])
    done = completion[~np.isnan(completion)]
    return {
        "scenarios": f"{count}",
        "collisions": f"{collisions} ({100.0 * collisions / count:.1f} %)",
        "scenarios with stops": f"{sum(m.stops > 0 for m in measures)}",
        f"scenarios near a stop (margin < {NEAR_STOP:g})": str(
            sum(m.stop_margin < NEAR_STOP for m in measures)
        ),
        "waypoints missed (> 2 mm)": f"{sum(misses)} in {sum(n > 0 for n in misses)} scenarios",
        "peak jerk median / p95 (m/s^3)": _median_p95(peak, "{:.1f}"),
        "RMS jerk median / p95 (m/s^3)": _median_p95(rms, "{:.2f}"),
        "completion time median / p95 (s)": _median_p95(done, "{:.2f}")
        + (f", {count - len(done)} never" if len(done) < count else ""),
        f"avoidance engaged (k_C >= {ENGAGED_K_C})": str(
            sum(o.run.peak_k_c >= ENGAGED_K_C for o in outcomes)
        ),
    }


def _median_p95(values: np.ndarray, fmt: str) -> str:
    if not len(values):
        return "-"
    return f"{fmt.format(np.median(values))} / {fmt.format(np.percentile(values, 95))}"


def format_summary(columns: dict[str, dict[str, str]]) -> str:
    """Columns side by side as a Markdown table."""
    names = list(columns)
    rows = list(next(iter(columns.values())))
    lines = ["| measure | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]
    lines += [f"| {row} | " + " | ".join(columns[n][row] for n in names) + " |" for row in rows]
    return "\n".join(lines)


@dataclass(frozen=True, slots=True)
class JerkComparison:
    """Fuzzy's peak jerk against conventional's, where either mode avoided."""

    engaged: int
    smoother: int
    exceptions: list[tuple[Outcome, Outcome]]


def compare_jerk(fuzzy: Sequence[Outcome], conventional: Sequence[Outcome]) -> JerkComparison:
    """Scenario by scenario: where avoidance engaged, is fuzzy's peak jerk the lower?"""
    by_index = {outcome.index: outcome for outcome in conventional}
    engaged = smoother = 0
    exceptions = []
    for first in fuzzy:
        second = by_index[first.index]
        if max(first.run.peak_k_c, second.run.peak_k_c) < ENGAGED_K_C:
            continue
        engaged += 1
        if first.run.measures.peak_jerk < second.run.measures.peak_jerk:
            smoother += 1
        else:
            exceptions.append((first, second))
    return JerkComparison(engaged, smoother, exceptions)


def write_csv(path: Path, outcomes: Sequence[Outcome]) -> None:
    """One row per scenario, mode and variant."""
    names = [spec.name for spec in fields(Measures)]
    header = ("variant", "mode", "index", "scenario", "duration", "peak_k_c")
    with path.open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow([*header, *names, "max_waypoint_miss"])
        for outcome in sorted(outcomes, key=lambda o: (o.variant, o.mode.value, o.index)):
            measures = outcome.run.measures
            values = [getattr(measures, name) for name in names]
            values[names.index("waypoint_miss")] = ";".join(
                repr(miss) for miss in measures.waypoint_miss
            )
            writer.writerow(
                [
                    outcome.variant,
                    outcome.mode.value,
                    outcome.index,
                    outcome.scenario.name,
                    repr(outcome.scenario.duration),
                    repr(outcome.run.peak_k_c),
                    *(repr(v) if isinstance(v, float) else v for v in values),
                    repr(measures.max_waypoint_miss),
                ]
            )


def worst(outcomes: Sequence[Outcome]) -> Outcome:
    """The worst run: a collision, then stops, then missed waypoints, then peak jerk."""
    return max(
        outcomes,
        key=lambda o: (
            not o.run.measures.collision_free,
            o.run.measures.stops,
            o.run.measures.max_waypoint_miss > WAYPOINT_TOLERANCE,
            o.run.measures.peak_jerk,
        ),
    )


def write_figures(out: Path, by_mode: dict[Mode, list[Outcome]]) -> list[Path]:
    """Distributions of both modes side by side, and each mode's worst case re-run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim.figure import comparison_figure
    from sim.simulation import simulate

    panels = (
        ("peak_jerk", "peak jerk [m/s^3]", True),
        ("rms_jerk", "RMS jerk [m/s^3]", True),
        ("completion_time", "completion time [s]", False),
        ("min_clearance", "min clearance [mm]", False),
    )
    figure, axes = plt.subplots(1, len(panels), figsize=(18, 4.5), constrained_layout=True)
    for axis, (name, label, logarithmic) in zip(axes, panels, strict=True):
        series = {
            mode.value: np.array([getattr(o.run.measures, name) for o in outcomes], dtype=float)
            * (1e3 if name == "min_clearance" else 1.0)
            for mode, outcomes in by_mode.items()
        }
        finite = [values[np.isfinite(values)] for values in series.values()]
        axis.boxplot(finite, showfliers=True)
        axis.set_xticks(range(1, len(series) + 1), list(series))
        if logarithmic:
            axis.set_yscale("log")
        axis.set_title(label)
    count = len(next(iter(by_mode.values())))
    figure.suptitle(f"{count} generated scenarios, fuzzy and conventional coordination")
    paths = [out / "compare.png"]
    figure.savefig(paths[0], dpi=100)
    plt.close(figure)
    for mode, outcomes in by_mode.items():
        case = worst(outcomes)
        runs = {m.value: simulate(case.scenario, m) for m in by_mode}
        paths.append(comparison_figure(runs, out / f"worst-{mode.value}.png"))
    return paths


# --- command line -----------------------------------------------------------------------


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
    parser.add_argument("--no-figure", action="store_true", help="skip the figures")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
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
    interruptible()
    for flag, value, least in (
        ("--count", args.count, 1),
        ("--workers", args.workers, 1),
        ("--batch", args.batch, 1),
        ("--seed", args.seed, 0),
    ):
        if value < least:
            parser.error(f"{flag} must be at least {least}, got {value}")
    variants = [Variant("baseline", tuple(Mode), {})]
    for text in args.sweep:
        try:
            variants += parse_sweep(text)
        except ConfigError as error:
            parser.error(f"--sweep {text}: {error}")

    executor: Processes | Cluster | None = None
    outcomes: list[Outcome] = []
    try:
        bar = _bar(args.count, "generating", "scenario", args.quiet)
        executor = (
            Cluster(args.scheduler) if args.scheduler else Processes(args.workers, bar.update)
        )
        indices = list(range(args.count))
        chunks = [(args.seed, indices[i : i + GENERATE_CHUNK]) for i in indices[::GENERATE_CHUNK]]
        generated: dict[int, Scenario] = {}
        for chunk in executor.map(generate_chunk, chunks):
            generated.update(chunk)
            bar.update(len(chunk))
        bar.close()
        scenarios = [generated[index] for index in indices]
        jobs = plan_jobs(scenarios, variants, args.batch, args.workers)
        total = sum(_run_ticks(scenario) for job in jobs for scenario in job.scenarios)
        bar = _bar(total, "simulating", "step", args.quiet)
        if isinstance(executor, Processes):
            executor.advance = bar.update
        for result in executor.map(run_job, [(job,) for job in jobs]):
            outcomes += result
            if not executor.streams:
                bar.update(sum(_run_ticks(outcome.scenario) for outcome in result))
        bar.close()
    finally:
        if executor is not None:
            executor.close()
    groups: dict[tuple[str, Mode], list[Outcome]] = {}
    for outcome in sorted(outcomes, key=lambda o: o.index):
        groups.setdefault((outcome.variant, outcome.mode), []).append(outcome)
    columns = {
        (mode.value if variant.name == "baseline" else f"{mode.value} {variant.name}"): summary(
            groups[(variant.name, mode)]
        )
        for variant in variants
        for mode in variant.modes
    }
    print(format_summary(columns))
    baseline = {mode: groups[("baseline", mode)] for mode in Mode}
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


def jerk_report(comparison: JerkComparison) -> str:
    """The share where fuzzy is smoother, and every exception."""
    engaged = comparison.engaged
    share = 100.0 * comparison.smoother / engaged if engaged else math.nan
    lines = [
        f"fuzzy peak jerk below conventional's in {comparison.smoother} of {engaged} "
        f"scenarios where avoidance engaged ({share:.1f} %)"
    ]
    for fuzzy, conventional in comparison.exceptions:
        ratio = fuzzy.run.measures.peak_jerk / conventional.run.measures.peak_jerk
        lines.append(
            f"  not below: #{fuzzy.index} {fuzzy.scenario.name}: fuzzy "
            f"{fuzzy.run.measures.peak_jerk:.1f}, conventional "
            f"{conventional.run.measures.peak_jerk:.1f} m/s^3 ({ratio:.2f}x)"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
