"""Which way round the obstacle the arm can take (controller/detour.py), and the plan check
that refuses a task with a segment neither way can take round."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from controller.detour import LIMIT_ROOM, passable, straight_passable, ways_round
from controller.planner import check_plan
from controller.run_end import RunOutcome
from controller.task_rules import check_task
from protocol.config import ControllerConfig, RobotConfig
from protocol.errors import NoWayRoundError
from protocol.geometry import EllipticCylinder
from protocol.kinematics import Elbow, reach_radii
from protocol.messages import Reason, reason_of
from protocol.ops import ARRAY, SCALAR
from protocol.scenario import Mode, Scenario, Waypoint
from sim.simulation import simulate

ROBOT = RobotConfig()
INNER, OUTER = reach_radii(ROBOT)


def across(radius: float, diameter: float, long: float | None = None) -> EllipticCylinder:
    """An obstacle centred on the x axis at ``radius``, its long axis along it."""
    return EllipticCylinder(radius, 0.0, long or diameter, diameter, 0.3, 0.0, 0.02)


def test_in_the_open_both_ways_round_are_passable() -> None:
    ways = ways_round(ROBOT, across(0.42, 0.06), (0.42, -0.15, 0.2), (0.42, 0.15, 0.2), Elbow.DOWN)
    assert ways == (True, True)


def test_a_move_that_passes_the_obstacle_or_goes_over_it_needs_no_way_round() -> None:
    obstacle = across(0.42, 0.06)
    assert ways_round(ROBOT, obstacle, (0.3, -0.15, 0.2), (0.3, 0.15, 0.2), Elbow.DOWN) is None
    high = obstacle.section().top + 0.01
    assert ways_round(ROBOT, obstacle, (0.42, -0.15, high), (0.42, 0.15, high), Elbow.DOWN) is None


@pytest.mark.parametrize(("past_the_hole", "passes"), [(0.0005, True), (-0.0005, False)])
def test_a_straight_move_through_the_hole_inside_the_inner_reach_is_out_of_the_limits(
    past_the_hole: float, passes: bool
) -> None:
    """A move along x = const at ``past_the_hole`` beyond the circle where theta2, LIMIT_ROOM
    inside its stop, holds the arm (just outside it: passable; just inside: not)."""
    inner, _ = reach_radii(
        RobotConfig(
            theta2_min=ROBOT.theta2_min + LIMIT_ROOM, theta2_max=ROBOT.theta2_max - LIMIT_ROOM
        )
    )
    x = inner + past_the_hole
    assert bool(straight_passable(SCALAR, ROBOT, (x, -0.3), (x, 0.3), 1.0)) is passes


def test_next_to_the_inner_reach_limit_only_the_outer_way_is_open() -> None:
    """Moving anticlockwise (+y) past an obstacle whose edge (grown by the pass margin) reaches
    over the circle where theta2 meets its stop: the way on the left (nearer the base) is
    closed."""
    diameter = 0.06
    radius = INNER + diameter / 2.0 + 0.02 + 0.015 - 0.002  # aim's edge 2 mm over it
    ways = ways_round(
        ROBOT,
        across(radius, diameter).grown(0.015),
        (radius, -0.15, 0.2),
        (radius, 0.15, 0.2),
        Elbow.DOWN,
    )
    assert ways == (False, True)


SLIDE, _ = reach_radii(
    RobotConfig(theta2_min=ROBOT.theta2_min + LIMIT_ROOM, theta2_max=ROBOT.theta2_max - LIMIT_ROOM)
)
"""The circle the arm slides round with theta2 LIMIT_ROOM inside its stop."""
SLIDE_START, SLIDE_GOAL = (0.1, -0.173, 0.2), (0.533, 0.077, 0.2)
"""A move across a radial obstacle from beside the hole inside the inner reach: the way
nearer the base cuts through the hole from the start to the obstacle's inner end."""


BEARING_AT_STOP = -0.662
"""rad the slide move is turned by where its slide meets theta1's stop, LIMIT_ROOM inside it
(found by turning it: the slide starts where the start's leg enters the circle)."""


