"""When a run ends: its task done, no progress made, its timeout reached, or no safe motion
left.

Written once over :mod:`protocol.ops`, like the law: the simulation and the controller node
run it on floats after each tick, the batch on arrays of runs. The task is done when every
waypoint is passed (the law's ``reached``), the plan's progress is at or past the last
waypoint's time (a plan waiting for the arm has not ended), and the arm has settled at the
last waypoint: the TCP within the task's tolerance of it and every joint slower than
SETTLED_SPEEDS. A run ends at the first tick at or after the plan's end (the last waypoint's
time plus the settling time) at which its task is done, so a run done on time ends on the
tick it always did, and one that a detour made late goes on; a run not done by its timeout
(:attr:`protocol.scenario.Scenario.time_limit`, on the run's clock) ends there, in the fault
TASK_TIMEOUT. A run ends at once, in the fault NO_SAFE_MOTION, on the tick the safety filter
finds no command that keeps the arm off the obstacle (:mod:`controller.safety`).

A run that makes no progress ends in the fault NO_PROGRESS, long before its timeout: when for
the task's ``no_progress_time`` (on the plan's clock) the arm has come no nearer (by
PROGRESS_STEP) to the waypoint the plan waits for, and the plan has not moved on towards the
last waypoint either (an arm that circles the obstacle, or is held short of a waypoint by a
joint's stop, while the plan waits for it). A plan that runs on (a pause at a waypoint, a slow
segment) is progress.
"""

from __future__ import annotations

import math
from enum import StrEnum
from typing import NamedTuple

from controller.control_law import ControlOutput, Point3
from protocol.geometry import distance
from protocol.ops import Mask, Ops, Real
from protocol.scenario import WAYPOINT_TOLERANCE, Scenario

PROGRESS_STEP = 0.001
"""m: how much nearer the waypoint the plan waits for the arm must come to make progress."""
PLAN_STEP = 0.05
"""s of plan: how far the plan must run on (before its last waypoint) to make progress."""

SETTLED_SPEEDS = (0.01, 0.01, 0.005)
"""rad/s, rad/s, m/s: joints all slower than this count as settled. The TCP then moves at
most about 1 cm/s (9 mm/s in the plane at full reach, 5 mm/s in height): an arm closing on
the waypoint under PT's gain, not one passing through it; the wire carries joint speeds in
steps of 0.001 rad/s and 0.0001 m/s."""


class RunOutcome(StrEnum):
    """How a run ended (its measures and the controller's result say so). An outcome that
    ends a run in a fault bears the name of that fault (``protocol.messages.ControllerFault``,
    the DBC's)."""

    DONE = "done"
    """Every waypoint passed and the arm settled at the last."""
    TASK_TIMEOUT = "task_timeout"
    """The run's timeout came first."""
    NO_SAFE_MOTION = "no_safe_motion"
    """The safety filter found no command that keeps the arm off the obstacle."""
    NO_PROGRESS = "no_progress"
    """The arm came no nearer the waypoint the plan waited for, for the task's
    ``no_progress_time``."""
    CUT_SHORT = "cut_short"
    """Ended otherwise, before any of those: a stop, another fault, an e-stop, the process
    stopped (only a co-simulation's run)."""


OUTCOMES = (
    RunOutcome.DONE,
    RunOutcome.TASK_TIMEOUT,
    RunOutcome.NO_SAFE_MOTION,
    RunOutcome.NO_PROGRESS,
)
"""How a run ended, by the code :func:`ending` gives, less one (0: it goes on)."""


class RunEnd(NamedTuple):
    """What ends a run of one scenario (or, as arrays, of each run of a batch)."""

    last: Real
    """The index of the last waypoint."""
    point: Point3
    """The last waypoint."""
    time: Real
    """The last waypoint's time on the plan."""
    end_tick: Real
    """The plan's end (the last waypoint's time plus the settling time): the first tick the
    run may end on, counted from 0 at the first waypoint."""
    limit_tick: Real
    """The timeout's tick, on the run's clock."""
    no_progress_ticks: Real
    """Ticks without progress that end a run (the task's ``no_progress_time``)."""


