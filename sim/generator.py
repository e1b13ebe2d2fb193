"""Random scenarios from a seed, for studies over thousands of runs.

Scenario ``index`` of seed ``seed`` depends on those two numbers only (its own random stream,
``numpy.random.default_rng([seed, index])``), so a study of 1,000 scenarios is the first
1,000 of a study of 100,000 and any worker can rebuild any slice of it.

Every scenario passes the checks a hand-written one does (:func:`check_scenario`, and the
planned path by :func:`check_plan`), and the generator's own rules on top (a draw that breaks
one is drawn again from the same stream):

- **waypoints kept clear** (the study's condition for "every waypoint passed within 2 mm"):
  every waypoint below the obstacle's top is at least :data:`WAYPOINT_CLEARANCE` clear of
  the inflated obstacle, and consecutive waypoints are at least :data:`MIN_SPACING` apart;
- the obstacle is either in the way (its inflated top above the whole planned path) or
  below it (its inflated top under the whole planned path), never cut by the plan's height,
  which no planar avoidance could handle;
- an obstacle in the way leaves room to go round it: its inflated section grown by
  :data:`PASSAGE` is reachable all round.

The cases (:class:`Case`) take turns by index, so every case is in any study of at least
``len(Case)`` scenarios.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from enum import Enum

import numpy as np

from controller.planner import check_plan, plan_of
from protocol.config import RobotConfig
from protocol.errors import ConfigError, KinematicsError, ScaraError
from protocol.geometry import EllipticCylinder
from protocol.kinematics import Elbow, inverse, reach_radii
from protocol.scenario import (
    DEFAULT_MARGIN,
    DEFAULT_TOOL_RADIUS,
    Mode,
    Scenario,
    Waypoint,
    check_scenario,
)
from sim.measures import STOP_REST_MARGIN, STOP_SPEED_FRACTION, stop_threshold_and_rests


class Case(Enum):
    """What a generated scenario is made to test."""

    OPEN = "open"
    """Waypoints and obstacle anywhere (sometimes a low obstacle)."""
    ACROSS = "across"
    """The obstacle across a segment."""
    BACK_ACROSS = "back_across"
    """Past the obstacle to a waypoint, then back across it to the next."""
    DOORSTEP = "doorstep"
    """The obstacle on the way in, just before a waypoint."""
    BOUNDARY = "boundary"
    """Waypoints near the reach's outer or inner edge, the obstacle across a segment."""
    STRETCHED = "stretched"
    """Two waypoints near the stretched-arm singularity (theta2 of about 5-11 deg)."""
    BELOW = "below"
    """An obstacle across a segment but below the path: the arm passes over it."""


WAYPOINT_CLEARANCE = 0.02
"""m: least clearance between a waypoint and the inflated obstacle it is below the top of."""
DOORSTEP_CLEARANCE = (0.02, 0.03)
"""m: the clearance of the waypoint an obstacle stands at the doorstep of."""
MIN_SPACING = 0.05
"""m: least distance between consecutive waypoints."""
PASSAGE = 0.03
"""m: room kept reachable all round an obstacle in the way (AO passes 15 mm off it)."""
HEIGHT_GAP = 0.01
"""m: least vertical gap between the obstacle's inflated top and the planned path."""
SETTLE_TIME = 3.0
"""s after the last waypoint's time: the run's allowance for the time detours cost."""
SPEED_RANGE = (0.08, 0.22)
"""m/s: the planned mean speed of a segment is drawn from this range ..."""
MIN_SEGMENT_TIME = 1.0
"""... and a segment lasts at least this long (s)."""
ANGLE_RANGE = math.radians(90.0)
"""Waypoints lie within this angle either side of the x axis (theta1 stays within limits)."""
Z_RANGE = (0.20, 0.37)
"""m: heights of the waypoints (the tool reaches 0.187-0.387 m)."""
TALL_HEIGHT = (0.40, 0.45)
"""m: heights of an obstacle in the way (above every reachable tool height)."""
DIAMETER_RANGE = (0.03, 0.14)
"""m: the obstacle's long diameter; the short one is a fraction of it ..."""
ASPECT_RANGE = (0.3, 1.0)
"""... drawn from this range."""
STRETCHED_RADIUS = (0.9955, 0.9985)
"""Fraction of the full reach of the stretched case's waypoints (theta2 about 5-11 deg)."""
MAX_ATTEMPTS = 500
"""Draws per scenario before giving up (a valid one comes within a few)."""
PATH_SAMPLES = 2000
"""Planned points checked against the height and speed rules."""
CRAWL_FRACTION = 0.1
"""The plan moves at least this fraction of its mean planar speed, except near its rests."""
DOORSTEP_BISECTIONS = 40
"""Halvings of the doorstep distance (0.5 m / 2^40: far below a micrometre)."""

