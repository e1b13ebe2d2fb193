"""The measures of a run, defined once for every source of runs (the in-process simulation,
a co-simulation's controller log, a replayed recording); see ``docs/design.md``."""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from controller.planner import Trajectory, plan_of
from controller.run_end import RunOutcome
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
"""... nor within this many seconds of plan of a stretch where the plan itself is slower than
the stop speed (:func:`slow_stretches`: the arm lags the plan, and slowing down to a planned
stop, or moving off from one, is not a stop), nor of a waypoint where it turns back while it
crawls (:func:`turn_backs`)."""
CRAWL_FRACTION = 0.1
"""The plan crawls below this fraction of its mean planar speed (five times the stop speed)."""
PLAN_SAMPLES = 2001
"""Points of the plan sampled for its length."""
Array = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]

JERK_WINDOW = 15
"""Ticks in the local cubic fit that jerk is taken from (30 ms at 500 Hz)."""


@dataclass(frozen=True, slots=True)
class Measures:
    outcome: RunOutcome
    """How the run ended: its task done, its timeout reached, no safe motion left, or (a
    co-simulation) cut short; the run's driver knows it, not the log."""
    collision_free: bool
    min_clearance: float
    stops: int
    stop_margin: float
    """How near the run came to a stop: the slowest planar speed the TCP kept up over
    STOP_MIN_TICKS ticks in a row where stops count, over the stop speed. Below 1 exactly
    where a stop is counted; inf if no stretch of the run counts, or the plan does not move in
    the plane."""
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
    ("outcome", "outcome", "", 1.0, "{}"),
    ("collision_free", "collision-free", "", 1.0, "{}"),
    ("min_clearance", "min clearance", "mm", 1e3, "{:.2f}"),
    ("stops", "stops", "", 1.0, "{}"),
    ("stop_margin", "stop margin (slowest / stop speed)", "", 1.0, "{:.2f}"),
    ("peak_jerk", "peak jerk", "m/s^3", 1.0, "{:.1f}"),
    ("rms_jerk", "RMS jerk", "m/s^3", 1.0, "{:.2f}"),
    ("max_command_jump", "max per-tick command jump", "rad/s", 1.0, "{:.4f}"),
    ("completion_time", "completion time", "s", 1.0, "{:.3f}"),
    ("path_length", "path length", "m", 1.0, "{:.4f}"),
    ("max_waypoint_miss", "worst waypoint miss", "mm", 1e3, "{:.3f}"),
)


def compute_measures(scenario: Scenario, log: RunLog, outcome: RunOutcome) -> Measures:
    """The measures of one run's log, which ended with ``outcome``: :class:`MeasureStream`
    fed the whole log at once."""
    stream = MeasureStream([scenario])
    if len(log):
        columns = {name: log[name][:, None] for name in MeasureStream.COLUMNS}
        stream.update(columns, np.ones((len(log), 1), dtype=bool))
    return stream.measures([outcome])[0]


def stop_threshold_and_rests(planned: Trajectory) -> tuple[float, list[int]]:
    """The speed below which the arm counts as stopped (STOP_SPEED_FRACTION of the plan's mean
    planar speed), and the plan's rests: the waypoints (by index) it passes slower than that
    (it stops where a coordinate turns back)."""
    times = planned.times
    samples = np.linspace(times[0], times[-1], PLAN_SAMPLES)
    planned_points = planned.sample(samples)[0]
    planned_length = float(np.sum(np.linalg.norm(np.diff(planned_points[:, :2], axis=0), axis=1)))
    threshold = STOP_SPEED_FRACTION * planned_length / (times[-1] - times[0])
    rests = [
        index
        for index, velocity in enumerate(planned.velocities)
        if math.hypot(velocity[0], velocity[1]) < threshold
    ]
    return threshold, rests


def crawl_speed(threshold: float) -> float:
    """The plan's crawl: CRAWL_FRACTION of its mean planar speed, from its stop speed."""
    return threshold * CRAWL_FRACTION / STOP_SPEED_FRACTION