def radial(inner_edge: float, bearing: float = 0.0) -> EllipticCylinder:
    """An obstacle along the ray at ``bearing`` whose inflated edge (the aim here) starts
    ``inner_edge`` beyond the slide circle and reaches past full reach: its outer way is
    closed."""
    centre = SLIDE + inner_edge + 0.24
    return EllipticCylinder(
        centre * math.cos(bearing), centre * math.sin(bearing), 0.44, 0.08, 0.3, bearing, 0.02
    )


def turned(point: tuple[float, float, float], bearing: float) -> tuple[float, float, float]:
    cos, sin = math.cos(bearing), math.sin(bearing)
    return (cos * point[0] - sin * point[1], sin * point[0] + cos * point[1], point[2])


@pytest.mark.parametrize(
    ("inner_edge", "ways"),
    [(0.0005, (True, False)), (0.01, (True, False)), (-0.003, (False, False))],
)
def test_a_way_through_the_hole_inside_the_inner_reach_slides_round_it(
    inner_edge: float, ways: tuple[bool, bool]
) -> None:
    """The way whose leg cuts the hole is open as the arm takes it: theta2 at its stop, round
    the slide circle, where that keeps outside the obstacle (its end just beyond the circle);
    an end over the circle closes it (the 24 points of the arc find it from about 1.5 mm
    over)."""
    obstacle = radial(inner_edge)
    assert ways_round(ROBOT, obstacle, SLIDE_START, SLIDE_GOAL, Elbow.DOWN) == ways


@pytest.mark.parametrize("mode", list(Mode))
def test_a_task_whose_way_slides_round_the_inner_reach_is_done(mode: Mode) -> None:
    """Just inside rule 6 at the slide's edge (the aim's end 0.5 mm beyond the slide circle):
    done, round the end nearer the base; 3 mm over it: refused, rule 6. Before the slide AO
    judged both ways closed here, kept to the outer side and ended for want of progress."""
    pass_margin = ControllerConfig().ao_pass_margin

    def task(inner_edge: float) -> Scenario:
        aim = radial(inner_edge)
        obstacle = dataclasses.replace(
            aim,
            long_diameter=aim.long_diameter - 2.0 * pass_margin,
            short_diameter=aim.short_diameter - 2.0 * pass_margin,
        )
        return Scenario(
            name="slide",
            waypoints=(Waypoint(0.0, *SLIDE_START), Waypoint(3.0, *SLIDE_GOAL)),
            obstacle=obstacle,
        )

    with pytest.raises(NoWayRoundError, match=r"waypoints\[0\.\.1\]: .*\(rule 6\)"):
        check_task(task(-0.003))
    accepted = task(0.0005)
    check_task(accepted)
    measures = simulate(accepted, mode).measures
    assert measures.outcome is RunOutcome.DONE
    assert measures.stops == 0
    assert max(measures.waypoint_miss) < 0.002


@pytest.mark.parametrize(
    ("past_the_stop", "ways"), [(-0.01, (True, False)), (0.01, (False, False))]
)
def test_a_way_that_slides_out_of_theta1s_limits_is_closed(
    past_the_stop: float, ways: tuple[bool, bool]
) -> None:
    """The same move turned towards theta1's stop at -150 degrees: turned by BEARING_AT_STOP
    its slide starts on the stop; ``past_the_stop`` rad farther the way is closed."""
    bearing = BEARING_AT_STOP - past_the_stop  # theta1_min lies clockwise
    assert (
        ways_round(
            ROBOT,
            radial(0.01, bearing),
            turned(SLIDE_START, bearing),
            turned(SLIDE_GOAL, bearing),
            Elbow.DOWN,
        )
        == ways
    )