Point = tuple[float, float, float]
Draw = tuple[list[Point], EllipticCylinder]


def generate_scenarios(count: int, seed: int, mode: Mode = Mode.FUZZY) -> list[Scenario]:
    """The first ``count`` scenarios of the study with ``seed``, in ``mode``."""
    return [generate_scenario_at(seed, index, mode) for index in range(count)]


def generate_scenario_at(seed: int, index: int, mode: Mode = Mode.FUZZY) -> Scenario:
    """Scenario ``index`` of the study with ``seed``: the same numbers, the same scenario."""
    if seed < 0 or index < 0:
        raise ConfigError("seed" if seed < 0 else "index", "must not be negative")
    case = list(Case)[index % len(Case)]
    rng = np.random.default_rng([seed, index])
    scenario = generate_scenario(rng, case, f"gen-{seed}-{index}-{case.value}")
    return scenario.with_mode(mode)


def generate_scenario(
    rng: np.random.Generator, case: Case, name: str, robot: RobotConfig | None = None
) -> Scenario:
    """A valid scenario of ``case`` from ``rng`` (invalid draws are drawn again)."""
    robot = robot or RobotConfig()
    for _ in range(MAX_ATTEMPTS):
        points, obstacle = _DRAWS[case](rng, robot)
        scenario = _timed_scenario(name, points, obstacle, rng, robot)
        if scenario is not None:
            return scenario
    raise ScaraError(f"no valid {case.value} scenario in {MAX_ATTEMPTS} draws ({name})")


def case_of(scenario: Scenario) -> Case:
    """The case of a generated scenario, from its name."""
    return Case(scenario.name.rsplit("-", 1)[-1])


def waypoints_clear(scenario: Scenario, room: float = WAYPOINT_CLEARANCE) -> bool:
    """Every waypoint reachable and, if below the obstacle's inflated top, at least ``room``
    clear of the inflated obstacle: the scenarios whose waypoints must all be passed."""
    obstacle = scenario.obstacle
    for point in scenario.waypoints:
        try:
            inverse(scenario.robot, point.x, point.y, point.z, scenario.elbow)
        except KinematicsError:
            return False
        if (
            obstacle is not None
            and point.z < obstacle.height + obstacle.inflation
            and obstacle.clearance(point.x, point.y) < room - 1e-9
        ):
            return False
    return True


# --- building blocks --------------------------------------------------------------------------


def _polar(rng: np.random.Generator, radius: tuple[float, float]) -> Point:
    r = rng.uniform(*radius)
    angle = rng.uniform(-ANGLE_RANGE, ANGLE_RANGE)
    return (r * math.cos(angle), r * math.sin(angle), rng.uniform(*Z_RANGE))


def _reach(robot: RobotConfig, inner: float, outer: float) -> tuple[float, float]:
    """The reachable radii less ``inner`` at the inside and ``outer`` at the outside."""
    low, high = reach_radii(robot)
    return (low + inner, high - outer)


def _random_points(rng: np.random.Generator, robot: RobotConfig, count: int) -> list[Point]:
    return [_polar(rng, _reach(robot, 0.05, 0.03)) for _ in range(count)]


def _obstacle(
    rng: np.random.Generator, x: float, y: float, height: float | None = None
) -> EllipticCylinder:
    """An elliptic cylinder of random size and yaw at (x, y); tall unless ``height`` is given."""
    long_diameter = rng.uniform(*DIAMETER_RANGE)
    return EllipticCylinder(
        x=x,
        y=y,
        long_diameter=long_diameter,
        short_diameter=long_diameter * rng.uniform(*ASPECT_RANGE),
        height=rng.uniform(*TALL_HEIGHT) if height is None else height,
        yaw=rng.uniform(0.0, math.pi),
        inflation=DEFAULT_TOOL_RADIUS + DEFAULT_MARGIN,
    )


def _moved(obstacle: EllipticCylinder, x: float, y: float) -> EllipticCylinder:
    return EllipticCylinder(
        x,
        y,
        obstacle.long_diameter,
        obstacle.short_diameter,
        obstacle.height,
        obstacle.yaw,
        obstacle.inflation,
    )


def _across(rng: np.random.Generator, start: Point, end: Point) -> EllipticCylinder:
    """An obstacle across the chord from ``start`` to ``end``: its centre between 35 % and
    65 % of the way, off the chord by at most half its short semi-axis."""
    share = rng.uniform(0.35, 0.65)
    probe = _obstacle(rng, 0.0, 0.0)
    dx, dy = end[0] - start[0], end[1] - start[1]
    length = max(math.hypot(dx, dy), 1e-9)
    offset = rng.uniform(-0.5, 0.5) * probe.semi_axes[1]
    x = start[0] + share * dx - offset * dy / length
    y = start[1] + share * dy + offset * dx / length
    return _moved(probe, x, y)