def turn_backs(planned: Trajectory, threshold: float) -> list[float]:
    """The times of the waypoints where the plan turns back while it crawls: it passes slower
    than its crawl speed (:func:`crawl_speed` of its stop speed ``threshold``), and its
    way STOP_REST_MARGIN after is more than 90 degrees from its way STOP_REST_MARGIN before
    (or at the plan's start or end, if nearer).

    A heading-steered arm turns round there: its speed along the heading passes through 0
    while the way it wants swings past 90 degrees off it, and the plan, a few times the stop
    speed, gives it no more than a few ms to swing (``edge_obstacle`` seed 4, 640: 110-147
    degrees at 1.5 times the stop speed, the arm below it 16 and 25 ticks)."""
    crawl = crawl_speed(threshold)
    times = np.asarray(planned.times[1:-1])
    if not len(times):
        return []
    around = np.concatenate([times - STOP_REST_MARGIN, times, times + STOP_REST_MARGIN])
    around = np.clip(around, planned.times[0], planned.times[-1])
    velocities = planned.sample(around)[1][:, :2].reshape(3, len(times), 2)
    before, at, after = velocities
    crawling = np.hypot(at[:, 0], at[:, 1]) < crawl
    turning_back = np.einsum("ij,ij->i", before, after) < 0.0
    return [float(t) for t in times[crawling & turning_back]]


def slow_stretches(planned: Trajectory, threshold: float) -> list[tuple[float, float]]:
    """The stretches of plan time where the plan's planar speed is below ``threshold``: its
    rests at waypoints, a coordinate of a cubic turning back between two (it overshoots its
    waypoint), and a plan that leaves a rest slowly. Exact: in each segment the speed squared
    less the threshold's is a quartic in local time."""
    stretches: list[tuple[float, float]] = []
    for index in range(len(planned.times) - 1):
        segments = [planned.segment(index, axis) for axis in (0, 1)]
        squared = np.array([0.0, 0.0, 0.0, 0.0, -(threshold**2)])
        for segment in segments:
            _, k1, k2, k3 = segment.coefficients
            squared = squared + np.polymul((3 * k3, 2 * k2, k1), (3 * k3, 2 * k2, k1))
        start, duration = segments[0].t_start, segments[0].duration
        roots: list[float] = list(np.roots(squared).real) if squared[:4].any() else []
        cuts = sorted({0.0, duration, *(r for r in roots if 0.0 < r < duration)})
        for low, high in itertools.pairwise(cuts):
            if np.polyval(squared, 0.5 * (low + high)) < 0.0:
                if stretches and stretches[-1][1] >= start + low - 1e-12:
                    stretches[-1] = (stretches[-1][0], start + high)
                else:
                    stretches.append((start + low, start + high))
    return stretches


