"""The two behaviours of the paper's Fig. 5: PT (planning trajectory) and AO (avoiding
obstacle, made of TL and TR), each giving a unicycle command (v, omega) for the TCP.

The TCP is steered in the XY plane like a unicycle with a virtual heading phi
(x' = v cos phi, y' = v sin phi, phi' = omega), as the paper's (v, omega) commands imply.
Where PT's way lies behind the heading, an arm that is all but still goes that way
backwards, the heading turned half round (:func:`backward_tracking`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

from controller.coordination import AHEAD_NONE, smoothstep
from controller.detour import passable, straight_passable
from controller.obstacle import ObstacleMeasurement
from protocol.config import ControllerConfig, RobotConfig
from protocol.geometry import Section, length, nearest_point, tangent_points, to_local, wrap_angle
from protocol.ops import Mask, Ops, Real

TURN_LEFT = 1
TURN_RIGHT = -1
PLANNED_REST_SPEED = 0.005
"""m/s: below this PT drops the crawl along the plan (AHEAD_SPEED_FRACTION) and the split
along and across it, whose direction is not defined at a standstill."""
CRAWL_SPEED_MIN = 0.008
"""m/s: the slowest PT crawls along a moving plan (:func:`crawl_speed`). At 5 mm/s, 1.5 times
the stop speed of a plan averaging 165 mm/s, an arm the hard switch handed back moving
against the plan's way reversed to the crawl and stood 6 ms (``edge_obstacle`` seed
11,000,000, 790)."""
AHEAD_SPEED_FRACTION = 0.25
"""A TCP ahead of the moving plan slows down to this fraction of the planned speed."""
REST_LINE_NEARER = 0.01
"""m: how much nearer, along the plan, the waypoint where the plan comes to rest must be to
the TCP than the reference is for PT to measure the way across from that waypoint's line
alone (:func:`plan_tracking`)."""
STEER_LOOKAHEAD = 0.002
"""m: the least distance along the plan over which PT steers back onto it
(:func:`plan_tracking`)."""
REST_HEADING = 0.7
"""The cosine of the angle (about 45 degrees) within which the plan's way must point at the
waypoint it comes to rest at, from the reference, for PT to measure the arm's way to it along
that way (:func:`plan_tracking`)."""
ACROSS_BAND = 0.8
"""|sin| of PT's heading error from which the TCP goes PT's way across the heading directly
(:func:`across_heading`)."""
BACKWARD_AO_SHARE = 0.05
"""The most AO's share of the blend (k_C over k_T + k_C) with which PT still goes a way behind
its heading backwards (:func:`backward_tracking`), AO's share kept as it moves the arm: with
AO fading out at 0.03, 0.01, 0.001 of the blend, the arm stood 16 ms while the heading turned
half round to PT's way (``edge_obstacle`` seed 10,000,000, 922, fuzzy)."""
BACKWARD_SPEED = 0.001
"""m/s: PT goes a way behind its heading backwards (:func:`backward_tracking`) only where it
wants at least this: below, the way is that of an arm all but on its reference (at a run's
start, micrometres off it), and turning the heading round for it turned AO, blended in a
few ticks later, the wrong way (fuzzy peak jerk 32 to 115 m/s^3, ``gen-0-962``)."""
AIM_SPARE = 0.0015
"""m: the way AO steers round passes this near a waypoint nearer the inflated obstacle than
AO's pass margin and this (:func:`aim_margin`): within the 1.9 mm that pass it ..."""
AIM_SHARE = 0.5
"""... or halfway between the waypoint and the obstacle, for a waypoint nearer than twice
AIM_SPARE."""


class Command(NamedTuple):
    """A unicycle command: speed along the heading (m/s) and turn rate (rad/s, CCW > 0)."""

    v: Real
    omega: Real


STOP = Command(0.0, 0.0)


class Tracking(NamedTuple):
    """PT's command, with what driving the same way backwards takes
    (:func:`backward_tracking`): the speed PT wants, the heading's error to the way it wants
    it, and the turn rate fed forward."""

    v: Real
    omega: Real
    speed: Real
    error: Real
    feedforward: Real


def aim_margin(pass_margin: float, room: float) -> float:
    """How far outside the inflated obstacle AO steers round on the way to a waypoint whose
    free room (its clearance from the inflated obstacle, :func:`controller.obstacle.free_room`)
    is ``room``: the pass margin, less for a waypoint inside it, which the way round must
    leave outside: AO going round at the full margin would circle such a waypoint for ever.
    Unchanged for a waypoint ``pass_margin + AIM_SPARE`` or more away."""
    return min(pass_margin, max(AIM_SHARE * room, room - AIM_SPARE))


