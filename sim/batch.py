"""The in-process simulation of many scenarios at once: one numpy step advances them all.

Each step is one tick of :func:`sim.simulation.simulate` for every run of the batch: the wire
(:mod:`protocol.messages`), the control law (:func:`controller.control_law.step`) and the
plant model (:func:`plant_sim.model.integrate`), the very formulas the controller and the
plant run, here with :data:`protocol.ops.ARRAY`. This module only packs the runs' state into
arrays (one element per run) and drives the ticks; ``tests/sim/test_one_law.py`` checks
every logged column of every tick against the scalar simulation.

Runs in one batch share the robot, the gains and the plant model; they differ in mode,
waypoints (a shorter plan is padded with its last stage), obstacle (a run without one gets a
section no TCP is ever below) and length: each run ends as :mod:`controller.run_end` says
(its task done, its timeout reached, or no safe motion left), and then leaves the arrays
soon after (no longer counted in its measures meanwhile).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from controller.control_law import LawState, Stage, first_state, law_of, stages_of, step
from controller.coordination import Coordination
from controller.fuzzy import RuleBase
from controller.planner import plan_of
from controller.run_end import OUTCOMES, UNWATCHED, RunEnd, Watch, ending, run_end_of
from plant_sim.model import integrate
from protocol.array_ops import rebuilt, take
from protocol.messages import joints_on_the_wire, rates_on_the_wire
from protocol.ops import ARRAY
from protocol.scenario import Mode, Scenario
from sim.measures import Measures, MeasureStream

Array = npt.NDArray[np.float64]
Index = npt.NDArray[np.intp]

BLOCK_TICKS = 64
"""Ticks of log kept before they are folded into the measures (memory: 15 columns of this)."""
COMPACT_SHARE = 0.03
"""Finished runs are dropped from the arrays once they are this share of them."""


def _leaves(value: Any) -> Iterator[Any]:
    """The numbers of a (nested) tuple, in order."""
    if isinstance(value, tuple):
        for part in value:
            yield from _leaves(part)
    else:
        yield value


def _rebuilt(like: Any, leaves: Iterator[Any]) -> Any:
    """``like``'s (nested) tuple shape, filled from ``leaves``."""
    if isinstance(like, tuple):
        return rebuilt(like, [_rebuilt(part, leaves) for part in like])
    return next(leaves)


def _stacked(items: Sequence[Any]) -> Any:
    """Per-run values (the same tuple shape for every run) as one of arrays, one element per
    run; what is not a number (a configuration) is shared, and taken from the first."""
    first = items[0]
    if isinstance(first, tuple):
        return rebuilt(first, [_stacked([item[k] for item in items]) for k in range(len(first))])
    if isinstance(first, bool | int | float):
        return np.array(items)
    return first


class _Plans:
    """Each run's plan as its :class:`Stage` table, and the stage each run is on."""

    def __init__(self, tables: Sequence[Sequence[Stage]]) -> None:
        width = max(len(table) for table in tables)
        self._template = tables[0][0]
        rows = [
            [list(_leaves(stage)) for stage in (*t, *[t[-1]] * (width - len(t)))] for t in tables
        ]
        self._types = [type(leaf) for leaf in _leaves(self._template)]
        self._table = np.array(rows, dtype=np.float64)  # (runs, stages, leaves)
        self._stage = np.zeros(len(tables), dtype=np.intp)
        self._now = [self._column(k, self._table[:, 0, k]) for k in range(len(self._types))]
        self._view = _rebuilt(self._template, iter(self._now))

    def _column(self, k: int, values: Array) -> Any:
        return values.astype({bool: np.bool_, int: np.intp}.get(self._types[k], np.float64))

    def at(self, progress: Array) -> Stage:
        """The stage each run's reference is on at plan time ``progress``."""
        while True:
            rows = np.flatnonzero(progress >= self._view.end)
            if not len(rows):
                return self._view  # type: ignore[no-any-return]
            self._stage[rows] += 1
            values = self._table[rows, self._stage[rows]]
            for k, now in enumerate(self._now):
                now[rows] = values[:, k]

    def keep(self, rows: Index) -> None:
        """Only the runs ``rows`` from now on."""
        self._table, self._stage = self._table[rows], self._stage[rows]
        self._now = [now[rows] for now in self._now]
        self._view = _rebuilt(self._template, iter(self._now))