def test_a_slide_that_would_pass_under_the_obstacle_is_closed() -> None:
    """``wide`` seed 4, 522, its second segment: the right way's leg from the obstacle's far
    end cuts through the hole, and the slide round it would pass under the obstacle, whose
    edge dips into the hole there. The leg's own points slid out were clear of it: judged by
    them alone the way was open, AO took it, and the arm stood at theta2's stop."""
    obstacle = EllipticCylinder(0.0874, 0.2909, 0.2551, 0.2126, 0.4064, 0.0944, 0.02)
    ways = ways_round(
        ROBOT,
        obstacle.grown(0.015),
        (-0.0751, 0.4646, 0.2131),
        (0.4473, -0.2648, 0.3682),
        Elbow.DOWN,
    )
    assert ways == (True, False)


def test_an_obstacle_across_the_whole_annulus_leaves_no_way_round() -> None:
    long = OUTER - INNER + 0.1
    ways = ways_round(
        ROBOT,
        across((INNER + OUTER) / 2.0, 0.06, long),
        ((INNER + OUTER) / 2.0, -0.15, 0.2),
        ((INNER + OUTER) / 2.0, 0.15, 0.2),
        Elbow.DOWN,
    )
    assert ways == (False, False)


def test_a_task_with_no_way_round_is_refused_naming_its_segment() -> None:
    middle = (INNER + OUTER) / 2.0
    task = Scenario(
        name="sealed",
        waypoints=(
            Waypoint(0.0, 0.3, -0.3, 0.2),
            Waypoint(2.0, middle, -0.15, 0.2),
            Waypoint(4.0, middle, 0.15, 0.2),
        ),
        obstacle=across(middle, 0.06, OUTER - INNER + 0.1),
    )
    with pytest.raises(NoWayRoundError, match=r"waypoints\[1\.\.2\]: no way round the obstacle"):
        check_plan(task)
    try:
        check_plan(task)
    except NoWayRoundError as error:
        assert reason_of(error) is Reason.NO_WAY_ROUND


@pytest.mark.parametrize("side", [1, -1])
def test_floats_and_arrays_agree(side: int) -> None:
    """The controller checks a way on floats, the study on arrays: the same answers, over
    obstacles from the inner reach limit outwards."""
    rng = np.random.default_rng(1)
    radii = rng.uniform(INNER + 0.04, INNER + 0.14, 60)
    obstacles = [across(radius, 0.06).grown(0.015).section() for radius in radii]
    starts = np.column_stack([radii, np.full(60, -0.2)]) + rng.uniform(-0.05, 0.05, (60, 2))
    goals = np.column_stack([radii, np.full(60, 0.2)]) + rng.uniform(-0.05, 0.05, (60, 2))
    scalar = [
        bool(passable(SCALAR, ROBOT, section, tuple(start), tuple(goal), side, 1.0))
        for section, start, goal in zip(obstacles, starts.tolist(), goals.tolist(), strict=True)
    ]
    sections = type(obstacles[0])(*(np.array(values) for values in zip(*obstacles, strict=True)))
    array = passable(
        ARRAY, ROBOT, sections, (starts[:, 0], starts[:, 1]), (goals[:, 0], goals[:, 1]), side, 1.0
    )
    assert array.tolist() == scalar
    if side == 1:  # the way nearer the base: open for the obstacles farther out only
        assert 0 < sum(scalar) < 60


@pytest.mark.parametrize("mode", list(Mode))
def test_an_obstacle_at_the_inner_reach_limit_is_passed_on_the_outer_side(mode: Mode) -> None:
    """The users' defect: an obstacle whose inflated edge touches the circle where theta2
    meets its stop. AO's side away from the nearer edge was the base's, where the arm cannot
    go; it slid along its stop into the obstacle. Now it goes round the outer side."""
    diameter = 0.08
    radius = INNER + diameter / 2.0 + 0.02  # the inflated edge on the inner limit
    task = Scenario(
        name="inner-limit",
        waypoints=(
            Waypoint(0.0, radius, -0.2, 0.2),
            Waypoint(2.0, radius, 0.2, 0.2),
            Waypoint(3.5, radius + 0.1, 0.25, 0.2),
        ),
        obstacle=across(radius, diameter),
    )
    check_plan(task)
    measures = simulate(task, mode).measures
    assert measures.collision_free
    assert measures.min_clearance > 0.01  # round the aim, not pinned against the stop
    assert max(measures.waypoint_miss) < 0.002