def crawl_speed(ops: Ops, planned_speed: Real) -> Real:
    """PT's crawl along a plan moving at ``planned_speed``: AHEAD_SPEED_FRACTION of it, and
    no slower than CRAWL_SPEED_MIN or the plan itself, the slower (an arm on a plan slower
    than that moves with it, not ahead of it) (:func:`plan_tracking`)."""
    return ops.max(AHEAD_SPEED_FRACTION * planned_speed, ops.min(CRAWL_SPEED_MIN, planned_speed))


def plan_tracking(
    ops: Ops,
    config: ControllerConfig,
    heading: Real,
    position: tuple[Real, Real],
    reference: tuple[Real, Real],
    reference_velocity: tuple[Real, Real],
    reference_acceleration: tuple[Real, Real],
    rest_ahead: tuple[Real, Real, Mask],
    past_waypoint: tuple[Real, Real],
) -> Tracking:
    """PT: follow the planned point; eq. 26's (v_T, omega_T).

    The wanted velocity is the plan's plus ``position_gain`` times the position error, split
    along and across the planned direction of travel; the TCP steers to its direction and
    moves at its size (so an arm beside a plan that slows down or waits still closes the
    gap). Along, it is never below AHEAD_SPEED_FRACTION of the planned speed: a TCP ahead of
    the plan (AO may drive it faster than planned) lets the plan catch up at a crawl rather
    than turning round, or standing still while the plan moves. Nor below CRAWL_SPEED_MIN:
    a quarter of a plan slowing through a waypoint, turning 55 degrees, left an arm ahead of
    it below the speed a stop counts from (edge_obstacle seed 4, 426, the hard switch).

    Once the TCP has passed the waypoint the plan heads for, ``past_waypoint`` gives the
    plan's own speed and the TCP's last commanded speed up to it (both 0 before the pass).
    The crawl is then at least AHEAD_SPEED_FRACTION of the plan's own speed: the plan, waiting
    short of that waypoint, moves off at a rising rate, and a crawl at that rate's share of
    its speed (or, while the rate was still small, aiming back at the reference as at a rest)
    stood the arm still on the waypoint until the reference came. Nor does PT brake the TCP
    below its last speed: an arm a little ahead where the plan turns back slowly through the
    waypoint, braked to the crawl, wanted a way that swung round with the plan faster than
    the heading could follow, and stood.

    But where the plan comes to rest at the waypoint ahead (``rest_ahead``: its place, and
    whether the plan rests there) the crawl ends there: it slows to ``position_gain`` times
    the TCP's way to it, along the plan, and waits there for the plan (crawling on, it went
    past the waypoint, away from where the plan stops, and had to come back). A TCP nearer
    that waypoint than the reference, along the plan, measures its way across from the line
    through the waypoint (in full from REST_LINE_NEARER nearer): measured from the
    reference's line, 50 mm back where the plan bends on to the waypoint, an arm that had
    come early crawled about 9 mm beside the waypoint, and stood where that line swung
    across it (``edge_obstacle`` seed 7,000,000, 484 and 727). A rest counts only where the
    plan's way from the reference points at the waypoint (within REST_HEADING): measured along
    the way of a plan that bends on to a waypoint 28 mm to the side, an arm beside the
    reference was past it, and turned back (``edge_obstacle`` seed 8,000,000, 61).

    The TCP steers back onto the plan over no less than STEER_LOOKAHEAD along it: over the
    crawl's own reach (``position_gain`` times the way across against the crawl, 0.5 mm at 5
    mm/s), a fraction of a millimetre across swung the way 60-150 degrees, and the heading
    chased it while the arm stood (``edge_obstacle`` seed 8,000,000, 511 and 61). The plan's
    own turn rate is fed forward. Where the plan (nearly) stands still the wanted velocity is the
    same sum, steered to as a whole: aiming at the planned point alone dropped the plan's last
    few mm/s as it came to a rest or left one, and an arm on its reference slowed to a stop
    there.
    """
    error_x, error_y = reference[0] - position[0], reference[1] - position[1]
    vx, vy = reference_velocity
    planned_speed = length(ops, vx, vy)
    moving_off, kept = past_waypoint
    moving = ops.max(planned_speed, moving_off)
    at_rest = moving < PLANNED_REST_SPEED
    divisor = ops.where(at_rest, 1.0, planned_speed)
    along_x, along_y = vx / divisor, vy / divisor
    lag = error_x * along_x + error_y * along_y
    offset = along_x * error_y - along_y * error_x
    crawl = ops.max(crawl_speed(ops, moving), kept)
    rest_x, rest_y, resting = rest_ahead
    if ops.any(resting):
        # Only a waypoint the plan heads for: one off to the side, where it bends on to it,
        # is not level with an arm just because the line along the plan's way passes it.
        ahead_x, ahead_y = rest_x - reference[0], rest_y - reference[1]
        resting = resting & (
            ahead_x * along_x + ahead_y * along_y >= REST_HEADING * length(ops, ahead_x, ahead_y)
        )
        to_rest = (rest_x - position[0]) * along_x + (rest_y - position[1]) * along_y
        nearer = -lag - abs(to_rest)
        if ops.any(resting & (nearer > 0.0)):
            from_rest = along_x * (rest_y - position[1]) - along_y * (rest_x - position[0])
            share = ops.where(resting, ops.clip(nearer / REST_LINE_NEARER, 0.0, 1.0), 0.0)
            offset = offset + share * (from_rest - offset)
        crawl = ops.where(resting, ops.min(crawl, config.position_gain * to_rest), crawl)
    along = ops.max(planned_speed + config.position_gain * lag, crawl)
    across = config.position_gain * offset
    speed = ops.min(length(ops, along, across), config.speed_max)
    # Steered back onto the plan over no less than STEER_LOOKAHEAD, whichever way along (the
    # way along is below nothing only where a crawl ended at a rest points back to it).
    least = config.position_gain * STEER_LOOKAHEAD
    steered = ops.max(along, least)
    if ops.any(resting):
        steered = ops.where(along >= 0.0, steered, ops.min(along, -least))
    target = ops.atan2(vy, vx) + ops.atan2(across, steered)
    ax, ay = reference_acceleration
    feedforward = (vx * ay - vy * ax) / (divisor * divisor)
    error = wrap_angle(target - heading)
    v = speed * ops.max(ops.cos(error), 0.0)
    omega = feedforward + config.heading_gain * error
    if ops.any(at_rest):
        wanted_x = vx + config.position_gain * error_x
        wanted_y = vy + config.position_gain * error_y
        wanted = length(ops, wanted_x, wanted_y)
        still = wanted < 1e-9
        error = ops.where(at_rest, wrap_angle(ops.atan2(wanted_y, wanted_x) - heading), error)
        speed = ops.where(at_rest, ops.where(still, 0.0, ops.min(wanted, config.speed_max)), speed)
        feedforward = ops.where(at_rest, 0.0, feedforward)
        v = ops.where(at_rest, speed * ops.max(ops.cos(error), 0.0), v)
        omega = ops.where(at_rest, ops.where(still, 0.0, config.heading_gain * error), omega)
    return Tracking(v, omega, speed, error, feedforward)