class _Batch:
    """The state of every run of a batch, advanced one tick per :meth:`step`."""

    def __init__(
        self, scenarios: Sequence[Scenario], modes: Sequence[Mode], rule_base: RuleBase | None
    ) -> None:
        first = scenarios[0]
        for scenario in scenarios:
            if (scenario.robot, scenario.controller, scenario.plant) != (
                first.robot,
                first.controller,
                first.plant,
            ):
                raise ValueError(
                    f"scenario {scenario.name!r}: a batch shares the robot, gains and plant"
                )
        config, plant = first.controller, first.plant
        self.period = config.period
        self.count = len(scenarios)
        self.end: RunEnd = _stacked([run_end_of(s) for s in scenarios])
        self.ticks = np.asarray(self.end.limit_tick + 1)
        """Each run's ticks: at most up to its timeout, until it ends."""
        self.ending = np.zeros(self.count, dtype=np.intp)
        """How each run ended (:func:`controller.run_end.ending`'s code; 0: it goes on)."""
        self.watch: Watch = _stacked([UNWATCHED] * self.count)
        self.start = np.array([s.waypoints[0].t for s in scenarios])
        coordination = Coordination.of(config.sensing_range, config.switch_distance, rule_base)
        plans = [plan_of(s) for s in scenarios]
        self.plans = _Plans(
            [
                stages_of(plan, s.obstacle, config.ao_pass_margin)
                for plan, s in zip(plans, scenarios, strict=True)
            ]
        )
        self.law = _stacked(
            [
                law_of(s.robot, config, s.obstacle, mode is Mode.FUZZY, coordination)
                for s, mode in zip(scenarios, modes, strict=True)
            ]
        )
        self.state: LawState = _stacked([first_state(plan) for plan in plans])
        self.position = np.array([s.initial_joints() for s in scenarios]).T.copy()
        self.velocity = np.zeros((3, self.count))
        robot = first.robot
        substep = self.period / plant.substeps
        self.plant = (
            (
                np.array([[limit] for limit in robot.speed_limits]),
                np.array([[limit * substep] for limit in robot.accel_limits]),
                np.array([[limit] for limit in robot.joint_min]),
                np.array([[limit] for limit in robot.joint_max]),
            ),
            1.0 - math.exp(-substep / plant.time_constant),
            substep,
            plant.substeps,
        )

    def keep(self, rows: Index) -> None:
        """Only the runs ``rows`` from now on (the others have finished)."""
        self.ticks, self.start = self.ticks[rows], self.start[rows]
        self.end, self.ending = take(self.end, rows), self.ending[rows]
        self.watch = take(self.watch, rows)
        self.law, self.state = take(self.law, rows), take(self.state, rows)
        self.position, self.velocity = self.position[:, rows], self.velocity[:, rows]
        self.plans.keep(rows)
        self.count = len(rows)

    def step(self, tick: int) -> dict[str, Array]:
        """One tick for every run; the log columns the measures need."""
        t = self.start + tick * self.period
        joints, speeds = self.position, self.velocity
        position, velocity = joints_on_the_wire(
            ARRAY, (joints[0], joints[1], joints[2]), (speeds[0], speeds[1], speeds[2])
        )
        output, self.state = step(ARRAY, self.law, self.plans, self.state, t, position)
        command = np.array(rates_on_the_wire(ARRAY, output.command))
        limits, blend, substep, substeps = self.plant
        self.position, self.velocity, _ = integrate(
            ARRAY, self.position, self.velocity, command, limits, blend, substep, substeps
        )
        code, self.watch = ending(
            ARRAY, self.end, self.state.reached, output, velocity, tick, tick, self.watch
        )
        ends = (code != 0) & (self.ending == 0)
        self.ending[ends] = code[ends]
        self.ticks[ends] = tick + 1
        tcp = output.tcp
        return {
            "clock": t,
            "theta1": position[0],
            "theta2": position[1],
            "theta1_rate": velocity[0],
            "theta2_rate": velocity[1],
            "d3_rate": velocity[2],
            "command_theta1": output.command[0],
            "command_theta2": output.command[1],
            "x": tcp[0],
            "y": tcp[1],
            "z": tcp[2],
            "reference_speed": output.reference_speed,
            "clearance": output.measurement.clearance,
            "progress": output.progress,
            "k_c": output.k_c,
        }


