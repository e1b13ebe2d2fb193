"""The study's work cut into tasks: the scenarios generated in chunks, and the runs (a scenario
in one mode and variant) cut into batches of even cost for the batch simulator
(:func:`plan_jobs`), each run in one worker (:func:`run_job`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

from controller.fuzzy import RuleBase
from controller.task_rules import check_task
from protocol.errors import ConfigError
from protocol.scenario import Mode, Scenario
from sim.batch import BatchRun, simulate_batch
from sim.generator import Family, generate_scenario_at
from sim.study.pool import progress_reporter
from sim.study.variants import Variant

DEFAULT_BATCH = 20_000
"""Most runs per batch (a scenario in one mode is one run). A batch costs numpy's per-call
overhead on every tick of its longest run, whatever its size, so fewer, larger batches are
faster: by default one per worker, each with both modes of its scenarios."""
TICK_OVERHEAD_STEPS = 600
"""A batch's cost per tick beyond its runs' steps, in scenario-steps: numpy's per-call
overhead, fitted to the times of a batch of short runs and one of long runs on our
machines (500 to 760)."""
GENERATE_CHUNK = 25
"""Scenarios generated per task (the generator takes tens of milliseconds for one)."""


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


def generate_chunk(
    seed: int, indices: Sequence[int], family: Family = Family.MIX, held_out: bool = False
) -> list[tuple[int, Scenario, ConfigError | None]]:
    """Scenarios ``indices`` of ``family``'s study ``seed`` (each depends on its index only;
    a held-out one only with ``held_out``), each with the controller's refusal if it refuses
    it (no way round the obstacle: the generator offers such tasks as a user would)."""
    return [
        (index, scenario, refusal(scenario))
        for index, scenario in (
            (index, generate_scenario_at(seed, index, family=family, held_out=held_out))
            for index in indices
        )
    ]


def refusal(scenario: Scenario) -> ConfigError | None:
    """The gate's refusal of ``scenario`` (:mod:`controller.task_rules`), if it refuses it."""
    try:
        check_task(scenario)
    except ConfigError as error:
        return error
    return None


def run_job(job: Job) -> list[Outcome]:
    """Run one batch (in a worker process or on a Dask worker)."""
    runs = simulate_batch(job.scenarios, job.modes, job.rule_base, on_block=progress_reporter())
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
        ticks = [run_ticks(scenarios[index]) for index, _ in runs]
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


def run_ticks(scenario: Scenario) -> int:
    """Ticks of a scenario's run (the unit of the progress bar and of a batch's cost)."""
    return round(scenario.duration / scenario.controller.period) + 1


def _even_cuts(ticks: Sequence[int], parts: int, most: int) -> list[range]:
    """Cut runs sorted by ``ticks`` into at most ``parts`` consecutive batches of at most
    ``most`` runs (``parts * most`` being enough), making the largest batch's cost (its
    ticks of overhead and its runs' steps) as small as it can be: a bisection on that cost,
    each cut taken greedily."""

    def cut(limit: float) -> list[range] | None:
        """Batches costing at most ``limit`` each, or None if ``parts`` are not enough."""
        batches, start, steps = [], 0, 0
        for end, count in enumerate(ticks):
            steps += count
            if end > start and (count * TICK_OVERHEAD_STEPS + steps > limit or end - start == most):
                batches.append(range(start, end))
                start, steps = end, count
            if count * TICK_OVERHEAD_STEPS + steps > limit or len(batches) == parts:
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
