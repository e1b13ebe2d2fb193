"""The control step: behaviours, the blend of eq. 30 and the joint limits."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from controller.behaviours import (
    ACROSS_BAND,
    AHEAD_SPEED_FRACTION,
    CRAWL_SPEED_MIN,
    PLANNED_REST_SPEED,
    REST_HEADING,
    REST_LINE_NEARER,
    STEER_LOOKAHEAD,
    TURN_LEFT,
    TURN_RIGHT,
    Tracking,
    across_heading,
    avoid_obstacle,
    backward_tracking,
    plan_tracking,
)
from controller.control_law import (
    PASSED,
    RATE_CHANGE,
    RATE_RAMP,
    TURN_ASIDE,
    TURN_KEEP,
    TURN_SHARE,
    WAITING_RATE,
    WAITING_REACH,
    ControlLaw,
    approach_limited,
    approach_pull,
    final_approach,
    height_lead,
    height_rate,
    rate_towards,
    reach_limited,
    turned_towards,
)
from controller.coordination import HEIGHT_FADE, WAY_PASSING_FULL, Coordination, weights
from controller.fuzzy import RuleBase
from controller.obstacle import ObstacleMeasurement, measure
from protocol.config import ControllerConfig, RobotConfig
from protocol.errors import ConfigError
from protocol.geometry import EllipticCylinder, wrap_angle
from protocol.kinematics import reach_radii
from protocol.ops import SCALAR
from protocol.scenario import Mode, Scenario, Waypoint, load_scenario
from sim.generator import generate_scenario_at
from sim.measures import WAYPOINT_TOLERANCE
from sim.simulation import simulate

CONFIG = ControllerConfig()
NO_REST = (0.0, 0.0, False)
"""PT's ``rest_ahead`` where the plan does not rest at the waypoint ahead."""
NOT_PASSED = (0.0, 0.0)
"""PT's ``past_waypoint`` before the TCP has passed the waypoint the plan heads for."""
_SECTION = EllipticCylinder(0.5, 0.0, 0.06, 0.06, 0.3, inflation=0.02).section()
NO_MIDWAY = (_SECTION, (0.5 + _SECTION.a, 0.0))
"""approach_pull's obstacle and a point midway on its boundary: the disc there covers
nothing."""


def test_tracking_on_the_plan_follows_it() -> None:
    command = plan_tracking(
        SCALAR, CONFIG, 0.0, (0.3, 0.0), (0.3, 0.0), (0.2, 0.0), (0.0, 0.0), NO_REST, NOT_PASSED
    )
    assert command.v == pytest.approx(0.2)
    assert command.omega == pytest.approx(0.0)


def test_tracking_ahead_of_the_plan_slows_down_instead_of_turning_round() -> None:
    command = plan_tracking(
        SCALAR, CONFIG, 0.0, (0.35, 0.0), (0.3, 0.0), (0.2, 0.0), (0.0, 0.0), NO_REST, NOT_PASSED
    )
    assert command.v == pytest.approx(AHEAD_SPEED_FRACTION * 0.2)  # crawls on, never stops
    assert command.omega == pytest.approx(0.0)


@pytest.mark.parametrize(
    ("short_of_rest", "along"),
    [
        (0.010, AHEAD_SPEED_FRACTION * 0.2),  # far from it: the crawl
        (0.001, CONFIG.position_gain * 0.001),  # just short: slowing into it
        (0.0, 0.0),  # on it: waits for the plan
    ],
)
def test_tracking_ahead_of_the_plan_crawls_no_further_than_where_the_plan_comes_to_rest(
    short_of_rest: float, along: float
) -> None:
    """The plan (at 0.3, 0.2 m/s along +x) comes to rest at the waypoint ahead: an arm 5 cm
    ahead of it crawls into the waypoint and waits there. Where the plan passes the waypoint
    without a rest, the crawl goes on."""
    arm = (0.35, 0.0)
    rest = (arm[0] + short_of_rest, 0.0)
    command = plan_tracking(
        SCALAR, CONFIG, 0.0, arm, (0.3, 0.0), (0.2, 0.0), (0.0, 0.0), (*rest, True), NOT_PASSED
    )
    assert command.v == pytest.approx(along)
    passing = plan_tracking(
        SCALAR, CONFIG, 0.0, arm, (0.3, 0.0), (0.2, 0.0), (0.0, 0.0), (*rest, False), NOT_PASSED
    )
    assert passing.v == pytest.approx(AHEAD_SPEED_FRACTION * 0.2)
    # 1 mm past it, its way points back at it (v 0 forwards: PT turns the arm, or backs it)
    past = plan_tracking(
        SCALAR,
        CONFIG,
        0.0,
        (rest[0] + 0.001, 0.0),
        (0.3, 0.0),
        (0.2, 0.0),
        (0.0, 0.0),
        (*rest, True),
        NOT_PASSED,
    )
    assert past.v == 0.0 and past.speed == pytest.approx(CONFIG.position_gain * 0.001)


@pytest.mark.parametrize(
    ("nearer", "share"),
    [
        (-0.001, 0.0),  # nearer the reference: its line
        (0.0, 0.0),
        (REST_LINE_NEARER / 2.0, 0.5),
        (REST_LINE_NEARER, 1.0),  # the waypoint's line alone from here on
        (REST_LINE_NEARER + 0.04, 1.0),
    ],
)
def test_tracking_nearer_the_waypoint_the_plan_rests_at_measures_its_way_across_from_there(
    nearer: float, share: float
) -> None:
    """The plan (at 0.3, 0.2 m/s along +x) rests at a waypoint 10 mm to the left of its line
    (it bends on to it); the arm, on the reference's line, 5 mm short of the waypoint along
    the plan and ``nearer`` nearer it than the reference. Its way across is measured from the
    waypoint's line in full from REST_LINE_NEARER nearer: from the reference's line alone,
    an arm come early crawled beside the waypoint (edge_obstacle seed 7,000,000, 484)."""
    short = 0.005
    arm = (0.3 + short + nearer, 0.0)
    rest = (arm[0] + short, 0.01, True)
    tracking = plan_tracking(
        SCALAR, CONFIG, 0.0, arm, (0.3, 0.0), (0.2, 0.0), (0.0, 0.0), rest, NOT_PASSED
    )
    crawl = min(AHEAD_SPEED_FRACTION * 0.2, CONFIG.position_gain * short)
    along = max(0.2 - CONFIG.position_gain * (arm[0] - 0.3), crawl)
    across = CONFIG.position_gain * share * 0.01
    assert tracking.error == pytest.approx(math.atan2(across, along))
    assert tracking.speed == pytest.approx(math.hypot(along, across))


