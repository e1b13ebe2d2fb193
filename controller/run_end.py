"""When a run ends: its task done, its timeout reached, or no safe motion left.

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
"""

from __future__ import annotations

from enum import StrEnum
from typing import NamedTuple

from controller.control_law import ControlOutput, Point3
from protocol.geometry import distance
from protocol.ops import Mask, Ops, Real
from protocol.scenario import WAYPOINT_TOLERANCE, Scenario

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
    CUT_SHORT = "cut_short"
    """Ended otherwise, before any of those: a stop, another fault, an e-stop, the process
    stopped (only a co-simulation's run)."""


OUTCOMES = (RunOutcome.DONE, RunOutcome.TASK_TIMEOUT, RunOutcome.NO_SAFE_MOTION)
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


def ending(
    ops: Ops,
    end: RunEnd,
    reached: Real,
    output: ControlOutput,
    joint_velocity: Point3,
    tick: Real,
    clock_tick: Real,
) -> Real:
    """How the run ends after the tick ``tick`` (on the plan's clock, from 0) at the run's
    clock's ``clock_tick`` (the same but in a held real-time run): a code of ENDINGS, 0 while
    it goes on: see OUTCOMES. (The rest as for :func:`task_done`.)"""
    done = task_done(ops, end, reached, output, joint_velocity) & (tick >= end.end_tick)
    timed_out = ops.not_(done) & (clock_tick >= end.limit_tick)
    return ops.where(output.no_safe_motion, 3, ops.where(done, 1, ops.where(timed_out, 2, 0)))
