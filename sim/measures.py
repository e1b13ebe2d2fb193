"""The measures of a run, defined once for every source of runs (the in-process simulation,
a co-simulation's controller log, a replayed recording); see ``docs/design.md``."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from controller.planner import plan_of
from controller.runlog import RunLog
from protocol.kinematics import tcp_velocity
from protocol.scenario import WAYPOINT_TOLERANCE as WAYPOINT_TOLERANCE  # the one definition
from protocol.scenario import Scenario

STOP_SPEED_FRACTION = 0.02
"""A stop is planar TCP speed below this fraction of the planned mean speed ..."""
STOP_MIN_TICKS = 3
"""... for at least this many ticks in a row ..."""
STOP_EDGE_MARGIN = 0.2
"""... while the plan itself is moving, not within this many seconds of start or end ..."""
STOP_REST_MARGIN = 0.1
"""... nor within this many seconds of plan of a planned rest (a waypoint the plan stops at:
the arm lags the plan, and slowing down to a planned stop is not a stop)."""
PLAN_SAMPLES = 2001
"""Points of the plan sampled for its length."""
JERK_WINDOW = 15
"""Ticks in the local cubic fit that jerk is taken from (30 ms at 500 Hz)."""


@dataclass(frozen=True, slots=True)
class Measures:
    collision_free: bool
    min_clearance: float
    stops: int
    peak_jerk: float
    rms_jerk: float
    max_command_jump: float
    completion_time: float
    path_length: float
    waypoint_miss: tuple[float, ...]

    @property
    def max_waypoint_miss(self) -> float:
        return max(self.waypoint_miss)

    def as_dict(self) -> dict[str, Any]:
        values = asdict(self)
        values["waypoint_miss"] = list(self.waypoint_miss)
        values["max_waypoint_miss"] = self.max_waypoint_miss
        return values


# (attribute, label, unit, scale for display, format)
TABLE_ROWS = (
    ("collision_free", "collision-free", "", 1.0, "{}"),
    ("min_clearance", "min clearance", "mm", 1e3, "{:.2f}"),
    ("stops", "stops", "", 1.0, "{}"),
    ("peak_jerk", "peak jerk", "m/s^3", 1.0, "{:.1f}"),
    ("rms_jerk", "RMS jerk", "m/s^3", 1.0, "{:.2f}"),
    ("max_command_jump", "max per-tick command jump", "rad/s", 1.0, "{:.4f}"),
    ("completion_time", "completion time", "s", 1.0, "{:.3f}"),
    ("path_length", "path length", "m", 1.0, "{:.4f}"),
    ("max_waypoint_miss", "worst waypoint miss", "mm", 1e3, "{:.3f}"),
)


def compute_measures(scenario: Scenario, log: RunLog) -> Measures:
    period = scenario.controller.period
    positions = log.columns("x", "y", "z")
    vx, vy = tcp_velocity(
        scenario.robot, log["theta1"], log["theta2"], log["theta1_rate"], log["theta2_rate"], np
    )
    velocity = np.column_stack([vx, vy, -log["d3_rate"]])
    jerk = np.linalg.norm(second_derivative(velocity, period, log["clock"]), axis=1)

    clearance = log["clearance"]
    min_clearance = float(np.min(clearance)) if len(clearance) else math.inf

    waypoints = scenario.waypoints
    progress = log["progress"]
    threshold, rests = stop_threshold_and_rests(scenario)
    planar_speed = np.hypot(velocity[:, 0], velocity[:, 1])
    watched = (
        (log["reference_speed"] >= threshold)
        & (progress >= waypoints[0].t + STOP_EDGE_MARGIN)
        & (progress <= waypoints[-1].t - STOP_EDGE_MARGIN)
        & ~near_any(progress, rests, STOP_REST_MARGIN)
    )
    stops = _count_runs(watched & (planar_speed < threshold), STOP_MIN_TICKS)

    misses = tuple(
        float(np.min(np.linalg.norm(positions - (w.x, w.y, w.z), axis=1))) for w in waypoints
    )
    last = waypoints[-1]
    done = (np.linalg.norm(positions - (last.x, last.y, last.z), axis=1) <= WAYPOINT_TOLERANCE) & (
        progress >= waypoints[-2].t
    )
    clock = log["clock"]
    completion = float(clock[np.argmax(done)] - waypoints[0].t) if done.any() else math.nan

    commands = log.columns("command_theta1", "command_theta2")
    return Measures(
        collision_free=bool(min_clearance > 0.0),
        min_clearance=min_clearance,
        stops=stops,
        peak_jerk=float(np.max(jerk)) if len(jerk) else 0.0,
        rms_jerk=float(np.sqrt(np.mean(jerk**2))) if len(jerk) else 0.0,
        max_command_jump=float(np.max(np.abs(np.diff(commands, axis=0))))
        if len(commands) > 1
        else 0.0,
        completion_time=completion,
        path_length=float(np.sum(np.linalg.norm(np.diff(positions, axis=0), axis=1))),
        waypoint_miss=misses,
    )


def stop_threshold_and_rests(scenario: Scenario) -> tuple[float, np.ndarray]:
    """The speed below which the arm counts as stopped (STOP_SPEED_FRACTION of the plan's mean
    planar speed), and the plan's rests: the times of the waypoints it passes slower than
    that (it stops where a coordinate turns back)."""
    waypoints = scenario.waypoints
    planned = plan_of(scenario)
    samples = np.linspace(waypoints[0].t, waypoints[-1].t, PLAN_SAMPLES)
    planned_points = np.array([planned.evaluate(float(t))[0] for t in samples])
    planned_length = float(np.sum(np.linalg.norm(np.diff(planned_points[:, :2], axis=0), axis=1)))
    threshold = STOP_SPEED_FRACTION * planned_length / (waypoints[-1].t - waypoints[0].t)
    rests = [
        time
        for time, velocity in zip(planned.times, planned.velocities, strict=True)
        if math.hypot(velocity[0], velocity[1]) < threshold
    ]
    return threshold, np.array(rests)


def near_any(values: np.ndarray, marks: np.ndarray, margin: float) -> np.ndarray:
    """Which ``values`` lie within ``margin`` of one of ``marks``."""
    return np.asarray(np.any(np.abs(values[:, None] - marks[None, :]) <= margin, axis=1))


def second_derivative(series: np.ndarray, period: float, clock: np.ndarray) -> np.ndarray:
    """Second derivative of each column by a Savitzky-Golay filter (cubic, JERK_WINDOW ticks).

    Differencing the measured velocity twice would mostly measure the wire's quantisation
    (1e-3 rad/s per step is ~100 m/s^3 of jerk at 500 Hz); the local cubic fit removes that
    while keeping the jerk of a switch, which lasts several ticks through the actuator lag.
    Only windows of consecutive ticks count: across a hold there is no measured state, and a
    fit over the gap would invent jerk.
    """
    half = JERK_WINDOW // 2
    if len(series) < JERK_WINDOW:
        return np.zeros((0, series.shape[1]))
    offsets = np.arange(-half, half + 1, dtype=float)
    design = np.vander(offsets, 4, increasing=True)
    weights = np.linalg.pinv(design)[2] * 2.0 / period**2
    windows = np.lib.stride_tricks.sliding_window_view(series, JERK_WINDOW, axis=0)
    gaps = np.diff(clock) > 1.5 * period
    spans_gap = np.convolve(gaps, np.ones(JERK_WINDOW - 1), mode="valid") > 0
    return np.asarray(windows @ weights)[~spans_gap]


def _count_runs(flags: np.ndarray, min_length: int) -> int:
    """How many runs of consecutive True values are at least ``min_length`` long."""
    padded = np.concatenate([[False], flags, [False]]).astype(np.int8)
    edges = np.diff(padded)
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return int(np.sum(ends - starts >= min_length))


def format_table(results: dict[str, Measures]) -> str:
    """The measures of several runs side by side, as a Markdown table."""
    names = list(results)
    lines = [
        "| measure | " + " | ".join(names) + " |",
        "|---|" + "---:|" * len(names),
    ]
    for attribute, label, unit, scale, fmt in TABLE_ROWS:
        cells = []
        for name in names:
            value = getattr(results[name], attribute)
            if isinstance(value, (bool, int)):
                cells.append(fmt.format(value))
            else:
                cells.append(fmt.format(value * scale))
        lines.append(f"| {label}{f' ({unit})' if unit else ''} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