class MeasureStream:
    """The measures of many runs, from their logs fed in blocks of ticks (columns named as in
    the run log, shaped (ticks, runs)): the batch simulator's thousands of runs, or one log.

    Only what the measures need is carried from block to block (minima, sums, the last
    JERK_WINDOW - 1 rows, the length of a run of slow ticks), so a batch of thousands of
    runs never holds a whole log. ``valid`` marks the ticks that count: a run that has
    finished is still fed, but no longer counted.
    """

    COLUMNS = (
        "clock",
        "theta1",
        "theta2",
        "theta1_rate",
        "theta2_rate",
        "d3_rate",
        "command_theta1",
        "command_theta2",
        "x",
        "y",
        "z",
        "reference_speed",
        "clearance",
        "progress",
    )

    def __init__(self, scenarios: Sequence[Scenario]) -> None:
        first = scenarios[0]
        self.robot = first.robot
        self.period = first.controller.period
        if any(s.robot != self.robot or s.controller.period != self.period for s in scenarios):
            raise ValueError("runs measured together must share the robot and the rate")
        count = len(scenarios)
        half = JERK_WINDOW // 2
        design = np.vander(np.arange(-half, half + 1, dtype=float), 4, increasing=True)
        self._weights = np.linalg.pinv(design)[2] * 2.0 / self.period**2
        self._counts = [len(s.waypoints) for s in scenarios]
        self._waypoints = np.full((count, max(self._counts), 3), math.inf)
        for row, scenario in enumerate(scenarios):
            self._waypoints[row, : self._counts[row]] = [
                (w.x, w.y, w.z) for w in scenario.waypoints
            ]
        self._last = np.array(self._counts) - 1
        self._start = np.array([s.waypoints[0].t for s in scenarios])
        self._end = np.array([s.waypoints[-1].t for s in scenarios])
        self._before_last = np.array([s.waypoints[-2].t for s in scenarios])
        self._threshold = np.zeros(count)
        # Where the plan comes to rest at a waypoint, that waypoint from the time of the one
        # before it (an arm early there waits for the plan); NaN elsewhere.
        self._rest_times = np.full((count, max(self._counts)), math.inf)
        self._rest_places = np.full((count, max(self._counts), 2), math.nan)
        every_stretch: list[list[tuple[float, float]]] = []
        for row, scenario in enumerate(scenarios):
            planned = plan_of(scenario)
            threshold, rests = stop_threshold_and_rests(planned)
            self._threshold[row] = threshold
            turns = [(t, t) for t in turn_backs(planned, threshold)]
            every_stretch.append(slow_stretches(planned, threshold) + turns)
            self._rest_times[row, : len(planned.times)] = planned.times
            for index in rests:
                if index:
                    self._rest_places[row, index] = planned.points[index][:2]
        self._slow = np.full((count, max(1, *map(len, every_stretch)), 2), math.nan)
        for row, stretches in enumerate(every_stretch):
            self._slow[row, : len(stretches)] = stretches
        self._rows = np.arange(count)
        self._min_clearance = np.full(count, math.inf)
        self._misses = np.full((count, self._waypoints.shape[1]), math.inf)
        self._peak = np.zeros(count)
        self._square_sum = np.zeros(count)
        self._windows = np.zeros(count, dtype=np.int64)
        self._jump = np.zeros(count)
        self._length = np.zeros(count)
        self._completion = np.full(count, math.nan)
        self._stops = np.zeros(count, dtype=np.int64)
        self._slow_run = np.zeros(count, dtype=np.int64)
        self._slowest = np.full(count, math.inf)
        self._tail_watched_speed = np.zeros((0, count))
        self._tail_velocity = np.zeros((0, 3, count))
        self._tail_clock = np.zeros((0, count))
        self._tail_position = np.zeros((0, 3, count))
        self._tail_command = np.zeros((0, 2, count))

    def update(self, columns: Mapping[str, Array], valid: Mask) -> None:
        """Fold in one block: each column (ticks, runs); ``valid`` (ticks, runs).

        Vectors are held as (ticks, component, runs) and their lengths written out
        component by component: the same sums as a norm over a last axis of 3, without
        numpy's slow reductions along so short an axis (a batch's blocks are millions of
        elements)."""
        progress, clock = columns["progress"], columns["clock"]
        vx, vy = tcp_velocity(
            self.robot,
            columns["theta1"],
            columns["theta2"],
            columns["theta1_rate"],
            columns["theta2_rate"],
            np,
        )
        velocity = np.stack([vx, vy, -columns["d3_rate"]], axis=1)
        position = np.stack([columns["x"], columns["y"], columns["z"]], axis=1)
        command = np.stack([columns["command_theta1"], columns["command_theta2"]], axis=1)

        clearance = np.where(valid, columns["clearance"], math.inf)
        self._min_clearance = np.minimum(self._min_clearance, clearance.min(axis=0))

        self._fold_jerk(velocity, clock, valid)

        speed = np.hypot(vx, vy)
        watched = (
            (columns["reference_speed"] >= self._threshold)
            & (progress >= self._start + STOP_EDGE_MARGIN)
            & (progress <= self._end - STOP_EDGE_MARGIN)
            & ~near_stretch(progress, self._slow, STOP_REST_MARGIN)
            & ~self._waiting_at_rest(progress, position)
            & valid
        )
        self._fold_stops(watched & (speed < self._threshold))
        self._fold_slowest(np.where(watched, speed, math.inf))

        for index in range(self._waypoints.shape[1]):
            distance = _length(position - self._waypoints[:, index].T)
            self._misses[:, index] = np.minimum(
                self._misses[:, index], np.where(valid, distance, math.inf).min(axis=0)
            )
        to_last = _length(position - self._waypoints[self._rows, self._last].T)
        done = (to_last <= WAYPOINT_TOLERANCE) & (progress >= self._before_last) & valid
        found = np.isnan(self._completion) & done.any(axis=0)
        if found.any():
            first = np.argmax(done, axis=0)
            self._completion[found] = clock[first[found], self._rows[found]] - self._start[found]

        command = np.concatenate([self._tail_command, command])
        position = np.concatenate([self._tail_position, position])
        counted = valid[len(valid) - len(command) + 1 :]
        if len(command) > 1:
            jump = np.abs(np.diff(command, axis=0))
            jump = np.maximum(jump[:, 0], jump[:, 1])
            self._jump = np.maximum(self._jump, np.where(counted, jump, 0.0).max(axis=0))
            step = _length(np.diff(position, axis=0))
            self._length += _running_sum(np.where(counted, step, 0.0))
        self._tail_command, self._tail_position = command[-1:], position[-1:]

    def _waiting_at_rest(self, progress: Array, position: Array) -> Mask:
        """Ticks where the TCP is within WAYPOINT_TOLERANCE in the plane of the waypoint the
        plan is on its way to, and the plan comes to rest there: the arm is early, and waits
        where the plan will stop."""
        ahead = (self._rest_times[None, :, :] <= progress[:, :, None]).sum(axis=-1)
        ahead = np.minimum(ahead, self._rest_times.shape[1] - 1)
        place = self._rest_places[self._rows[None, :], ahead]  # (ticks, runs, 2)
        gap = np.hypot(position[:, 0] - place[..., 0], position[:, 1] - place[..., 1])
        return np.asarray(gap <= WAYPOINT_TOLERANCE)

    def _fold_jerk(self, velocity: Array, clock: Array, valid: Mask) -> None:
        """Jerk: the second derivative of the TCP velocity by a Savitzky-Golay filter (cubic,
        JERK_WINDOW ticks), the weighted sum written out in a fixed order.

        Differencing the measured velocity twice would mostly measure the wire's quantisation
        (1e-3 rad/s per step is ~100 m/s^3 of jerk at 500 Hz); the local cubic fit removes
        that while keeping the jerk of a switch, which lasts several ticks through the
        actuator lag. Only windows of consecutive ticks count: across a hold there is no
        measured state, and a fit over the gap would invent jerk.
        """
        series = np.concatenate([self._tail_velocity, velocity])
        clocks = np.concatenate([self._tail_clock, clock])
        if len(series) >= JERK_WINDOW:
            count = len(series) - JERK_WINDOW + 1
            fitted = self._weights[0] * series[:count]
            term = np.empty_like(fitted)
            for lag in range(1, JERK_WINDOW):
                fitted += np.multiply(self._weights[lag], series[lag : lag + count], out=term)
            jerk = _length(fitted)
            gaps = np.diff(clocks, axis=0) > 1.5 * self.period
            spans_gap = np.lib.stride_tricks.sliding_window_view(gaps, JERK_WINDOW - 1, axis=0)
            counted = valid[len(valid) - count :] & ~spans_gap.any(axis=-1)
            self._peak = np.maximum(self._peak, np.where(counted, jerk, 0.0).max(axis=0))
            self._square_sum += _running_sum(np.where(counted, jerk * jerk, 0.0))
            self._windows += counted.sum(axis=0)
        self._tail_velocity = series[-(JERK_WINDOW - 1) :]
        self._tail_clock = clocks[-(JERK_WINDOW - 1) :]

    def _fold_stops(self, slow: Mask) -> None:
        """Count runs of at least STOP_MIN_TICKS slow ticks, across blocks: each where it
        ends, a run still going at the end of a block where the next one starts fast.

        Counted so, a run's stops do not depend on the blocks its log is fed in."""
        if not len(slow):
            return
        self._stops += (self._slow_run >= STOP_MIN_TICKS) & ~slow[0]
        index = np.arange(len(slow))[:, None]
        last_fast = np.maximum.accumulate(np.where(slow, -1, index), axis=0)
        length = index - last_fast + np.where(last_fast < 0, self._slow_run, 0)
        ends = slow.copy()
        ends[:-1] &= ~slow[1:]
        ends[-1] = False
        self._stops += (ends & (length >= STOP_MIN_TICKS)).sum(axis=0)
        self._slow_run = np.where(slow[-1], length[-1], 0)

    def _fold_slowest(self, watched_speed: Array) -> None:
        """The slowest speed kept up over STOP_MIN_TICKS ticks in a row (``watched_speed``:
        inf where stops do not count), across blocks."""
        series = np.concatenate([self._tail_watched_speed, watched_speed])
        if len(series) >= STOP_MIN_TICKS:
            windows = np.lib.stride_tricks.sliding_window_view(series, STOP_MIN_TICKS, axis=0)
            self._slowest = np.minimum(self._slowest, windows.max(axis=-1).min(axis=0))
        self._tail_watched_speed = series[-(STOP_MIN_TICKS - 1) :]

    BY_ROW = (
        "_waypoints",
        "_last",
        "_start",
        "_end",
        "_before_last",
        "_threshold",
        "_slow",
        "_rest_times",
        "_rest_places",
        "_min_clearance",
        "_misses",
        "_peak",
        "_square_sum",
        "_windows",
        "_jump",
        "_length",
        "_completion",
        "_stops",
        "_slow_run",
        "_slowest",
    )
    BY_COLUMN = (
        "_tail_velocity",
        "_tail_clock",
        "_tail_position",
        "_tail_command",
        "_tail_watched_speed",
    )

    def keep(self, rows: npt.NDArray[np.intp]) -> None:
        """Only the runs ``rows`` from now on (the others have ended)."""
        for name in self.BY_ROW:
            setattr(self, name, getattr(self, name)[rows])
        for name in self.BY_COLUMN:
            setattr(self, name, getattr(self, name)[..., rows])
        self._counts = [self._counts[row] for row in rows]
        self._rows = np.arange(len(rows))

    def measures(
        self, outcomes: Sequence[RunOutcome], rows: npt.NDArray[np.intp] | None = None
    ) -> list[Measures]:
        """The measures of the runs ``rows`` (all if None), in their order, which ended with
        ``outcomes`` (one each)."""
        stops = self._stops + (self._slow_run >= STOP_MIN_TICKS)
        rms = np.sqrt(self._square_sum / np.maximum(self._windows, 1))
        margin = np.divide(  # a plan that stays put in the plane has no stop speed
            self._slowest,
            self._threshold,
            out=np.full_like(self._slowest, math.inf),
            where=self._threshold > 0.0,
        )
        rows = self._rows if rows is None else rows
        return [
            Measures(
                outcome=outcome,
                collision_free=bool(self._min_clearance[row] > 0.0),
                min_clearance=float(self._min_clearance[row]),
                stops=int(stops[row]),
                stop_margin=float(margin[row]),
                peak_jerk=float(self._peak[row]),
                rms_jerk=float(rms[row]),
                max_command_jump=float(self._jump[row]),
                completion_time=float(self._completion[row]),
                path_length=float(self._length[row]),
                waypoint_miss=tuple(float(m) for m in self._misses[row, : self._counts[row]]),
            )
            for row, outcome in zip(rows, outcomes, strict=True)
        ]