def _across_a_segment(rng: np.random.Generator, points: list[Point]) -> EllipticCylinder:
    segment = int(rng.integers(0, len(points) - 1))
    return _across(rng, points[segment], points[segment + 1])


# --- the cases ---------------------------------------------------------------------------------


def _draw_open(rng: np.random.Generator, robot: RobotConfig) -> Draw:
    points = _random_points(rng, robot, int(rng.integers(2, 7)))
    x, y, _ = _polar(rng, _reach(robot, 0.08, 0.06))
    low = rng.random() < 0.3
    return points, _obstacle(rng, x, y, rng.uniform(0.03, 0.12) if low else None)


def _draw_across(rng: np.random.Generator, robot: RobotConfig) -> Draw:
    points = _random_points(rng, robot, int(rng.integers(2, 7)))
    return points, _across_a_segment(rng, points)


def _draw_back_across(rng: np.random.Generator, robot: RobotConfig) -> Draw:
    x, y, _ = _polar(rng, _reach(robot, 0.15, 0.15))
    obstacle = _obstacle(rng, x, y)
    reach = obstacle.semi_axes[0] + WAYPOINT_CLEARANCE
    direction = rng.uniform(-math.pi, math.pi)
    legs = []
    for turn, distance in (
        (0.0, reach + rng.uniform(0.02, 0.10)),
        (math.pi + rng.uniform(-0.4, 0.4), reach + rng.uniform(0.0, 0.05)),
        (rng.uniform(-0.6, 0.6), reach + rng.uniform(0.02, 0.10)),
    ):
        angle = direction + turn
        legs.append((x + distance * math.cos(angle), y + distance * math.sin(angle)))
    z = rng.uniform(*Z_RANGE)
    crossing = [(px, py, z + rng.uniform(-0.02, 0.02)) for px, py in legs]
    extra = int(rng.integers(0, 4))
    before = int(rng.integers(0, extra + 1))
    points = (
        _random_points(rng, robot, before) + crossing + _random_points(rng, robot, extra - before)
    )
    return points, obstacle


def _draw_doorstep(rng: np.random.Generator, robot: RobotConfig) -> Draw:
    points = _random_points(rng, robot, int(rng.integers(2, 7)))
    index = int(rng.integers(1, len(points)))
    target, previous = points[index], points[index - 1]
    back = math.atan2(previous[1] - target[1], previous[0] - target[0])
    direction = back + rng.uniform(-0.5, 0.5)
    obstacle = _obstacle(rng, target[0], target[1])
    wanted = rng.uniform(*DOORSTEP_CLEARANCE)
    near, far = 0.0, 0.5
    for _ in range(DOORSTEP_BISECTIONS):  # the distance that leaves the wanted clearance
        middle = 0.5 * (near + far)
        trial = _moved(
            obstacle,
            target[0] + middle * math.cos(direction),
            target[1] + middle * math.sin(direction),
        )
        if trial.clearance(target[0], target[1]) < wanted:
            near = middle
        else:
            far = middle
    return points, _moved(
        obstacle, target[0] + far * math.cos(direction), target[1] + far * math.sin(direction)
    )


def _draw_boundary(rng: np.random.Generator, robot: RobotConfig) -> Draw:
    low, high = reach_radii(robot)
    points = []
    for _ in range(int(rng.integers(2, 7))):
        band = (high - 0.06, high - 0.008) if rng.random() < 0.6 else (low + 0.005, low + 0.05)
        points.append(_polar(rng, band) if rng.random() < 0.7 else _random_points(rng, robot, 1)[0])
    return points, _across_a_segment(rng, points)


def _draw_stretched(rng: np.random.Generator, robot: RobotConfig) -> Draw:
    high = reach_radii(robot)[1]
    count = int(rng.integers(3, 7))
    first = int(rng.integers(0, count - 1))
    points = _random_points(rng, robot, count)
    anchor = rng.uniform(-ANGLE_RANGE + 0.3, ANGLE_RANGE - 0.3)
    for offset, index in enumerate((first, first + 1)):
        radius = high * rng.uniform(*STRETCHED_RADIUS)
        angle = anchor + (offset - 0.5) * rng.uniform(0.15, 0.4)
        points[index] = (radius * math.cos(angle), radius * math.sin(angle), points[index][2])
    # The obstacle across a segment that leaves or reaches the stretched pair.
    if first + 2 < count and (first == 0 or rng.random() < 0.5):
        segment = first + 1
    elif first > 0:
        segment = first - 1
    else:
        segment = first
    return points, _across(rng, points[segment], points[segment + 1])