def across_heading(ops: Ops, tracking: Tracking, crawl: Real, share: Real, moving: Real) -> Real:
    """The TCP's speed across its heading (to the left > 0) towards PT's way where that lies
    about 90 degrees off the heading (|sin| of the error from ACROSS_BAND, in full at 90
    degrees): what the speed ``moving`` the blend gives along the heading lacks of ``share``
    (PT's in the blend) of PT's speed, no more than ``crawl``: the TCP moves no slower than
    that.

    The unicycle's speed along its heading falls as the cosine of the error, to nothing at 90
    degrees; where PT's way swung round faster than the heading could turn (the reference
    passing the arm, a way that closes on a waypoint from the side), the arm stood while the
    heading turned. The TCP itself can move either way, and does, but only so far as it would
    otherwise all but stand: where AO carries the arm round the obstacle with PT's way far
    off the heading, PT's pull across drew it 2 mm nearer the obstacle in the reference
    scenario.
    """
    sin_error = ops.sin(tracking.error)
    if not ops.any(abs(sin_error) > ACROSS_BAND):
        return 0.0
    band = smoothstep(ops, (abs(sin_error) - ACROSS_BAND) / (1.0 - ACROSS_BAND))
    wanted = share * band * abs(sin_error) * ops.min(tracking.speed, crawl)
    lacking = ops.max(wanted * wanted - moving * moving, 0.0)
    return ops.where(sin_error >= 0.0, 1.0, -1.0) * ops.sqrt(lacking)


def backward_tracking(ops: Ops, config: ControllerConfig, tracking: Tracking) -> Command:
    """PT's wanted velocity driven with the heading turned half round, for a way that lies
    more than 90 degrees off the heading: the unicycle goes there backwards instead of
    standing while it turns (the TCP itself can move either way)."""
    error = tracking.error
    turned = error - ops.where(error > 0.0, math.pi, -math.pi)
    return Command(
        -tracking.speed * ops.cos(error), tracking.feedforward + config.heading_gain * turned
    )