@pytest.mark.parametrize(
    ("error", "share", "moving", "across"),
    [
        (0.0, 1.0, 0.0, 0.0),
        (math.asin(ACROSS_BAND), 1.0, 0.0, 0.0),  # the band's edge
        (math.asin(ACROSS_BAND + 0.02), 1.0, 0.0, 0.028 * (ACROSS_BAND + 0.02) * 0.01),
        (math.pi / 2.0, 1.0, 0.0, 0.01),  # 90 degrees off: all of it, up to the crawl
        (-math.pi / 2.0, 1.0, 0.0, -0.01),  # to the right
        (math.pi / 2.0, 0.5, 0.0, 0.005),  # PT's share of the blend
        (math.pi / 2.0, 1.0, 0.006, 0.008),  # what the speed along the heading lacks
        (math.pi / 2.0, 1.0, -0.006, 0.008),  # the same, backwards
        (math.pi / 2.0, 1.0, 0.01, 0.0),  # already as fast: nothing across
        (math.pi - math.asin(ACROSS_BAND), 1.0, 0.0, 0.0),  # a way behind: backwards instead
    ],
)
def test_the_tcp_goes_pt_way_across_a_heading_90_degrees_off_it_as_fast_as_it_lacks(
    error: float, share: float, moving: float, across: float
) -> None:
    """Where PT's way lies about 90 degrees off the heading, the unicycle's speed along it is
    all but nothing; the TCP goes across the heading what ``moving`` (the blend's speed
    along the heading) lacks of PT's share of its speed, up to the crawl (here 10 mm/s of
    PT's 30), from |sin| of the error ACROSS_BAND in (a smoothstep: at 0.1 of the way in,
    0.028 of it)."""
    tracking = Tracking(0.0, 0.0, 0.03, error, 0.0)
    assert across_heading(SCALAR, tracking, 0.01, share, moving) == pytest.approx(across, abs=1e-12)


@pytest.mark.parametrize(
    ("planned", "crawl"),
    [
        (
            CRAWL_SPEED_MIN / AHEAD_SPEED_FRACTION + 0.001,
            CRAWL_SPEED_MIN + AHEAD_SPEED_FRACTION * 0.001,
        ),
        (CRAWL_SPEED_MIN / AHEAD_SPEED_FRACTION - 0.001, CRAWL_SPEED_MIN),
        (CRAWL_SPEED_MIN + 0.0001, CRAWL_SPEED_MIN),
        (CRAWL_SPEED_MIN - 0.0001, CRAWL_SPEED_MIN - 0.0001),  # no faster than the plan
        (PLANNED_REST_SPEED + 0.0001, PLANNED_REST_SPEED + 0.0001),
    ],
)
def test_tracking_ahead_of_a_slow_plan_crawls_no_slower_than_a_plan_that_moves(
    planned: float, crawl: float
) -> None:
    """An arm 5 cm ahead crawls at a quarter of the plan's speed down to CRAWL_SPEED_MIN,
    and at that speed below it, or the plan's where that is the slower: a quarter of a plan
    slowing through a waypoint left an arm ahead of it below the stop speed (edge_obstacle
    seed 4, 426), and at 5 mm/s an arm handed back moving the other way reversed to the
    crawl below it (edge_obstacle seed 11,000,000, 790)."""
    command = plan_tracking(
        SCALAR,
        CONFIG,
        0.0,
        (0.35, 0.0),
        (0.3, 0.0),
        (planned, 0.0),
        (0.0, 0.0),
        NO_REST,
        NOT_PASSED,
    )
    assert command.v == pytest.approx(crawl)


@pytest.mark.parametrize("rate", [0.0001, 0.05, 0.5, 1.0])
def test_tracking_past_the_waypoint_crawls_at_a_share_of_the_plans_own_speed(rate: float) -> None:
    """The plan waited short of a waypoint the arm has now passed, and moves off at a rising
    rate: the arm, 5 cm ahead, crawls on at a share of the plan's own speed (0.2 m/s), not of
    the rate's share of it, even while that share is below the speed of a plan at rest.
    Before the waypoint is passed, at the rate's share; or, the plan at rest, PT aims back at
    the reference."""
    arm, planned = (0.35, 0.0), (0.2 * rate, 0.0)
    passed = plan_tracking(
        SCALAR, CONFIG, 0.0, arm, (0.3, 0.0), planned, (0.0, 0.0), NO_REST, (0.2, 0.0)
    )
    assert passed.v == pytest.approx(AHEAD_SPEED_FRACTION * 0.2)
    before = plan_tracking(
        SCALAR, CONFIG, 0.0, arm, (0.3, 0.0), planned, (0.0, 0.0), NO_REST, NOT_PASSED
    )
    if 0.2 * rate >= PLANNED_REST_SPEED:
        crawl = max(AHEAD_SPEED_FRACTION * 0.2 * rate, CRAWL_SPEED_MIN)
        assert before.v == pytest.approx(crawl)
    else:
        assert before.v == 0.0
        assert before.speed == pytest.approx(CONFIG.position_gain * 0.05 - 0.2 * rate)


@pytest.mark.parametrize("last", [0.0, 0.03, 0.12, 0.2])
def test_tracking_past_the_waypoint_does_not_brake_the_arm_below_its_last_speed(
    last: float,
) -> None:
    """Past the waypoint the plan heads for, an arm 5 cm ahead of a plan at 0.2 m/s goes on
    at the speed it was last sent at (up to the plan's, as the law passes it), or at the
    crawl where that is the faster: braked to the crawl where the plan turns back slowly
    through the waypoint, it wanted a way that swung round faster than its heading turned."""
    arm, planned = (0.35, 0.0), (0.2, 0.0)
    passed = plan_tracking(
        SCALAR, CONFIG, 0.0, arm, (0.3, 0.0), planned, (0.0, 0.0), NO_REST, (0.2, last)
    )
    assert passed.v == pytest.approx(max(last, AHEAD_SPEED_FRACTION * 0.2))
    assert passed.error == pytest.approx(0.0)


@pytest.mark.parametrize("planned", [0.004, 0.006])
def test_tracking_a_plan_coming_to_a_rest_keeps_its_speed_either_side_of_the_rest_speed(
    planned: float,
) -> None:
    """Either side of PLANNED_REST_SPEED an arm on its reference moves with the plan (it once
    aimed at the reference alone below it, and stood still while the plan moved on)."""
    assert 0.004 < PLANNED_REST_SPEED < 0.006  # the two cases sit either side of it
    on_plan = plan_tracking(
        SCALAR,
        CONFIG,
        math.pi / 2,
        (0.3, 0.0),
        (0.3, 0.0),
        (0.0, planned),
        (0.0, 0.0),
        NO_REST,
        NOT_PASSED,
    )
    assert on_plan.v == pytest.approx(planned)
    assert on_plan.omega == pytest.approx(0.0)
    behind = plan_tracking(
        SCALAR,
        CONFIG,
        math.pi / 2,
        (0.3, -0.001),
        (0.3, 0.0),
        (0.0, planned),
        (0.0, 0.0),
        NO_REST,
        NOT_PASSED,
    )
    assert behind.v == pytest.approx(planned + CONFIG.position_gain * 0.001)


@pytest.mark.parametrize("planned", [0.0, 0.003, 0.2])
def test_tracking_a_way_behind_the_heading_goes_there_backwards(planned: float) -> None:
    """PT wants to go the other way (at a rest where the plan turns back, or the arm ahead
    of a plan at rest): forwards it turns on the spot, v 0; backwards, with the heading turned
    half round, it goes that way at once, at the speed PT wants."""
    behind = (0.3 + 0.001, 0.0)  # the reference lies 1 mm behind an arm heading along +x
    tracking = plan_tracking(
        SCALAR, CONFIG, 0.0, behind, (0.3, 0.0), (-planned, 0.0), (0.0, 0.0), NO_REST, NOT_PASSED
    )
    assert tracking.v == 0.0
    assert tracking.speed == pytest.approx(planned + CONFIG.position_gain * 0.001)
    backward = backward_tracking(SCALAR, CONFIG, tracking)
    assert backward.v == pytest.approx(tracking.speed)  # along the heading turned to -x
    assert backward.omega == pytest.approx(0.0, abs=1e-9)
    aside = plan_tracking(
        SCALAR, CONFIG, 0.5, behind, (0.3, 0.0), (-planned, 0.0), (0.0, 0.0), NO_REST, NOT_PASSED
    )
    # heading 0.5 rad: its back, at 0.5 + pi, turns by -0.5 rad onto the way (-x)
    assert backward_tracking(SCALAR, CONFIG, aside).omega == pytest.approx(
        -CONFIG.heading_gain * 0.5
    )