class Watch(NamedTuple):
    """What the watch over a run's progress remembers (:func:`ending`)."""

    waited: Point3
    """The waypoint the plan waited for."""
    best: Real
    """The nearest the TCP has come to it since the last progress."""
    plan: Real
    """The plan's time at the last progress."""
    since: Real
    """The tick of the last progress."""


UNWATCHED = Watch((math.nan, math.nan, math.nan), math.inf, -math.inf, 0)
"""The watch before a run's first tick, which is progress."""


def run_end_of(scenario: Scenario) -> RunEnd:
    """What ends a run of ``scenario``."""
    period = scenario.controller.period
    waypoints = scenario.waypoints
    last = waypoints[-1]
    return RunEnd(
        len(waypoints) - 1,
        (last.x, last.y, last.z),
        last.t,
        round(scenario.duration / period),
        round(scenario.time_limit / period),
        round(scenario.no_progress_time / period),
    )


def task_done(
    ops: Ops,
    end: RunEnd,
    reached: Real,
    output: ControlOutput,
    joint_velocity: Point3,
) -> Mask:
    """Whether the task is done after a tick: ``reached`` the law's state's (after the tick),
    ``output`` the tick's, ``joint_velocity`` as measured at the tick."""
    speeds = [
        abs(speed) < limit for speed, limit in zip(joint_velocity, SETTLED_SPEEDS, strict=True)
    ]
    return (
        (reached >= end.last)
        & (output.progress >= end.time)
        & (distance(ops, output.tcp, end.point) <= WAYPOINT_TOLERANCE)
        & speeds[0]
        & speeds[1]
        & speeds[2]
    )


def watched(
    ops: Ops, end: RunEnd, watch: Watch, output: ControlOutput, tick: Real, settled: Mask
) -> Watch:
    """The watch after the tick ``tick``: progress if the plan waits for another waypoint,
    the TCP came PROGRESS_STEP nearer it, the plan ran PLAN_STEP on before its last
    waypoint's time, or the task is done but for the settling time (``settled``)."""
    waited, progress = output.waited, output.progress
    away = distance(ops, output.tcp, waited)
    other = (
        (waited[0] != watch.waited[0])
        | (waited[1] != watch.waited[1])
        | (waited[2] != watch.waited[2])
    )
    moved = (progress - watch.plan >= PLAN_STEP) & (progress < end.time)
    fresh = other | moved
    nearer = away <= watch.best - PROGRESS_STEP
    made = fresh | nearer | settled
    return Watch(
        waited,
        ops.where(made, away, watch.best),
        ops.where(fresh, progress, watch.plan),
        ops.where(made, tick, watch.since),
    )


def ending(
    ops: Ops,
    end: RunEnd,
    reached: Real,
    output: ControlOutput,
    joint_velocity: Point3,
    tick: Real,
    clock_tick: Real,
    watch: Watch,
) -> tuple[Real, Watch]:
    """How the run ends after the tick ``tick`` (on the plan's clock, from 0) at the run's
    clock's ``clock_tick`` (the same but in a held real-time run): a code of ENDINGS, 0 while
    it goes on: see OUTCOMES; and the watch over its progress after the tick (``watch``:
    before it; UNWATCHED before the first). (The rest as for :func:`task_done`.)"""
    settled = task_done(ops, end, reached, output, joint_velocity)
    watch = watched(ops, end, watch, output, tick, settled)
    done = settled & (tick >= end.end_tick)
    stuck = ops.not_(done) & (tick - watch.since >= end.no_progress_ticks)
    timed_out = ops.not_(done) & (clock_tick >= end.limit_tick)
    code = ops.where(done, 1, ops.where(stuck, 4, ops.where(timed_out, 2, 0)))
    return ops.where(output.no_safe_motion, 3, code), watch