def avoid_obstacle(
    ops: Ops,
    config: ControllerConfig,
    robot: RobotConfig,
    aim: Section,
    obstacle: Section,
    measurement: ObstacleMeasurement,
    min_distance: Real,
    side: Real,
    heading: Real,
    position: tuple[Real, Real],
    goal: tuple[Real, Real],
    elbow: Real,
    check_again: Mask,
) -> tuple[Command, Real]:
    """AO with its TL/TR choice (``side``: +1 TL, -1 TR, 0 none yet), and the side kept.

    AO acts while the obstacle is present and ahead, or the TCP moves towards it (or is
    inside it); it chooses its side when it starts to act, away from the side the obstacle is
    nearer on unless the joint limits close that way round to ``goal`` and leave the other
    open (:mod:`controller.detour`; ``elbow``: the sign of theta2; ``obstacle``, the inflated
    one, where the straight way keeps clear of it: :func:`_side_the_joints_take`), keeps it
    while it acts unless that way closes (checked again while ``check_again``: a joint near
    its stop or full reach, where a way round closes, or the plan just moved on to its next
    waypoint, the goal the way was judged to), and forgets it when it stops.
    """
    engaged = measurement.present & ops.not_(
        (ops.max(measurement.ahead, measurement.toward) <= AHEAD_NONE)
        & (measurement.clearance > 0.0)
    )
    fresh = side == 0
    chosen = ops.where(measurement.d_left >= measurement.d_right, TURN_LEFT, TURN_RIGHT)
    side = ops.where(engaged, ops.where(fresh, chosen, side), 0)
    # The side is checked when it is chosen, and again when asked (check_again) if the way to
    # the goal is blocked.
    side = ops.branch(
        engaged & (fresh | check_again & measurement.blocked),
        _side_the_joints_take,
        side,
        ops,
        robot,
        aim,
        obstacle,
        position,
        goal,
        side,
        elbow,
        measurement.blocked,
    )
    command = ops.branch(
        engaged,
        _avoid,
        STOP,
        ops,
        config,
        aim,
        side,
        heading,
        position,
        min_distance,
    )
    return command, side


def _side_the_joints_take(
    ops: Ops,
    robot: RobotConfig,
    aim: Section,
    obstacle: Section,
    position: tuple[Real, Real],
    goal: tuple[Real, Real],
    preferred: Real,
    elbow: Real,
    blocked: Mask,
) -> Real:
    """``preferred``, unless its way round is closed and the other one open.

    Where the straight way to ``goal`` is ``blocked``, the way round ``aim`` (AO's). Where
    it keeps clear of the obstacle but runs out of the joint limits (through the hole inside
    the inner reach), the arm follows a plan that bends round past the obstacle's end, within
    AO's margin: there a way is closed only where it is closed round ``obstacle`` (the
    inflated one) itself. AO, choosing there by d_L and d_R alone, took an arm round the end
    where the obstacle meets the inner reach, and it stood at theta2's stop, 1 mm from it.

    A way is judged first clear of the hole inside the inner reach; only where neither is,
    by whether the arm can slide round the hole (:func:`controller.detour.passable`). Judged
    by the slide alone, AO kept ways along theta2's stop where the other side was clear, and
    fuzzy runs went rougher (``edge_limit`` seed 4, 313: peak jerk 68 to 338 m/s^3). From
    inside AO's margin no way round it is open on either side; there the sides are judged
    round the inflated obstacle itself (AO kept the side that had taken an arm into the
    corner between full reach and an obstacle reaching in from beyond it, and it stood there:
    ``edge_obstacle`` seed 8,000,000, 805, fuzzy).
    """
    bent: Mask = False
    if ops.any(ops.not_(blocked)):
        straight = straight_passable(ops, robot, position, goal, elbow)
        bent = ops.not_(blocked) & ops.not_(straight)
    sections = ((blocked, aim), (bent, obstacle))
    closed = (blocked | bent) & ops.not_(
        _way_open(ops, robot, sections, position, goal, preferred, elbow, slide=False)
    )
    if not ops.any(closed):
        return preferred
    other_open = _way_open(ops, robot, sections, position, goal, -preferred, elbow, slide=False)
    turn = closed & other_open
    undecided = closed & ops.not_(other_open)
    if ops.any(undecided):
        # Neither way clear of theta2's stop: the one the arm can slide round.
        kept, other = _ways_open(ops, robot, sections, position, goal, preferred, elbow, True)
        turn = turn | (undecided & ops.not_(kept) & other)
        # From inside AO's margin no way round it is open: judged round the inflated obstacle
        # itself, as a way that bends round past its end is.
        inside = undecided & blocked & ops.not_(kept | other)
        if ops.any(inside):
            own = ((inside, obstacle),)
            kept, other = _ways_open(ops, robot, own, position, goal, preferred, elbow, False)
            turn = turn | (inside & ops.not_(kept) & other)
    return ops.where(turn, -preferred, preferred)