def test_an_arm_still_at_a_rest_where_the_plan_turns_back_moves_off_with_it() -> None:
    """The plan comes to a rest at p_1 and turns straight back: the arm, heading the way it
    came, moved off backwards on the first tick the plan moved, not after a turn on the spot."""
    task = Scenario(
        name="there-and-back",
        waypoints=(
            Waypoint(0.0, 0.3, 0.0, 0.25),
            Waypoint(1.0, 0.4, 0.0, 0.25),
            Waypoint(2.0, 0.3, 0.0, 0.25),
        ),
        obstacle=None,
    )
    run = simulate(task, Mode.CONVENTIONAL)
    log = run.log
    leaving = np.flatnonzero((log["progress"] > 1.0) & (log["reference_speed"] > 0.001))[0]
    later = leaving + 5
    assert log["x"][later] < log["x"][leaving]  # already on its way back
    assert run.measures.stops == 0


def test_at_a_runs_start_the_heading_is_not_turned_round_for_micrometres() -> None:
    """At the first waypoint PT's way is set by an arm micrometres off its reference: turned
    round for it (below BACKWARD_SPEED), the heading swung half a turn and back, and AO,
    blended in a few ticks later, went the wrong way (fuzzy peak jerk 32 to 115 m/s^3)."""
    task = generate_scenario_at(0, 962)
    first, second = task.waypoints[0], task.waypoints[1]
    along = math.atan2(second.y - first.y, second.x - first.x)
    log = simulate(task, Mode.FUZZY).log
    assert max(abs(wrap_angle(heading - along)) for heading in log["heading"][:100]) < 0.2


@pytest.mark.parametrize("offset", [0.0005, -0.0005, 0.002, 0.01])
def test_tracking_ahead_of_the_plan_steers_back_onto_it_over_no_less_than_the_lookahead(
    offset: float,
) -> None:
    """An arm ahead crawls at AHEAD_SPEED_FRACTION of the plan's speed, and steering back
    onto the plan over the crawl's own reach (position_gain times the way across against the
    crawl: 0.5 mm at 5 mm/s) swung PT's way by 60-80 degrees with a fraction of a millimetre
    across (edge_obstacle seed 8,000,000, 511 and 61, the heading chasing it). It steers over
    no less than STEER_LOOKAHEAD; its speed is unchanged."""
    arm = (0.35, offset)
    tracking = plan_tracking(
        SCALAR, CONFIG, 0.0, arm, (0.3, 0.0), (0.02, 0.0), (0.0, 0.0), NO_REST, NOT_PASSED
    )
    crawl = max(AHEAD_SPEED_FRACTION * 0.02, CRAWL_SPEED_MIN)
    assert CONFIG.position_gain * STEER_LOOKAHEAD > crawl  # the lookahead is what steers
    assert tracking.error == pytest.approx(math.atan2(-offset, STEER_LOOKAHEAD))
    assert tracking.speed == pytest.approx(math.hypot(crawl, CONFIG.position_gain * offset))


def test_tracking_past_where_the_plan_rests_steers_back_over_the_lookahead_behind() -> None:
    """An arm 1 mm past the waypoint where the plan rests, and 0.5 mm beside the plan: its
    way points back at the waypoint, and the lookahead keeps it pointing back (a floor on the
    way along, taken forwards, drove an arm waiting there off along the plan at full speed)."""
    rest = (0.35, 0.0, True)
    tracking = plan_tracking(
        SCALAR, CONFIG, 0.0, (0.351, 0.0005), (0.3, 0.0), (0.2, 0.0), (0.0, 0.0), rest, NOT_PASSED
    )
    assert tracking.error == pytest.approx(math.atan2(-0.0005, -STEER_LOOKAHEAD))


@pytest.mark.parametrize(
    ("bearing", "rests_ahead"),
    [
        (0.0, True),  # straight ahead of the reference
        (math.acos(REST_HEADING) - 0.01, True),  # just inside
        (math.acos(REST_HEADING) + 0.01, False),  # just outside: off to the side
        (math.pi / 2.0, False),
    ],
)
def test_tracking_counts_a_rest_only_where_the_plan_heads_for_it(
    bearing: float, rests_ahead: bool
) -> None:
    """The waypoint the plan rests at, 30 mm from the reference at ``bearing`` off the plan's
    way, and the arm on the plan's line 2 mm past the waypoint's level: measured along the
    plan's way, an arm beside the reference was past a waypoint 28 mm to the side of it,
    turned back to its level and swung round (edge_obstacle seed 8,000,000, 61, the hard
    switch). PT measures the way to a rest only within REST_HEADING of the plan's way from
    the reference; elsewhere the arm crawls on as if the plan did not rest there."""
    reference, planned = (0.3, 0.0), (0.02, 0.0)
    rest = (0.3 + 0.03 * math.cos(bearing), 0.03 * math.sin(bearing))
    arm = (rest[0] + 0.002, 0.0)
    tracking = plan_tracking(
        SCALAR, CONFIG, 0.0, arm, reference, planned, (0.0, 0.0), (*rest, True), NOT_PASSED
    )
    no_rest = plan_tracking(
        SCALAR, CONFIG, 0.0, arm, reference, planned, (0.0, 0.0), NO_REST, NOT_PASSED
    )
    if rests_ahead:  # back to the waypoint's level, across to its line
        across = CONFIG.position_gain * rest[1]
        back = math.atan2(across, -CONFIG.position_gain * 0.002)
        assert wrap_angle(tracking.error - back) == pytest.approx(0.0, abs=1e-12)
    else:
        assert tracking == no_rest


def test_tracking_beside_the_plan_steers_back() -> None:
    left_of_plan = plan_tracking(
        SCALAR, CONFIG, 0.0, (0.3, 0.02), (0.3, 0.0), (0.2, 0.0), (0.0, 0.0), NO_REST, NOT_PASSED
    )
    assert left_of_plan.omega < 0.0  # turn right, back onto the path
    assert 0.0 < left_of_plan.v <= CONFIG.speed_max