def _running_sum(values: Array) -> Array:
    """Sums over axis 0 added in order, whatever the array's layout (``sum`` adds pairwise
    along a contiguous axis): a run's measures do not depend on the batch it ran in."""
    return np.asarray(np.cumsum(values, axis=0)[-1])


def _length(vectors: Array) -> Array:
    """The lengths of (ticks, 3, runs) vectors, summed as a norm over the components."""
    x, y, z = vectors[:, 0], vectors[:, 1], vectors[:, 2]
    return np.asarray(np.sqrt(x * x + y * y + z * z))


def near_stretch(values: np.ndarray, stretches: np.ndarray, margin: float) -> np.ndarray:
    """Which ``values`` (ticks, runs) lie within ``margin`` of one of each run's ``stretches``
    (runs, count, 2: start and end; NaN rows none)."""
    near = np.zeros(values.shape, dtype=bool)
    for index in range(stretches.shape[1]):
        start, end = stretches[:, index, 0], stretches[:, index, 1]
        near |= (values >= start - margin) & (values <= end + margin)
    return near


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
            if isinstance(value, (bool, int, str)):
                cells.append(fmt.format(value))
            else:
                cells.append(fmt.format(value * scale))
        lines.append(f"| {label}{f' ({unit})' if unit else ''} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