def _ways_open(
    ops: Ops,
    robot: RobotConfig,
    sections: tuple[tuple[Mask, Section], ...],
    position: tuple[Real, Real],
    goal: tuple[Real, Real],
    preferred: Real,
    elbow: Real,
    slide: bool,
) -> tuple[Mask, Mask]:
    """Whether the way round on ``preferred``'s side is open, and the other side's
    (:func:`_way_open`)."""
    return (
        _way_open(ops, robot, sections, position, goal, preferred, elbow, slide),
        _way_open(ops, robot, sections, position, goal, -preferred, elbow, slide),
    )


def _way_open(
    ops: Ops,
    robot: RobotConfig,
    sections: tuple[tuple[Mask, Section], ...],
    position: tuple[Real, Real],
    goal: tuple[Real, Real],
    side: Real,
    elbow: Real,
    slide: bool,
) -> Mask:
    """Whether the way round on ``side`` is passable (``slide``: :func:`passable`), round
    each section where its mask is set."""
    open_: Mask = True
    for where, section in sections:
        if ops.any(where):
            way = passable(ops, robot, section, position, goal, side, elbow, slide)
            open_ = ops.where(where, way, open_)
    return open_


def _avoid(
    ops: Ops,
    config: ControllerConfig,
    aim: Section,
    side: Real,
    heading: Real,
    position: tuple[Real, Real],
    min_distance: Real,
) -> Command:
    """AO (TL when ``side`` is +1, TR when -1): eq. 28-29.

    v_A = f_vA(min(d_L, d_R) cos beta), omega_A = f_omegaA(sin beta / min(d_L, d_R)) times the
    side. Here beta is taken from the heading to the chosen edge of ``aim``, the obstacle
    grown by ``config.ao_pass_margin``: while PT drives, the heading points at p_j and this
    is the paper's beta; once AO has turned the TCP, measuring from the heading makes AO
    settle on the tangent (pure pursuit: curvature 2 sin beta / d) instead of turning
    without end.
    """
    px, py = position
    lx, ly = to_local(aim, px, py)
    outside, left_x, left_y, right_x, right_y = tangent_points(ops, aim, px, py, lx, ly)
    left_hand = side == TURN_LEFT
    edge_x = ops.where(left_hand, left_x, right_x)
    edge_y = ops.where(left_hand, left_y, right_y)
    edge_angle = ops.branch(
        ops.not_(outside),
        _along_boundary,
        ops.atan2(edge_y - py, edge_x - px),
        ops,
        aim,
        side,
        px,
        py,
        lx,
        ly,
    )
    beta = side * wrap_angle(edge_angle - heading)
    distance = ops.max(min_distance, 1e-3)
    along = distance * ops.cos(beta)
    v = config.ao_speed_min + (config.ao_speed_max - config.ao_speed_min) * ops.tanh(
        ops.max(along, 0.0) / config.ao_speed_distance
    )
    omega = config.ao_turn_max * ops.tanh(ops.sin(beta) / distance / config.ao_turn_scale)
    return Command(v, side * omega)


def _along_boundary(
    ops: Ops, aim: Section, side: Real, px: Real, py: Real, lx: Real, ly: Real
) -> Real:
    """Inside ``aim`` there is no tangent: the way to go is along the boundary through the
    TCP, on the chosen side, tilted outwards by how deep the TCP is."""
    depth, nearest_x, nearest_y = nearest_point(ops, aim, lx, ly)
    normal_x, normal_y = nearest_x - px, nearest_y - py
    flip = depth >= 0.0
    normal_x = ops.where(flip, -normal_x, normal_x)
    normal_y = ops.where(flip, -normal_y, normal_y)
    zero = (normal_x == 0.0) & (normal_y == 0.0)
    normal_x = ops.where(zero, px - aim.x, normal_x)
    normal_y = ops.where(zero, py - aim.y, normal_y)
    along_boundary = ops.atan2(normal_y, normal_x) - side * math.pi / 2.0
    tilt = ops.min(1.0, abs(depth) / ops.max(aim.inflation, 1e-3)) * math.pi / 4.0
    return along_boundary + side * tilt