@pytest.mark.parametrize("side", [TURN_LEFT, TURN_RIGHT])
def test_avoiding_turns_to_the_chosen_side_and_settles_on_the_edge(side: int) -> None:
    obstacle = EllipticCylinder(0.5, 0.0, 0.06, 0.06, 0.3, inflation=0.02)
    tcp = (0.3, 0.0, 0.2)
    measurement = measure(obstacle, tcp, (0.7, 0.0), CONFIG.sensing_range)
    aim = obstacle.grown(CONFIG.ao_pass_margin)

    def avoiding(heading: float) -> float:
        command, kept = avoid_obstacle(
            SCALAR,
            CONFIG,
            RobotConfig(),
            aim.section(),
            obstacle.section(),
            measurement,
            measurement.min_distance,
            side,
            heading,
            tcp[:2],
            (0.7, 0.0),
            1.0,
            False,
        )
        assert kept == side
        return command

    head_on = avoiding(0.0)
    assert math.copysign(1.0, head_on.omega) == side
    assert head_on.v > 0.0
    # Heading straight at the edge of the obstacle grown by the pass margin: no more turning.
    edges = aim.tangent_points(*tcp[:2])
    assert edges is not None
    edge = edges[0] if side == TURN_LEFT else edges[1]
    at_edge = math.atan2(edge[1] - tcp[1], edge[0] - tcp[0])
    settled = avoiding(at_edge)
    assert settled.omega == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize(
    ("goal", "side"),
    [((0.379, -0.059), TURN_LEFT), ((0.0, 0.2), TURN_RIGHT)],
)
def test_where_the_straight_way_runs_through_the_inner_hole_avoiding_takes_the_open_side(
    goal: tuple[float, float], side: int
) -> None:
    """An obstacle 40 cm long reaching in from past the arm's middle to near the inner reach
    (wide seed 2, 73): the straight way from the TCP to (0.379, -0.059) keeps clear of it
    through the hole inside the inner reach, where the arm cannot go, and the plan bends
    round past the obstacle. d_R a little over d_L chose the right, towards the inner reach,
    and the arm stood at theta2's stop; the joints now choose the left. To (0.0, 0.2) the
    straight way is open and d_L and d_R choose, as before."""
    obstacle = EllipticCylinder(0.036, 0.37, 0.375, 0.159, 0.41, yaw=1.8, inflation=0.02)
    tcp = (-0.263, 0.35, 0.215)
    measurement = measure(obstacle, tcp, goal, CONFIG.sensing_range)
    assert not measurement.blocked
    assert measurement.d_right > measurement.d_left
    heading = math.atan2(goal[1] - tcp[1], goal[0] - tcp[0])
    for check_again in (False, True):
        assert _side_chosen(obstacle, measurement, heading, tcp, goal, check_again) == side


@pytest.mark.parametrize(("gap", "side"), [(0.0065, TURN_LEFT), (0.0055, TURN_RIGHT)])
def test_past_an_obstacle_by_the_inner_hole_the_side_is_judged_round_the_obstacle_itself(
    gap: float, side: int
) -> None:
    """A move whose straight way runs through the hole inside the inner reach, past an
    obstacle whose inflated edge is ``gap`` outside the inner reach: d_L and d_R choose the
    left, between the obstacle and the base. The plan passes within AO's margin there, so the
    way is judged round the inflated obstacle, not AO's aim (which closes it at any gap
    below the margin): open from about 5.9 mm (LIMIT_ROOM, and the legs' and the arc's
    points), kept; closed below, and AO goes round the far end."""
    inner, _ = reach_radii(RobotConfig())
    obstacle = EllipticCylinder(inner + gap + 0.02 + 0.05, 0.0, 0.1, 0.06, 0.3, 0.0, 0.02)
    tcp, goal = (0.17, -0.12, 0.2), (0.17, 0.12)
    measurement = measure(obstacle, tcp, goal, CONFIG.sensing_range)
    assert not measurement.blocked
    assert measurement.d_left > measurement.d_right
    assert _side_chosen(obstacle, measurement, math.pi / 2.0, tcp, goal, False) == side


@pytest.mark.parametrize("check_again", [False, True])
def test_a_side_kept_is_checked_again_when_asked_and_left_where_its_way_is_closed(
    check_again: bool,
) -> None:
    """An obstacle reaching out past the outer reach, the TCP at one end and the goal at the
    other (outer seed 5,000,000, 518, as the plan moved on to waypoint 2): the way round the
    far side runs out of reach, the near side's is open. The far side, chosen on the way to
    the waypoint before, is kept until it is checked again, then left."""
    obstacle = EllipticCylinder(0.0839, -0.567, 0.0466, 0.0277, 0.4233, 2.0086, 0.02)
    tcp, goal = (-0.074, -0.5854, 0.296), (0.1601, -0.5705)
    measurement = measure(obstacle, tcp, goal, CONFIG.sensing_range)
    assert measurement.blocked
    heading = math.atan2(goal[1] - tcp[1], goal[0] - tcp[0])
    # TURN_RIGHT: round the far side, away from the base.
    side = _side_chosen(obstacle, measurement, heading, tcp, goal, check_again, TURN_RIGHT)
    assert side == (TURN_LEFT if check_again else TURN_RIGHT)


@pytest.mark.parametrize("kept", [TURN_RIGHT, TURN_LEFT])
def test_inside_aos_margin_a_side_kept_is_judged_round_the_obstacle_itself(kept: int) -> None:
    """The corner between full reach and an obstacle reaching in from beyond it, the TCP 1 mm
    outside the inflated obstacle and the goal back round its near side (edge_obstacle seed
    8,000,000, 805): from inside AO's margin no way round the margin is open, and the side
    AO had taken, round the far end past full reach, was kept while the arm stood. Judged
    round the inflated obstacle itself, the near side is open and the far side closed."""
    obstacle = EllipticCylinder(0.4706, 0.2529, 0.1254, 0.0452, 0.413, 0.0957, 0.02)
    tcp, goal = (0.5486, 0.2428, 0.2), (0.4643, 0.2017)
    measurement = measure(obstacle, tcp, goal, CONFIG.sensing_range)
    assert measurement.blocked
    heading = math.radians(46.0)  # into the corner
    assert _side_chosen(obstacle, measurement, heading, tcp, goal, True, kept) == TURN_LEFT


def _side_chosen(
    obstacle: EllipticCylinder,
    measurement: ObstacleMeasurement,
    heading: float,
    tcp: tuple[float, float, float],
    goal: tuple[float, float],
    check_again: bool,
    kept: int = 0,
) -> float:
    """The side AO takes, its elbow down, round ``obstacle`` grown by the pass margin:
    afresh, or with the side ``kept`` from before."""
    _, chosen = avoid_obstacle(
        SCALAR,
        CONFIG,
        RobotConfig(),
        obstacle.grown(CONFIG.ao_pass_margin).section(),
        obstacle.section(),
        measurement,
        measurement.min_distance,
        kept,
        heading,
        tcp[:2],
        goal,
        1.0,
        check_again,
    )
    return chosen


def test_conventional_switch_is_all_or_nothing() -> None:
    obstacle = EllipticCylinder(0.5, 0.0, 0.06, 0.06, 0.3, inflation=0.02)
    coordination = Coordination.of(sensing_range=0.5, switch_distance=0.05)

    def conventional(measurement: ObstacleMeasurement) -> tuple[float, float]:
        below_top = obstacle.section().top - 0.2
        return weights(
            SCALAR, coordination, False, measurement, measurement.min_distance, 0.0, below_top
        )

    far = measure(obstacle, (0.3, 0.0, 0.2), (0.7, 0.0), 0.5)
    near = measure(obstacle, (0.44, 0.0, 0.2), (0.7, 0.0), 0.5)
    behind = measure(obstacle, (0.56, 0.0, 0.2), (0.7, 0.0), 0.5)
    assert conventional(far) == (1.0, 0.0)
    assert conventional(near) == (0.0, 1.0)
    assert conventional(behind) == (1.0, 0.0)


def test_fuzzy_avoidance_fades_out_below_the_obstacles_top_not_at_it() -> None:
    """An arm rising over a low obstacle: k_C from full HEIGHT_FADE below the top to none at
    it, where DM stops seeing the obstacle (it used to drop from 1 to 0 in one tick)."""
    obstacle = EllipticCylinder(0.5, 0.0, 0.06, 0.06, 0.3, inflation=0.02)
    coordination = Coordination.of(sensing_range=0.5, switch_distance=0.05)
    top = obstacle.section().top
    near = measure(obstacle, (0.44, 0.0, 0.2), (0.7, 0.0), 0.5)

    def k_c(below_top: float) -> float:
        return weights(SCALAR, coordination, True, near, near.min_distance, 0.0, below_top)[1]

    full = k_c(HEIGHT_FADE)
    assert full > 0.5 and k_c(1.0) == full
    fading = [k_c(HEIGHT_FADE * share) for share in (0.75, 0.5, 0.25, 0.0)]
    assert full > fading[0] > fading[1] > fading[2] > fading[3] == 0.0
    above = measure(obstacle, (0.44, 0.0, top + 0.001), (0.7, 0.0), 0.5)
    assert weights(SCALAR, coordination, True, above, above.min_distance, 0.0, -0.001)[1] == 0.0