@dataclass(frozen=True, slots=True)
class BatchRun:
    """One scenario's run in a batch: its measures, and how far AO ever took over."""

    measures: Measures
    peak_k_c: float
    """The largest k_C of the run (1 when the conventional switch flipped to AO)."""


def _modes_of(scenarios: Sequence[Scenario], mode: Mode | Sequence[Mode] | None) -> list[Mode]:
    if mode is None:
        return [scenario.mode for scenario in scenarios]
    if isinstance(mode, Mode):
        return [mode] * len(scenarios)
    modes = list(mode)
    if len(modes) != len(scenarios):
        raise ValueError(f"{len(modes)} modes for {len(scenarios)} scenarios")
    return modes


def trace_batch(scenarios: Sequence[Scenario], modes: Sequence[Mode]) -> list[dict[str, Array]]:
    """Every tick's log columns of each run (``modes``: one per scenario), for comparing the
    batch with the scalar law tick by tick; the runs are kept in the arrays to the end."""
    with np.errstate(all="ignore"):
        batch = _Batch(scenarios, _modes_of(scenarios, modes), None)
        rows: list[dict[str, Array]] = []
        while not batch.ending.all():
            rows.append(batch.step(len(rows)))
    return [
        {name: np.array([row[name][index] for row in rows[:ticks]]) for name in rows[0]}
        for index, ticks in enumerate(batch.ticks.tolist())
    ]


def simulate_batch(
    scenarios: Sequence[Scenario],
    mode: Mode | Sequence[Mode] | None = None,
    rule_base: RuleBase | None = None,
    on_block: Callable[[int], None] | None = None,
) -> list[BatchRun]:
    """Each scenario's run as :func:`sim.simulation.simulate` gives it, all at once.

    ``mode``: one for the whole batch, or one per scenario, else the scenarios' own (a batch
    may mix them: running both modes of the same scenarios in one batch pays numpy's
    per-tick overhead once for both); ``rule_base`` for the fuzzy coordinator (else Table
    2's); ``on_block(n)`` is told of every n scenario-ticks done (for a progress bar). A
    run's results do not depend on the other scenarios of its batch.
    """
    if not scenarios:
        return []
    modes = _modes_of(scenarios, mode)
    with np.errstate(all="ignore"):
        batch = _Batch(scenarios, modes, rule_base)
        stream = MeasureStream(scenarios)
        peak_k_c = np.zeros(batch.count)
        runs: list[BatchRun | None] = [None] * len(scenarios)
        original = np.arange(len(scenarios))
        names = (*MeasureStream.COLUMNS, "k_c")
        block_start = 0
        buffers: dict[str, Array] = {}
        while batch.count:
            length = min(BLOCK_TICKS, int(batch.ticks.max()) - block_start)
            if not buffers or buffers["k_c"].shape[1] != batch.count:
                # One set of buffers per batch size: fresh ones for each block would be tens
                # of megabytes of new pages to fault in every BLOCK_TICKS ticks.
                buffers = {name: np.empty((BLOCK_TICKS, batch.count)) for name in names}
            block = {name: buffers[name][:length] for name in names}
            for offset in range(length):
                row = batch.step(block_start + offset)
                for name in names:
                    block[name][offset] = row[name]
                if batch.ending.all():  # every run has ended: so does the block
                    length = offset + 1
                    block = {name: values[:length] for name, values in block.items()}
                    break
            ticks = np.arange(block_start, block_start + length)[:, None]
            valid = ticks < batch.ticks
            stream.update(block, valid)
            peak_k_c = ARRAY.max(peak_k_c, np.where(valid, block["k_c"], 0.0).max(axis=0))
            if on_block is not None:
                on_block(int(valid.sum()))
            block_start += length
            finished = batch.ticks <= block_start
            if finished.sum() >= COMPACT_SHARE * batch.count:
                # Finished runs leave the arrays: no more work is spent on them.
                done, going = np.flatnonzero(finished), np.flatnonzero(~finished)
                outcomes = [OUTCOMES[code - 1] for code in batch.ending[done]]
                for index, measures, peak in zip(
                    original[done], stream.measures(outcomes, done), peak_k_c[done], strict=True
                ):
                    runs[index] = BatchRun(measures, float(peak))
                batch.keep(going)
                stream.keep(going)
                peak_k_c, original = peak_k_c[going], original[going]
    return [run for run in runs if run is not None]
