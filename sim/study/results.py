"""What the study reports: a table of both modes (and each variant) side by side, the
scenario-by-scenario comparison of peak jerk, every run's measures as CSV, and figures of
the distributions and of each mode's worst case (re-run in the scalar simulation for its log).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from controller.run_end import RunOutcome
from protocol.scenario import Mode
from sim.measures import WAYPOINT_TOLERANCE, Measures
from sim.study.jobs import Outcome

ENGAGED_K_C = 0.5
"""A run where k_C reached this has avoided: AO carried at least half of the command."""
NEAR_STOP = 2.0
"""A run whose stop margin is below this came near a stop: it was slower than twice the stop
speed for STOP_MIN_TICKS ticks (how many runs a change of the law may tip into stops)."""


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
        "timed out": f"{sum(m.outcome is RunOutcome.TASK_TIMEOUT for m in measures)}",
        "no safe motion": f"{sum(m.outcome is RunOutcome.NO_SAFE_MOTION for m in measures)}",
        "no progress": f"{sum(m.outcome is RunOutcome.NO_PROGRESS for m in measures)}",
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