def test_fuzzy_avoidance_counts_where_the_way_passes_near_not_where_it_keeps_clear() -> None:
    """k_C in full where the straight way to p_j passes within WAY_PASSING_FULL of the
    obstacle, none where it passes as far as the switch distance, falling in between (AO drew
    arms 20 mm off a plan that passed 55 mm away, where the hard switch never switches)."""
    obstacle = EllipticCylinder(0.5, 0.0, 0.06, 0.06, 0.3, inflation=0.02)
    coordination = Coordination.of(sensing_range=0.5, switch_distance=0.05)
    near = measure(obstacle, (0.44, 0.0, 0.2), (0.7, 0.0), 0.5)

    def k_c(passing: float) -> float:
        seen = near._replace(passing=passing)
        return weights(SCALAR, coordination, True, seen, seen.min_distance, 0.0, 1.0)[1]

    full = k_c(0.0)
    assert full > 0.5 and k_c(WAY_PASSING_FULL) == full
    assert k_c(WAY_PASSING_FULL + 0.0005) < full
    assert k_c(0.05 - 0.0005) > 0.0 and k_c(0.05) == 0.0 == k_c(0.2)
    between = [
        k_c(WAY_PASSING_FULL + share * (0.05 - WAY_PASSING_FULL)) for share in (0.25, 0.5, 0.75)
    ]
    assert full > between[0] > between[1] > between[2] > 0.0


@pytest.mark.parametrize("mode", list(Mode))
def test_commands_respect_joint_speed_and_acceleration_limits(mode: Mode) -> None:
    run = simulate(load_scenario("reference"), mode)
    robot, period = run.scenario.robot, run.scenario.controller.period
    commands = run.log.columns("command_theta1", "command_theta2", "command_d3")
    speed = np.array(robot.speed_limits)
    step = np.array(robot.accel_limits) * period
    assert np.all(np.abs(commands) <= speed * (1 + 1e-12))
    assert np.all(np.abs(np.diff(commands, axis=0)) <= step * (1 + 1e-9))


def test_controller_config_names_bad_values() -> None:
    with pytest.raises(ConfigError) as error:
        ControllerConfig(rate_hz=5000.0)
    assert error.value.field == "controller.rate_hz"
    with pytest.raises(ConfigError) as error:
        ControllerConfig(heading_gain=math.nan)
    assert error.value.field == "controller.heading_gain"


def test_the_plan_runs_on_time_while_the_arm_keeps_up() -> None:
    log = simulate(load_scenario("no_obstacle")).log
    assert np.array_equal(log["progress"], log["t"])


def test_the_plan_waits_at_a_waypoint_for_an_arm_held_off_by_a_detour() -> None:
    # long_wall: rounding the wall, the arm is still far from the waypoint after it when the
    # plan reaches that waypoint's time (without waiting it passed 13.3 mm away).
    run = simulate(load_scenario("long_wall"))
    lost = run.log["t"][-1] - run.log["progress"][-1]
    assert lost > 0.1
    assert run.measures.max_waypoint_miss <= WAYPOINT_TOLERANCE
    assert run.measures.stops == 0
    assert run.measures.collision_free


def test_the_plans_rate_changes_gradually() -> None:
    run = simulate(load_scenario("long_wall"))
    period = run.scenario.controller.period
    rate = np.diff(run.log["progress"]) / period
    assert rate.min() < 0.5
    assert np.all((rate >= 0.0) & (rate <= 1.0 + 1e-12))
    assert np.abs(np.diff(rate)).max() <= period / RATE_CHANGE + 1e-9


def test_the_plans_rate_moves_off_from_a_wait_without_a_step_in_its_slope() -> None:
    """Up, the rate's slope ramps (by at most 1/RATE_CHANGE per RATE_RAMP), so that the
    reference's acceleration does too, and the rate lands on 1 without passing it; down, it
    goes at once, 1 to 0 in RATE_CHANGE, so that the plan waits where the gate closes."""
    period = 0.002
    step = period / (RATE_CHANGE * RATE_RAMP)
    rate, slope = 0.0, 0.0
    slopes = [slope]
    while not (rate == 1.0 and slope == 0.0):
        rate, slope = rate_towards(SCALAR, period, rate, slope, 1.0)
        assert 0.0 <= rate <= 1.0
        slopes.append(slope)
    assert np.abs(np.diff(slopes)).max() <= step + 1e-9
    assert max(slopes) == pytest.approx(1.0 / RATE_CHANGE)
    assert len(slopes) * period < RATE_CHANGE + RATE_RAMP + 3 * period
    rate, ticks = 1.0, 0
    while rate > 0.0:
        rate, slope = rate_towards(SCALAR, period, rate, slope, 0.0)
        ticks += 1
    assert ticks == round(RATE_CHANGE / period)
    # Falling at full slope when the plan may move on again: the fall stops at once.
    rate, slope = rate_towards(SCALAR, period, 0.5, 0.0, 0.0)
    assert slope == -1.0 / RATE_CHANGE
    rate, slope = rate_towards(SCALAR, period, rate, slope, 1.0)
    assert 0.0 <= slope <= step + 1e-9 and rate >= 0.5 - period / RATE_CHANGE


def test_the_plan_stands_still_while_the_node_holds() -> None:
    scenario = load_scenario("long_wall")
    law = ControlLaw.for_scenario(scenario)
    joints = scenario.initial_joints()
    for tick in range(200):
        law.step(tick * scenario.controller.period, joints)
    held = law.progress
    law.step(199 * scenario.controller.period, joints)  # a hold: the plan's clock stopped
    assert law.progress == held


def assert_cut_to(
    limit: Callable[[float, float], tuple[float, float]], normal: float, allowed: float
) -> None:
    """``limit`` keeps at most ``allowed`` of the velocity along the unit vector at angle
    ``normal``, and the rest of it (the part across it, and any negative part along it)."""
    out_x, out_y = math.cos(normal), math.sin(normal)
    along_x, along_y = -out_y, out_x
    for towards, along in ((0.1, 0.0), (0.1, 0.05), (0.1, -0.2), (-0.1, 0.05), (0.0, 0.1)):
        limited_x, limited_y = limit(
            towards * out_x + along * along_x, towards * out_y + along * along_y
        )
        assert limited_x * out_x + limited_y * out_y == pytest.approx(min(towards, allowed))
        assert limited_x * along_x + limited_y * along_y == pytest.approx(along)


def _off_the_long_end(clearance: float) -> tuple[ObstacleMeasurement, float]:
    """The reference scenario's obstacle measured from a TCP ``clearance`` off its long end,
    and the angle pointing from there into it."""
    obstacle = load_scenario("reference").obstacle
    assert obstacle is not None
    out_x, out_y = math.cos(obstacle.yaw), math.sin(obstacle.yaw)  # outward, off the long end
    reach = obstacle.semi_axes[0] + clearance
    tcp = (obstacle.x + reach * out_x, obstacle.y + reach * out_y, obstacle.height / 2.0)
    measurement = measure(obstacle, tcp, (0.0, 0.0), CONFIG.sensing_range, math.pi)
    assert measurement.clearance == pytest.approx(clearance)
    return measurement, obstacle.yaw + math.pi