def _draw_below(rng: np.random.Generator, robot: RobotConfig) -> Draw:
    points, obstacle = _draw_across(rng, robot)
    top = min(p[2] for p in points) - obstacle.inflation - HEIGHT_GAP
    return points, EllipticCylinder(
        obstacle.x,
        obstacle.y,
        obstacle.long_diameter,
        obstacle.short_diameter,
        rng.uniform(0.3, 0.9) * top,
        obstacle.yaw,
        obstacle.inflation,
    )


_DRAWS: dict[Case, Callable[[np.random.Generator, RobotConfig], Draw]] = {
    Case.OPEN: _draw_open,
    Case.ACROSS: _draw_across,
    Case.BACK_ACROSS: _draw_back_across,
    Case.DOORSTEP: _draw_doorstep,
    Case.BOUNDARY: _draw_boundary,
    Case.STRETCHED: _draw_stretched,
    Case.BELOW: _draw_below,
}


# --- checks --------------------------------------------------------------------------------------


def _timed_scenario(
    name: str,
    points: list[Point],
    obstacle: EllipticCylinder,
    rng: np.random.Generator,
    robot: RobotConfig,
) -> Scenario | None:
    """The scenario through ``points`` with timed segments, or None if a rule refuses it."""
    pairs = list(itertools.pairwise(points))
    if any(math.dist(first, second) < MIN_SPACING for first, second in pairs):
        return None
    times = [0.0]
    for first, second in pairs:
        duration = max(MIN_SEGMENT_TIME, math.dist(first, second) / rng.uniform(*SPEED_RANGE))
        times.append(round(times[-1] + duration, 3))
    obstacle = _as_written(obstacle)
    scenario = Scenario(
        name=name,
        waypoints=tuple(
            Waypoint(t, round(x, 4), round(y, 4), round(z, 4))
            for t, (x, y, z) in zip(times, points, strict=True)
        ),
        obstacle=obstacle,
        settle_time=SETTLE_TIME,
        robot=robot,
        tool_radius=DEFAULT_TOOL_RADIUS,
    )
    try:
        check_scenario(scenario)
        check_plan(scenario)
    except ConfigError:
        return None
    return scenario if _fits_the_rules(scenario, obstacle) else None


def _as_written(obstacle: EllipticCylinder) -> EllipticCylinder:
    """``obstacle`` to a tenth of a millimetre and a thousandth of a degree, as a scenario
    file would give it (so that the file of a generated scenario reads back the same)."""
    return EllipticCylinder(
        round(obstacle.x, 4),
        round(obstacle.y, 4),
        round(obstacle.long_diameter, 4),
        round(obstacle.short_diameter, 4),
        round(obstacle.height, 4),
        math.radians(round(math.degrees(obstacle.yaw), 3)),
        obstacle.inflation,
    )


def _fits_the_rules(scenario: Scenario, obstacle: EllipticCylinder) -> bool:
    """The generator's own rules (module docstring) on top of the scenario checks."""
    if not _moves_sensibly(scenario):
        return False
    plan = plan_of(scenario)
    start, end = scenario.waypoints[0].t, scenario.waypoints[-1].t
    heights = plan.sample(np.linspace(start, end, PATH_SAMPLES))[0][:, 2]
    top = obstacle.height + obstacle.inflation
    if heights.min() > top + HEIGHT_GAP:
        return True  # the path passes over it
    if heights.max() > top - HEIGHT_GAP or not waypoints_clear(scenario):
        return False
    a, b = obstacle.semi_axes
    for angle in np.linspace(0.0, 2.0 * math.pi, 36, endpoint=False):
        x, y = obstacle.to_world((a + PASSAGE) * math.cos(angle), (b + PASSAGE) * math.sin(angle))
        try:
            inverse(scenario.robot, x, y, float(heights[0]), Elbow.DOWN)
        except KinematicsError:
            return False
    return True


def _moves_sensibly(scenario: Scenario) -> bool:
    """The plan never crawls (below CRAWL_FRACTION of its mean planar speed) except within
    STOP_REST_MARGIN of a waypoint it stops at: a crawl is where the stop measure cannot
    tell a lagging arm from a stopped one (the wire's velocity quantum is 1e-3 rad/s)."""
    threshold, rests = stop_threshold_and_rests(scenario)
    crawl = threshold * CRAWL_FRACTION / STOP_SPEED_FRACTION
    plan = plan_of(scenario)
    times = np.linspace(scenario.waypoints[0].t, scenario.waypoints[-1].t, PATH_SAMPLES)
    velocities = plan.sample(times)[1].tolist()
    speeds = np.array([math.hypot(vx, vy) for vx, vy, _ in velocities])
    near_rest = np.any(np.abs(times[:, None] - rests[None, :]) <= STOP_REST_MARGIN, axis=1)
    crawling = (speeds < crawl) & ~near_rest
    return not crawling.any()
