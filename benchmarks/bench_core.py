"""Core performance benchmark: fuzzy coordinator, one control step, the in-process simulation.

Measures, side by side in one run:

1. one ``FuzzyInference.weights`` evaluation against scikit-fuzzy's
   ``ControlSystemSimulation.compute()`` on the same rule base, and their speed ratio;
2. one full ``ControlLaw.step`` (measure, behaviours, coordination, Jacobian, limits),
   replayed over the joint states of a real run of the reference scenario, in both modes;
3. the in-process simulation of the reference scenario: wall time and real-time factor.

Prints a Markdown table with each target and PASS/FAIL; ``--json PATH`` also writes the numbers.
Run from the project root: ``python benchmarks/bench_core.py [--quick] [--json PATH]``;
``--before REV [--rounds N]`` runs it on revision REV's code and on this tree's, in turns, and
prints both side by side.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import random
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from against import add_against_arguments, side_by_side

from controller.control_law import ControlLaw
from controller.fuzzy import FuzzyInference, RuleBase
from protocol.scenario import Mode, Scenario, load_scenario
from sim.simulation import simulate

SKFUZZY_RESOLUTION = 201
"""Points per sampled universe for scikit-fuzzy (its typical use: np.linspace(lo, hi, 201))."""
INPUT_SEED = 20240601
INPUT_COUNT = 1000

TARGET_FUZZY_US = 10.0
TARGET_RATIO = 100.0
TARGET_STEP_US = 100.0
TARGET_REALTIME = 20.0


@dataclass(frozen=True, slots=True)
class Settings:
    """How long each measurement runs."""

    batches: int
    batch_size: int
    skfuzzy_calls: int
    step_repeats: int
    sim_runs: int


FULL = Settings(batches=200, batch_size=INPUT_COUNT, skfuzzy_calls=300, step_repeats=3, sim_runs=5)
QUICK = Settings(batches=40, batch_size=INPUT_COUNT, skfuzzy_calls=100, step_repeats=1, sim_runs=3)


@dataclass(slots=True)
class Row:
    """One line of the result table (times in microseconds unless ``unit`` says otherwise)."""

    key: str
    label: str
    unit: str
    median: float | None
    p99: float | None = None
    worst: float | None = None
    target: str = ""
    passed: bool | None = None


# -- inputs ----------------------------------------------------------------------------------


def spread_inputs(rule_base: RuleBase, count: int = INPUT_COUNT) -> list[tuple[float, float]]:
    """``count`` (min_distance, beta) pairs drawn uniformly over both universes (fixed seed)."""
    rng = random.Random(INPUT_SEED)
    d_low, d_high = rule_base.inputs["min_distance"].universe
    b_low, b_high = rule_base.inputs["beta"].universe
    return [(rng.uniform(d_low, d_high), rng.uniform(b_low, b_high)) for _ in range(count)]


# -- 1. fuzzy coordinator --------------------------------------------------------------------


def bench_ours(
    inference: FuzzyInference, inputs: Sequence[tuple[float, float]], settings: Settings
) -> list[float]:
    """Per-call microseconds of each batch of ``batch_size`` calls (Python loop included)."""
    weights = inference.weights
    batch = list(inputs[: settings.batch_size])
    for d, b in batch:  # warm-up
        weights(d, b)
    per_call: list[float] = []
    clock = time.perf_counter_ns
    for _ in range(settings.batches):
        start = clock()
        for d, b in batch:
            weights(d, b)
        per_call.append((clock() - start) / 1000.0 / len(batch))
    return per_call


def build_skfuzzy(rule_base: RuleBase) -> Any:
    """The rule base as an independent scikit-fuzzy Mamdani system (sampled universes)."""
    import skfuzzy as fuzz
    from skfuzzy import control as ctrl

    antecedents = {}
    for name, fuzzy_input in rule_base.inputs.items():
        low, high = fuzzy_input.universe
        antecedent = ctrl.Antecedent(np.linspace(low, high, SKFUZZY_RESOLUTION), name)
        for term, trapezoid in fuzzy_input.terms.items():
            points = [trapezoid.a, trapezoid.b, trapezoid.c, trapezoid.d]
            antecedent[term] = fuzz.trapmf(antecedent.universe, points)
        antecedents[name] = antecedent
    consequents = {}
    for name, fuzzy_output in rule_base.outputs.items():
        low, high = fuzzy_output.universe
        consequent = ctrl.Consequent(np.linspace(low, high, SKFUZZY_RESOLUTION), name)
        for term, triangle in fuzzy_output.triangles().items():
            consequent[term] = fuzz.trimf(consequent.universe, list(triangle))
        consequents[name] = consequent
    rules = [
        ctrl.Rule(
            antecedents["min_distance"][rule.min_distance] & antecedents["beta"][rule.beta],
            (consequents["k_T"][rule.k_T], consequents["k_C"][rule.k_C]),
        )
        for rule in rule_base.rules
    ]
    # cache=False: every call really computes, even if an input pair repeats.
    return ctrl.ControlSystemSimulation(ctrl.ControlSystem(rules), cache=False)


def bench_skfuzzy(
    simulation: Any, inputs: Sequence[tuple[float, float]], calls: int
) -> tuple[list[float], list[tuple[float, float]]]:
    """Per-call microseconds of inputs -> compute() -> outputs, and the outputs."""

    def evaluate(d: float, b: float) -> tuple[float, float]:
        simulation.input["min_distance"] = d
        simulation.input["beta"] = b
        simulation.compute()
        return float(simulation.output["k_T"]), float(simulation.output["k_C"])

    for d, b in inputs[:10]:  # warm-up
        evaluate(d, b)
    clock = time.perf_counter_ns
    times: list[float] = []
    results: list[tuple[float, float]] = []
    for index in range(calls):
        d, b = inputs[index % len(inputs)]
        start = clock()
        result = evaluate(d, b)
        times.append((clock() - start) / 1000.0)
        results.append(result)
    return times, results


# -- 2. control step -------------------------------------------------------------------------


def bench_step(scenario: Scenario, repeats: int) -> tuple[list[float], int, bool]:
    """Per-step microseconds of ``law.step`` replayed on a real run's states (fresh law each
    repeat); also the tick count and whether the replay reproduced the logged commands."""
    log = simulate(scenario).log
    ticks = [
        (float(t), (float(a), float(b), float(c)))
        for t, a, b, c in log.columns("t", "theta1", "theta2", "d3")
    ]
    logged = log.columns("command_theta1", "command_theta2", "command_d3")
    clock = time.perf_counter_ns
    times: list[float] = []
    reproduced = True
    for repeat in range(repeats + 1):  # repeat 0 is a warm-up, not timed
        law = ControlLaw.for_scenario(scenario)
        step = law.step
        commands: list[tuple[float, float, float]] = []
        for t, q in ticks:
            start = clock()
            output = step(t, q)
            elapsed = clock() - start
            if repeat:
                times.append(elapsed / 1000.0)
            commands.append(output.command)
        reproduced = reproduced and bool(np.array_equal(np.array(commands), logged))
    return times, len(ticks), reproduced


# -- 3. simulation ---------------------------------------------------------------------------


def bench_simulation(scenario: Scenario, runs: int) -> list[float]:
    """Wall seconds of each of ``runs`` full ``simulate`` calls (after one warm-up run)."""
    simulate(scenario)
    walls: list[float] = []
    for _ in range(runs):
        start = time.perf_counter()
        simulate(scenario)
        walls.append(time.perf_counter() - start)
    return walls


# -- report ----------------------------------------------------------------------------------


def percentile(values: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


def fmt(value: float | None, unit: str) -> str:
    if value is None:
        return "-"
    if unit == "x":
        return f"{value:,.0f}x" if value >= 100 else f"{value:.1f}x"
    if unit == "ms":
        return f"{value:.1f} ms"
    return f"{value:.2f} us" if value < 100 else f"{value:,.0f} us"


def verdict(passed: bool | None) -> str:
    return "-" if passed is None else "PASS" if passed else "FAIL"


def markdown(rows: Sequence[Row]) -> str:
    lines = [
        "| Measurement | Median | p99 | Max | Target | Result |",
        "|---|---:|---:|---:|---|:---:|",
    ]
    for row in rows:
        cells = [fmt(row.median, row.unit), fmt(row.p99, row.unit), fmt(row.worst, row.unit)]
        lines.append(
            f"| {row.label} | {' | '.join(cells)} | {row.target or '-'} | {verdict(row.passed)} |"
        )
    return "\n".join(lines)


def timed_rows(key: str, label: str, values: Sequence[float], target: float | None) -> Row:
    median = statistics.median(values)
    return Row(
        key,
        label,
        "us",
        median,
        percentile(values, 99),
        max(values),
        f"median <= {target:g} us" if target is not None else "",
        (median <= target) if target is not None else None,
    )


def environment() -> dict[str, str]:
    info = {
        "python": platform.python_version(),
        "implementation": platform.python_implementation(),
        "machine": platform.machine(),
        "system": platform.system(),
        "cpus": str(os.cpu_count()),
        "numpy": np.__version__,
    }
    try:
        import skfuzzy

        info["scikit-fuzzy"] = str(skfuzzy.__version__)
    except ImportError:
        info["scikit-fuzzy"] = "not installed"
    return info


def run(settings: Settings, say: Callable[[str], None]) -> tuple[list[Row], list[str]]:
    """All measurements; the table rows and notes to print under it."""
    rows: list[Row] = []
    notes: list[str] = []
    rule_base = RuleBase.load()
    inference = FuzzyInference(rule_base)
    inputs = spread_inputs(rule_base)

    say(f"[1/3] FuzzyInference.weights: {settings.batches} batches x {settings.batch_size} calls")
    ours = bench_ours(inference, inputs, settings)
    rows.append(
        timed_rows(
            "fuzzy_ours",
            f"1. FuzzyInference.weights, per call ({settings.batches} batches x "
            f"{settings.batch_size}; p99/max over batches)",
            ours,
            TARGET_FUZZY_US,
        )
    )
    try:
        simulation = build_skfuzzy(rule_base)
    except ImportError:
        simulation = None
        notes.append("scikit-fuzzy is not installed: its rows and the ratio were skipped.")
    if simulation is not None:
        say(f"[1/3] skfuzzy compute(): {settings.skfuzzy_calls} calls")
        theirs, results = bench_skfuzzy(simulation, inputs, settings.skfuzzy_calls)
        rows.append(
            timed_rows(
                "fuzzy_skfuzzy",
                f"1. skfuzzy ControlSystemSimulation.compute(), {SKFUZZY_RESOLUTION}-point "
                f"universes, per call ({settings.skfuzzy_calls} calls)",
                theirs,
                None,
            )
        )
        ratio = statistics.median(theirs) / statistics.median(ours)
        rows.append(
            Row(
                "fuzzy_ratio",
                "1. Speed ratio skfuzzy / ours (medians)",
                "x",
                ratio,
                target=f">= {TARGET_RATIO:g}x",
                passed=ratio >= TARGET_RATIO,
            )
        )
        used = inputs[: len(results)]
        error = max(
            max(abs(a - c), abs(b - d))
            for (a, b), (c, d) in zip(
                (inference.weights(x, y) for x, y in used), results, strict=True
            )
        )
        notes.append(
            f"Same rule base check: max |ours - skfuzzy| over {len(results)} inputs = "
            f"{error:.2e} (skfuzzy's sampling error at {SKFUZZY_RESOLUTION} points; "
            "ours is the exact closed-form centroid)."
        )
    notes.append(
        f"Fuzzy inputs: {len(inputs)} (min_distance, beta) pairs uniform over the universes "
        f"{rule_base.inputs['min_distance'].universe} m x [-pi, pi] rad, seed {INPUT_SEED}; "
        "skfuzzy uses the first of them, cache=False, inputs set + compute() + outputs read."
    )

    reference = load_scenario("reference")
    duration = reference.duration
    all_reproduced = True
    for mode in Mode:
        say(f"[2/3] ControlLaw.step, {mode.value}: {settings.step_repeats} replays")
        times, ticks, reproduced = bench_step(reference.with_mode(mode), settings.step_repeats)
        rows.append(
            timed_rows(
                f"step_{mode.value}",
                f"2. ControlLaw.step, {mode.value} ({settings.step_repeats} x {ticks} ticks)",
                times,
                TARGET_STEP_US,
            )
        )
        if not reproduced:
            all_reproduced = False
            notes.append(f"WARNING: the {mode.value} replay did not reproduce the logged commands.")
    notes.append(
        "Control step: each tick timed alone (perf_counter_ns) on a fresh law fed the joint "
        "states and times of a real simulate() run"
        + ("; the replay reproduces the run's commands bit for bit." if all_reproduced else ".")
    )

    for mode in Mode:
        say(f"[3/3] simulate(reference), {mode.value}: {settings.sim_runs} runs")
        walls = bench_simulation(reference.with_mode(mode), settings.sim_runs)
        median = statistics.median(walls)
        rows.append(
            Row(
                f"sim_{mode.value}_wall",
                f"3. simulate(reference), {mode.value}: wall time per run "
                f"({settings.sim_runs} runs)",
                "ms",
                median * 1e3,
                worst=max(walls) * 1e3,
            )
        )
        factor = duration / median
        rows.append(
            Row(
                f"sim_{mode.value}_realtime",
                f"3. Real-time factor, {mode.value} ({duration:g} s simulated / median wall)",
                "x",
                factor,
                worst=duration / max(walls),
                target=f">= {TARGET_REALTIME:g}x",
                passed=factor >= TARGET_REALTIME,
            )
        )
    notes.append(
        "Real-time factor row: Max column is the factor of the slowest run. "
        "Garbage collection stays enabled throughout (as in real operation)."
    )
    return rows, notes


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark; 0 if every target passes, 1 otherwise."""
    parser = argparse.ArgumentParser(
        description=(
            "Benchmark the fuzzy coordinator (vs scikit-fuzzy), one control step and the "
            "in-process simulation of the reference scenario; print a Markdown table with "
            "targets and PASS/FAIL. Exit status 1 if any target fails."
        )
    )
    parser.add_argument("--quick", action="store_true", help="a shorter, noisier run")
    parser.add_argument("--json", type=Path, metavar="PATH", help="also write the numbers here")
    add_against_arguments(parser)
    args = parser.parse_args(argv)
    settings = QUICK if args.quick else FULL

    def say(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    if args.before:
        print(
            side_by_side(
                Path(__file__).name, args.before, ["--quick"] * args.quick, args.rounds, say
            )
        )
        return 0

    started = time.perf_counter()
    rows, notes = run(settings, say)
    elapsed = time.perf_counter() - started
    env = environment()

    print("## Core benchmark" + (" (quick)" if args.quick else ""))
    print()
    print(", ".join(f"{key} {value}" for key, value in env.items()) + f"; total {elapsed:.1f} s")
    print()
    print(markdown(rows))
    print()
    for note in notes:
        print(f"- {note}")

    if args.json is not None:
        document = {
            "quick": args.quick,
            "settings": asdict(settings),
            "skfuzzy_resolution": SKFUZZY_RESOLUTION,
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