@pytest.mark.parametrize(
    "clearance", [0.004, CONFIG.safety_buffer + 0.0005, CONFIG.safety_buffer, 0.0005, -0.003]
)
def test_the_tcp_moves_towards_the_margin_no_faster_than_its_clearance_allows(
    clearance: float,
) -> None:
    """Towards the margin at ``approach_rate`` times the clearance less the safety filter's
    buffer, and not at all from the buffer in, where the filter lets nothing in either."""
    measurement, towards_it = _off_the_long_end(clearance)
    assert_cut_to(
        lambda vx, vy: approach_limited(SCALAR, CONFIG, vx, vy, measurement, (0.0, 0.0)),
        towards_it,
        CONFIG.approach_rate * max(clearance - CONFIG.safety_buffer, 0.0),
    )


SLIDE = AHEAD_SPEED_FRACTION * 0.2
"""The slide along the obstacle of a plan going along it at 0.2 m/s."""


@pytest.mark.parametrize(
    ("towards", "along", "planned", "along_after"),
    [
        (0.1, 0.0, (0.2, 0.0), SLIDE),  # straight in: slides the plan's way
        (0.1, 0.0, (-0.2, 0.0), -SLIDE),  # the other way along, with the plan
        (0.1, 0.01, (0.2, 0.0), SLIDE),  # up to the plan's share, not beyond
        (0.1, 0.06, (0.2, 0.0), 0.06),  # already faster that way: left alone
        (0.1, -0.03, (0.2, 0.0), SLIDE),  # against the plan: turned its way
        (0.02, 0.0, (0.2, 0.0), 0.02 - CONFIG.approach_rate * 0.003),  # no more than is cut
        (0.01, 0.0, (0.2, 0.0), 0.0),  # nothing cut, nothing slid
        (0.1, 0.0, (0.01, 0.0), CRAWL_SPEED_MIN),  # a slow plan: the crawl's floor
        (0.1, 0.0, (SLIDE / 2.0, math.sqrt(0.04 - SLIDE**2 / 4.0)), SLIDE / 2.0),  # half in
        (0.1, -0.03, (0.0, 0.2), -0.03),  # a plan heading straight in: no way along
    ],
)
def test_what_the_approach_limit_cuts_slides_the_arm_the_way_the_plan_goes_along_the_obstacle(
    towards: float, along: float, planned: tuple[float, float], along_after: float
) -> None:
    """Edge_obstacle seed 4, 431: the hard switch handed PT an arm 1 mm from the margin,
    whose way back to a plan bending through the margin pointed straight into it; with what
    moved it in cut, it stood while the plan moved on. What is cut now moves it along the
    obstacle the way the plan goes (``planned``: along the obstacle, into it), at PT's crawl:
    AHEAD_SPEED_FRACTION of the plan's speed, no slower than CRAWL_SPEED_MIN; in part
    where the plan goes along it at less than that fraction of its speed, the share it does
    (half, here)."""
    measurement, towards_it = _off_the_long_end(0.004)  # 3 mm outside the buffer
    in_x, in_y = math.cos(towards_it), math.sin(towards_it)
    along_x, along_y = -in_y, in_x
    vx, vy = approach_limited(
        SCALAR,
        CONFIG,
        towards * in_x + along * along_x,
        towards * in_y + along * along_y,
        measurement,
        (planned[0] * along_x + planned[1] * in_x, planned[0] * along_y + planned[1] * in_y),
    )
    allowed = CONFIG.approach_rate * (0.004 - CONFIG.safety_buffer)
    assert vx * in_x + vy * in_y == pytest.approx(min(towards, allowed))
    assert vx * along_x + vy * along_y == pytest.approx(along_after)


@pytest.mark.parametrize("gap", [0.004, 0.0005, 0.0])
def test_the_tcp_moves_outwards_no_faster_than_its_distance_from_full_reach_allows(
    gap: float,
) -> None:
    scenario = load_scenario("reference")
    full_reach = scenario.robot.a1 + scenario.robot.a2
    bearing = 0.7
    tcp = ((full_reach - gap) * math.cos(bearing), (full_reach - gap) * math.sin(bearing), 0.2)
    assert_cut_to(
        lambda vx, vy: reach_limited(
            SCALAR, CONFIG.reach_rate, full_reach, vx, vy, tcp, (0.0, 0.0)
        ),
        bearing,
        CONFIG.reach_rate * gap,
    )


@pytest.mark.parametrize(
    ("outwards", "along", "planned", "along_after"),
    [
        (0.1, 0.0, (0.2, 0.0), SLIDE),  # straight out: slides the plan's way round
        (0.1, 0.0, (-0.2, 0.0), -SLIDE),  # the other way round, with the plan
        (0.1, -0.03, (0.2, 0.0), SLIDE),  # against the plan: turned its way
        (0.1, 0.06, (0.2, 0.0), 0.06),  # already faster that way: left alone
        (0.02, 0.0, (0.2, 0.0), 0.02 - CONFIG.reach_rate * 0.001),  # no more than is cut
        (0.1, -0.03, (0.0, 0.2), -0.03),  # a plan heading straight out: no way round
    ],
)
def test_what_the_reach_limit_cuts_slides_the_arm_round_the_reach_circle_the_way_the_plan_goes(
    outwards: float, along: float, planned: tuple[float, float], along_after: float
) -> None:
    """Edge_obstacle seed 8,000,000, 805: AO's way round an obstacle reaching in from beyond
    full reach, tilted outwards, was cut to the reach circle's way into the corner with the
    obstacle, where the arm stood. What the reach limit cuts slides the arm round the reach
    circle the way the plan goes (``planned``: round the circle, outwards), as the approach
    limit's does along the obstacle."""
    full_reach = RobotConfig().a1 + RobotConfig().a2
    bearing, gap = 0.7, 0.001
    out_x, out_y = math.cos(bearing), math.sin(bearing)
    round_x, round_y = -out_y, out_x
    tcp = ((full_reach - gap) * out_x, (full_reach - gap) * out_y, 0.2)
    vx, vy = reach_limited(
        SCALAR,
        CONFIG.reach_rate,
        full_reach,
        outwards * out_x + along * round_x,
        outwards * out_y + along * round_y,
        tcp,
        (planned[0] * round_x + planned[1] * out_x, planned[0] * round_y + planned[1] * out_y),
    )
    assert vx * out_x + vy * out_y == pytest.approx(min(outwards, CONFIG.reach_rate * gap))
    assert vx * round_x + vy * round_y == pytest.approx(along_after)


def test_the_height_leads_by_the_share_of_the_way_to_the_waypoint_an_arm_ahead_has_come() -> None:

    def lead(ahead: bool, to_next: float, reference_to_next: float) -> float:
        return float(height_lead(SCALAR, ahead, to_next, reference_to_next))

    reference_to_next = 0.04  # the reference 40 mm short of p_j
    assert lead(True, 0.04, reference_to_next) == 0.0  # with it, or beside the way as far
    assert lead(True, 0.035, reference_to_next) == 0.0  # 5 mm ahead: not yet
    assert lead(True, 0.0, reference_to_next) == pytest.approx(1.0)
    assert lead(True, 0.02, reference_to_next) == pytest.approx(0.5)
    assert 0.0 < lead(True, 0.025, reference_to_next) < 15.0 / 40.0
    # Heading for p_j-1, not yet passed: the lead is for p_j only.
    assert lead(False, 0.0, reference_to_next) == 0.0
    # Near p_j it leads from a few millimetres ahead: 1 mm from it, the reference 5 mm short.
    assert lead(True, 0.001, 0.005) == pytest.approx(0.8)
    assert lead(True, 0.009, 0.013) == 0.0  # 4 mm ahead, but 9 mm from p_j: not yet
    assert lead(True, 0.001, 0.002) == 0.0  # 1 mm ahead: not at all


def _come_onto_waypoint(
    law: ControlLaw, index: int, along: float, across: float
) -> tuple[float, float, list[float]]:
    """Move a point that goes at the final approach's velocity towards waypoint ``index``
    from ``along`` past it on the plan's way out and ``across`` to its left, until it is
    within PASSED of it: its velocity then (along and across the plan, m/s) and how far it
    was from the waypoint at each step. Never faster than straight at it."""
    stage = law.stages[index - 1]  # the segment to waypoint index
    out_x, out_y = stage.leaving
    point = stage.point
    x = point[0] + along * out_x - across * out_y
    y = point[1] + along * out_y + across * out_x
    distances = []
    for _ in range(5000):
        distance = math.hypot(point[0] - x, point[1] - y)
        vx, vy, _ = final_approach(
            SCALAR,
            CONFIG.position_gain,
            point,
            stage.leaving,
            distance,
            (x, y, point[2]),
            stage.loop_radius,
        )
        distances.append(distance)
        assert math.hypot(vx, vy) <= CONFIG.position_gain * distance * (1.0 + 1e-12)
        if distance <= PASSED:
            return vx * out_x + vy * out_y, out_x * vy - out_y * vx, distances
        x, y = x + vx * CONFIG.period, y + vy * CONFIG.period
    raise AssertionError("never came onto the waypoint")


@pytest.mark.parametrize(
    ("along", "across"), [(0.005, 0.0), (0.004, -0.001), (0.003, 0.002), (0.008, -0.003)]
)
def test_an_arm_past_the_waypoint_is_looped_round_not_brought_back_against_the_plan(
    along: float, across: float
) -> None:
    # Straight back, it would come onto the waypoint against the plan and have to turn round
    # on it when the plan moves on (gen-11-4651, gen-13-2173: stops).
    law = ControlLaw.for_scenario(load_scenario("reference"))
    speed_along, speed_across, distances = _come_onto_waypoint(law, 1, along, across)
    # Across the plan (within about 10 degrees), not against it.
    assert speed_along > -0.2 * abs(speed_across)
    assert min(distances[:-1]) > PASSED
    assert max(distances) > math.hypot(along, across)  # round the waypoint, not at it


def test_the_handover_to_the_loop_turns_the_way_and_keeps_the_speed() -> None:
    """Across the handover from the straight way to the loop the arm goes at the gain times
    its distance: the two ways point apart there (on the far side of the loop's circle), and
    added as vectors they all but cancelled (edge_reach-0-375: 5 of 37 mm/s, a stop)."""
    point, leaving, radius = (0.0, 0.0, 0.2), (1.0, 0.0), 0.003
    away = 0.0037
    shares = []
    for against in np.linspace(0.0, 0.5, 11):  # the cosine of the angle against the way out
        tcp = (against * away, math.sqrt(1.0 - against**2) * away, 0.2)
        vx, vy, share = final_approach(
            SCALAR, CONFIG.position_gain, point, leaving, away, tcp, radius
        )
        shares.append(share)
        assert math.hypot(vx, vy) == pytest.approx(CONFIG.position_gain * away)
    assert shares[0] == 0.0 and shares[-1] == 1.0 and 0.0 < shares[5] < 1.0


@pytest.mark.parametrize(
    ("apart", "last_aside", "turned_left"),
    [
        (math.pi - 0.01, 0.5, True),  # all but opposite, the short way right: left, as last
        (math.pi - 0.01, -0.5, False),  # the short way right, as last
        (TURN_KEEP + 0.01, 0.5, True),  # just inside TURN_KEEP: round last's side
        (TURN_KEEP - 0.01, 0.5, False),  # just outside it: the short way
        (math.pi - 0.01, TURN_ASIDE + 0.01, True),  # last just aside: its side
        (math.pi - 0.01, TURN_ASIDE - 0.01, False),  # all but along: the short way
    ],
)
def test_the_way_turns_round_the_side_the_arm_last_moved_to_where_the_two_point_opposite(
    apart: float, last_aside: float, turned_left: bool
) -> None:
    """PT's way on and the final approach's way back all but opposite (``apart``, the way back
    just right of straight back): the short way round changed side from one tick to the next,
    and the arm's way flipped with it through a stop (user seed 8,000,000, 999, the hard
    switch). From TURN_KEEP apart it turns round the side the last commanded velocity lies
    on, where it lies to a side (TURN_ASIDE): all but along the way on, a rounding's side
    turned the way against the two added (edge_obstacle seed 6,000,000, 931)."""
    on = (0.05, 0.0)
    back = (0.04 * math.cos(-apart), 0.04 * math.sin(-apart))
    last = (0.03 * math.sqrt(1.0 - last_aside**2), 0.03 * last_aside)  # |sin| last_aside
    _, vy = turned_towards(SCALAR, on, back, 0.5, last)
    assert (vy > 0.0) is turned_left
    added_y = 0.5 * back[1]
    assert abs(vy - added_y) > 0.5 * TURN_SHARE * 0.045 * math.sin(apart / 2.0)  # turned


def test_the_final_approach_taking_over_from_a_way_pointing_back_turns_it_and_keeps_speed() -> None:
    """An arm that went by a waypoint a few millimetres beside it: PT's way on and the final
    approach's way back point apart, and added as vectors they all but cancelled halfway (1
    of 66 mm/s, a stop: edge_reach seed 2, 38). There the way now turns, for TURN_SHARE of it;
    within 90 degrees the two are still added, to the bit."""
    on, back = (0.066, 0.0), (-0.04, -0.004)
    added = (0.5 * (on[0] + back[0]), 0.5 * (on[1] + back[1]))
    vx, vy = turned_towards(SCALAR, on, back, 0.5, on)
    mean_speed = 0.5 * (math.hypot(*on) + math.hypot(*back))
    assert math.hypot(*added) < TURN_SHARE * mean_speed <= math.hypot(vx, vy)
    assert vy < added[1] - 0.5 * TURN_SHARE * mean_speed  # turned the short way round
    for share in (0.0, 1.0):  # each end is itself
        assert turned_towards(SCALAR, on, back, share, on) == pytest.approx(
            on if share == 0.0 else back, abs=1e-15
        )
    # Within 90 degrees, and where either is nothing: added.
    assert turned_towards(SCALAR, (0.05, 0.0), (0.0001, 0.03), 0.3, (0.0, 0.0)) == (
        0.05 + 0.3 * (0.0001 - 0.05),
        0.0 + 0.3 * (0.03 - 0.0),
    )
    assert turned_towards(SCALAR, (0.0, 0.0), (-0.02, 0.01), 0.25, (0.0, 0.0)) == (
        0.0 + 0.25 * (-0.02 - 0.0),
        0.0 + 0.25 * (0.01 - 0.0),
    )


def test_an_arm_short_of_the_waypoint_is_brought_straight_onto_it() -> None:
    law = ControlLaw.for_scenario(load_scenario("reference"))
    speed_along, speed_across, distances = _come_onto_waypoint(law, 1, -0.004, 0.002)
    assert speed_across == pytest.approx(-0.5 * speed_along)  # on the straight line in
    assert distances == sorted(distances, reverse=True)
    # The last waypoint, where the plan stops, has no way out: straight from any side.
    last = law.stages[-1]  # the rest at the last waypoint
    assert last.leaving == (0.0, 0.0)
    point = last.point
    tcp = (point[0] + 0.004, point[1] - 0.001, point[2])
    approach = final_approach(
        SCALAR,
        CONFIG.position_gain,
        point,
        last.leaving,
        math.hypot(0.004, 0.001),
        tcp,
        last.loop_radius,
    )
    assert approach == pytest.approx(
        (CONFIG.position_gain * -0.004, CONFIG.position_gain * 0.001, 0.0)
    )


def test_final_approach_reaches_past_the_free_room_where_the_plan_waits_and_way_is_clear() -> None:
    """An arm 10 mm from a waypoint 8 mm from the obstacle (outside its free room): where the
    discs the obstacle leaves free round the two cover the straight way, the final approach
    takes over once the plan waits; not while the plan runs on, nor where the discs leave a
    gap, nor from beyond WAITING_REACH."""
    room = clear_way = 0.008
    outside_room = 0.0  # _depth of an arm outside the free room
    near = WAITING_REACH[0]

    def pull(rate: float, away: float, clearance: float) -> float:
        return float(
            approach_pull(
                SCALAR, rate, outside_room, away, clearance, room, clear_way, 0.0, *NO_MIDWAY
            )
        )

    assert pull(0.0, near, 0.012) == pytest.approx(1.0)  # 12 + 8 - 10 >= clear_way: in full
    assert 0.0 < pull(0.0, near, 0.005) < 1.0  # covered by 3 mm: in part
    assert pull(0.0, near, 0.0019) == 0.0  # 1.9 + 8 < 10: a gap the straight way could cross
    assert pull(WAITING_RATE, near, 0.012) == 0.0  # the plan runs on: PT's, not the approach's
    assert 0.0 < pull(0.0, (near + WAITING_REACH[1]) / 2, 0.05) < 1.0
    assert pull(0.0, WAITING_REACH[1], 0.05) == 0.0  # from farther: PT brings it nearer first
    # In the free room the approach acts as far as the plan waits, clear way or not.
    in_room = approach_pull(SCALAR, 0.25, 1.0, 0.001, 0.0, room, clear_way, 0.0, *NO_MIDWAY)
    assert in_room == pytest.approx(0.75)


def test_final_approach_takes_the_way_back_along_the_obstacle_the_disc_midway_covers() -> None:
    """An arm carried 15 mm past a waypoint 8 mm from the obstacle, 7 mm from it
    (``edge_obstacle`` seed 5,000,000, 639 fuzzy): the discs round the two leave the middle
    of the way back uncovered, but the obstacle is as far from the middle as from its ends,
    and the final approach takes over; not where the middle is as near the obstacle as the
    two discs leave it (a way that could cross the obstacle)."""
    obstacle = EllipticCylinder(0.5, 0.0, 0.06, 0.06, 0.3, inflation=0.02).section()
    edge = 0.5 + obstacle.a  # x of the inflated boundary, on the local x axis
    room = clear_way = 0.008
    away, clearance = 0.015, 0.007

    def pull(midway_clearance: float) -> float:
        midway = (edge + midway_clearance, 0.0)
        return float(
            approach_pull(
                SCALAR, 0.0, 0.0, away, clearance, room, clear_way, away, obstacle, midway
            )
        )

    assert clearance + room - away == pytest.approx(0.0)  # the two discs just meet
    assert pull(0.0085) == pytest.approx(1.0)  # 7 + 8.5 - 7.5 >= clear_way: in full
    assert 0.0 < pull(0.002) < 1.0  # covered by 1.5 mm: in part
    assert pull(0.0004) == 0.0  # 7 + 0.4 < 7.5, half the way: a gap the way could cross


def test_final_approach_takes_over_past_the_waited_waypoint_along_the_plans_line() -> None:
    """An arm AO brought out 50 mm past the waypoint the plan waits for, along the plan's way
    (PT sees it ahead of the reference and would crawl on, away from the waypoint): the
    final approach takes over however far, on the plan's line and up to WAITING_REACH[0] off
    it, in part farther off, not from WAITING_REACH[1] off it (an arm going round the
    obstacle), nor short of the waypoint (a lagging arm, which PT brings nearer first); and
    the pull does not jump as the arm comes past the waypoint."""
    room = clear_way = 0.008
    low, high = WAITING_REACH
    far = 0.05

    def pull(off: float, beyond: float) -> float:
        away = math.hypot(off, beyond)
        return float(
            approach_pull(SCALAR, 0.0, 0.0, away, 0.1, room, clear_way, beyond, *NO_MIDWAY)
        )

    assert pull(0.0, far) == pytest.approx(1.0)
    assert pull(low, far) == pytest.approx(1.0)
    assert 0.0 < pull((low + high) / 2, far) < 1.0
    assert pull(high + 0.001, far) == 0.0
    assert pull(0.0, -far) == 0.0
    assert pull(0.015, 1e-9) == pytest.approx(pull(0.015, -1e-9), abs=1e-6)
    running = approach_pull(SCALAR, WAITING_RATE, 0.0, far, 0.1, room, clear_way, far, *NO_MIDWAY)
    assert running == 0.0


def test_the_height_loop_steering_to_a_waypoint_feeds_forward_none_of_the_plans_speed() -> None:
    """On the reference (aim 0) the plan's vertical speed is fed forward in full; steering to
    the waypoint waited for (aim 1), none of it: the loop closes on the waypoint's height
    alone, whatever the plan's speed; between, both in proportion."""
    gain, height, waited, tcp = 10.0, 0.25, 0.2344, 0.2322

    def rate(speed: float, aim: float) -> float:
        return float(height_rate(SCALAR, gain, (height, speed), waited, tcp, aim))

    assert rate(-0.2, 0.0) == pytest.approx(-0.2 + gain * (height - tcp))
    assert rate(-0.2, 1.0) == pytest.approx(gain * (waited - tcp))
    assert rate(0.3, 1.0) == rate(-0.2, 1.0) > 0.0  # up to the waypoint, not on down
    assert rate(-0.2, 0.5) == pytest.approx((rate(-0.2, 0.0) + rate(-0.2, 1.0)) / 2)


def test_without_an_obstacle_in_reach_the_velocity_is_left_alone() -> None:
    far = measure(None, (0.3, 0.0, 0.2), (0.5, 0.0), CONFIG.sensing_range)
    assert approach_limited(SCALAR, CONFIG, 0.1, -0.2, far, (0.2, 0.0)) == (0.1, -0.2)


def test_a_runs_law_takes_the_packaged_rule_base_read_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each run's start builds its law in the tick that starts it: the packaged Table 2 is
    read and checked against its schema once per process, not once per run."""
    scenario = load_scenario("scenarios/reference.toml")
    first = ControlLaw.for_scenario(scenario)

    def read_again(cls: type[RuleBase], path: object = None) -> RuleBase:
        raise AssertionError("the rule file was read again")

    monkeypatch.setattr(RuleBase, "load", classmethod(read_again))
    second = ControlLaw.for_scenario(scenario)
    assert second.law.coordination.inference.rule_base is first.law.coordination.inference.rule_base
