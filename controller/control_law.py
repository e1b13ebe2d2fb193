"""One control step: measure, behave, coordinate, map to joints, limit (Fig. 6 end to end).

:func:`step` is the law, written once over :mod:`protocol.ops`: :class:`ControlLaw` runs it
on floats for the controller (one arm, every tick), and ``sim/batch.py`` on arrays for the
study (thousands of runs at once). It is pure in the simple-pid sense: it is handed the time
and the measured joints and the few values a controller must remember between ticks
(:class:`LawState`), and knows nothing of buses or clocks.

Beyond the paper's blend, the plan waits for an arm that a detour has held off the way to an
inner waypoint (time scaling): the reference moves on past the waypoint once the arm has come
to it, instead of pulling the arm across the corner. Near the waypoint the arm is brought
onto it (the final approach), and limits on the output keep it off the obstacle's margin and
off the arm's full reach. The safety filter (:mod:`controller.safety`) has the last word.
``docs/design.md`` describes the law and ``docs/study.md`` the measurements each part answers.
"""

from __future__ import annotations

import itertools
import math
from typing import NamedTuple, Protocol

from controller.behaviours import (
    AHEAD_SPEED_FRACTION,
    BACKWARD_AO_SHARE,
    BACKWARD_SPEED,
    PLANNED_REST_SPEED,
    Command,
    Tracking,
    across_heading,
    aim_margin,
    avoid_obstacle,
    backward_tracking,
    crawl_speed,
    plan_tracking,
)
from controller.coordination import Coordination, smoothstep, weights
from controller.obstacle import NO_OBSTACLE, ObstacleMeasurement, free_room, sense
from controller.planner import Trajectory, cubic, plan_of
from controller.safety import Limits, barrier, box, filtered, limits_of
from protocol.config import ControllerConfig, RobotConfig
from protocol.geometry import (
    EllipticCylinder,
    Section,
    distance,
    length,
    nearest_to,
    wrap_angle,
)
from protocol.kinematics import (
    ArmTrig,
    arm_trig,
    joint_rates,
    reach_radii,
    tool_position,
    tool_velocity,
)
from protocol.ops import SCALAR, Mask, Ops, Real
from protocol.scenario import Mode, Scenario

Point3 = tuple[Real, Real, Real]

GOAL_HANDOVER = 0.5
"""s of plan: how long before a waypoint's time DM starts looking towards the one after it."""
BEHIND = (0.0005, 0.001)
"""m: how far the arm may be off the way from the reference to the next waypoint
(:func:`_behind`). Near the waypoint the plan slows as that grows across this span and waits
beyond it."""
PASSED = 0.0019
"""m: a waypoint the TCP came this close to counts as passed: just inside the 2 mm a
waypoint must be passed within, so that an arm that went by within the task's tolerance is
not slid back onto it."""
GATE_APPROACH = 0.4
"""s of plan before a waypoint over which the gate closes (the reference may slow to wait)."""
GATE_RELEASE = 0.2
"""s of plan after a waypoint over which its free room hands over to the next one's
(:func:`_at_waypoint`)."""
RATE_CHANGE = 0.1
"""s: the plan's rate goes from 1 to 0 or back in no less than this, so the reference never
brakes or starts harder than the arm can follow (an arm overshooting a waiting reference
would have to turn back: a stop)."""
RATE_RAMP = 0.05
"""s: rising, the rate's slope goes from none to its most (1 per RATE_CHANGE) in no less than
this, so that the reference's acceleration ramps where the plan moves off after a wait:
stepping the slope stepped it by up to 1/RATE_CHANGE times the plan's speed (6 m/s^2 at 0.6
m/s), and the arm's jerk peaked as it moved off."""
CLEAR_WAY = 0.01
"""m: AO gives way once the obstacle is this much farther from the TCP than the waypoint it
heads for (:func:`_at_waypoint`): AO would only take the arm round an obstacle beyond it. At
most the waypoint's free room: a waypoint nearer the obstacle lies just in front of it, and
an arm coming straight at it must be handed to PT before AO turns it along the obstacle
(which took it past the waypoint and round the obstacle again and again)."""
HEIGHT_LEAD = (0.01, 0.02)
"""m: how much nearer the next waypoint than the reference the TCP is when the height loop
starts to lead (:func:`height_lead`), and when it leads in full. Led from the first
millimetre, the height changed most runs at a doorstep and raised their peak jerk."""
HEIGHT_LEAD_NEAR = (0.008, 0.002)
"""m: near p_j the height leads sooner: from this far from p_j in the plane, in full from
this near, once the TCP is HEIGHT_LEAD_NEAR_AHEAD nearer p_j than the reference; else an arm
slowing onto p_j as the reference caught up could go by it in the plane but below it."""
HEIGHT_LEAD_NEAR_AHEAD = (0.002, 0.004)
"""m: see HEIGHT_LEAD_NEAR. From the first millimetre ahead, the aim jumps (a millimetre is a
large share of the way there) and the peak jerk of open runs rose."""
LOOP_RADIUS = 0.003
"""m: the radius of the circle the final approach takes an arm round, when the straight way
onto the waypoint would point against the plan (:func:`final_approach`): more than PASSED,
and within 6 mm of the waypoint. At most LOOP_ROOM of the waypoint's free room, so that the
circle keeps clear of the obstacle whichever side of the waypoint it lies on."""
LOOP_ROOM = 1.0 / 3.0
ROOM_FLOOR = 1e-4
"""m: CLEAR_WAY and LOOP_RADIUS are never less, for a waypoint on the obstacle's edge."""
LOOP_AGAINST = 0.5
"""How far the straight way onto a waypoint points against the plan's way out of it (the
cosine of the angle between them, negated) where the final approach is a loop in full. From
90 degrees the straight way hands over to the loop, and from 120 degrees it loops."""
TURN_APART = 0.5
"""How far the blended command and the final approach's velocity point apart (the cosine of
the angle between them, negated) where the final approach takes over by turning the way
(:func:`turned_towards`) in full: from 90 degrees it starts to, from 120 it does in full."""
TURN_KEEP = 5.0 * math.pi / 6.0
"""rad: how far apart (up to half a turn) the two ways :func:`turned_towards` turns between
must point for the way to turn round the side the arm last moved to, not the short way."""
TURN_ASIDE = 0.25
"""|sin| of the angle from the way on to the velocity last commanded from which that velocity
lies to one side of it, for :func:`turned_towards` (all but along it, the side it lay on was
a rounding's, and the way, turned round it, cancelled the two added: edge_obstacle seed
6,000,000, 931, the hard switch)."""
TURN_SHARE = 0.3
"""How far, there, the velocity goes from the two added as vectors to the way turned at a
speed between theirs. Added, they all but cancelled: an arm that had gone by a waypoint a few
millimetres beside it, pulled back, stood (`edge_reach` seed 2, 38). Turned in full, it
swung round at speed, and jerked more than the hard switch (`fast` 461: 806 against 644
m/s^3)."""
NEAR_STOP = math.radians(5.0)
"""rad: a revolute joint this near its stop (theta2 this near 0, full reach) has AO check that
its way round is still open."""
WAITING_RATE = 0.5
"""The plan's rate below which it all but waits for the arm (:func:`approach_pull`)."""
WAITING_REACH = (0.01, 0.02)
"""m: the final approach takes over wherever the straight way is clear (:func:`approach_pull`)
for an arm within the first of these of the waypoint the plan all but waits for, or of the
plan's line past it, fading out to the second. From farther, its pull (the gain times the
way) jerked arms lagging a fast plan, and arms going round the obstacle past the waypoint."""
GOAL_KEPT = (0.005, 0.03)
"""m: how far off the way to p_j (as in BEHIND) the arm is when DM's look-ahead to the
following waypoint is undone: an arm still on its way round the obstacle keeps looking at
p_j."""
GOAL_BACK = (0.8, 0.95)
"""The cosine of the angle at p_j between the arm and p_j+1 over which DM's look-ahead is
undone too, for an arm that has not passed p_j: where the plan turns back at p_j, the point
sliding from p_j to p_j+1 would pass by the arm still coming in, and the direction DM
measures from (and fuzzy's k_C with it) swing half a turn in a few ticks."""


class Stage(NamedTuple):
    """What the law reads of the plan while the reference is on one stage: segment i, from
    waypoint i to i + 1, or (the last stage) the rest at the final waypoint. Fixed by the
    plan, so worked out once (:func:`stages_of`); floats, or one array element per run."""

    start: Real
    """Plan time the stage starts at: tau = progress - start."""
    end: Real
    """Plan time the next stage starts at (inf for the rest)."""
    k0: Point3
    """The cubic's coefficients per axis (:func:`controller.planner.cubic`); the rest holds
    the final waypoint: k0 is it, the others 0."""
    k1: Point3
    k2: Point3
    k3: Point3
    index: Real
    """j: the waypoint p_j headed for."""
    point: Point3
    """p_j"""
    point_before: Point3
    """p_j-1"""
    time: Real
    """p_j's time."""
    time_before: Real
    room: Real
    """p_j's free room (:func:`controller.obstacle.free_room`)."""
    room_before: Real
    aim: Section
    """What AO steers round on the way to p_j: the inflated obstacle grown by
    :func:`controller.behaviours.aim_margin`."""
    clear_way: Real
    """p_j's CLEAR_WAY (:func:`_at_waypoint`)."""
    clear_way_before: Real
    loop_radius: Real
    """p_j's LOOP_RADIUS (:func:`final_approach`)."""
    loop_radius_before: Real
    leaving: tuple[Real, Real]
    """The plan's way out of p_j (:func:`_leaving`)."""
    leaving_before: tuple[Real, Real]
    rests: Mask
    """The plan comes to rest at p_j (no way out of it): PT's crawl ends there."""
    inner: Mask
    """p_j is an inner waypoint (not the last)."""
    inner_before: Mask
    """p_j-1 is an inner waypoint (not the first)."""
    approach: Real
    """The segment's GATE_APPROACH, release and GOAL_HANDOVER, each at most half of it so
    that those of its two ends never overlap."""
    release: Real
    handover: Real
    goal_slide: tuple[Real, Real]
    """p_j+1 - p_j in the plane, where DM's goal slides to (0 at the last waypoint)."""


class Plan(Protocol):
    """Where on its stages a plan is (a driver's, scalar or batch)."""

    def at(self, progress: Real) -> Stage:
        """The stage (or stages) the reference is on at plan time ``progress`` (which never
        goes back between calls)."""
        ...


class Law(NamedTuple):
    """What the law of one scenario (or, as arrays, of each run of a batch) holds fixed."""

    robot: RobotConfig
    config: ControllerConfig
    obstacle: Section
    fuzzy: Mask
    """Table 2's coordinator, else the conventional switch."""
    coordination: Coordination
    full_reach: float
    speed_limits: tuple[float, float, float]
    step_limits: tuple[float, float, float]
    """The most a joint's command may change in one tick."""
    limits: Limits
    """The safety filter's box (:func:`controller.safety.limits_of`)."""


class LawState(NamedTuple):
    """What the law remembers from one tick to the next."""

    heading: Real
    """The TCP's unicycle heading."""
    side: Real
    """AO's TL/TR choice (+1, -1; 0: none)."""
    previous: Point3
    """The last command."""
    progress: Real
    """The plan's time the reference stands at: advances by ``rate`` times t's."""
    rate: Real
    """How fast the plan's time runs against t, 0..1 (:func:`_wanted_rate`)."""
    rate_slope: Real
    """How fast ``rate`` changes, per second of t."""
    last_t: Real
    reached: Real
    """The last waypoint the TCP has come within PASSED of."""


class ControlOutput(NamedTuple):
    """The joint velocity command of one tick and what led to it (for logs and figures)."""

    command: Point3
    tcp: Point3
    reference: Point3
    reference_speed: Real
    measurement: ObstacleMeasurement
    tracking: Tracking
    avoiding: Command
    k_t: Real
    k_c: Real
    blended: Command
    heading: Real
    limited: Mask
    """The output limits or the safety filter changed the command."""
    progress: Real
    no_safe_motion: Mask
    """No command within the joint limits keeps the barrier (:mod:`controller.safety`): the
    controller faults and brakes."""
    waited: Point3
    """The waypoint the plan waits for: the first not yet passed (or p_j, once passed, until
    the plan moves on): what a run's progress is judged by (:mod:`controller.run_end`)."""


def law_of(
    robot: RobotConfig,
    config: ControllerConfig,
    obstacle: EllipticCylinder | None,
    fuzzy: Mask,
    coordination: Coordination,
) -> Law:
    """The fixed part of a scenario's law."""
    return Law(
        robot,
        config,
        NO_OBSTACLE if obstacle is None else obstacle.section(),
        fuzzy,
        coordination,
        reach_radii(robot)[1],
        robot.speed_limits,
        (
            robot.accel_limits[0] * config.period,
            robot.accel_limits[1] * config.period,
            robot.accel_limits[2] * config.period,
        ),
        limits_of(robot, config),
    )


def first_state(trajectory: Trajectory) -> LawState:
    """The state before the first tick: heading along the first segment, the plan at its
    start."""
    points = trajectory.points
    heading = math.atan2(points[1][1] - points[0][1], points[1][0] - points[0][0])
    start = trajectory.times[0]
    return LawState(heading, 0, (0.0, 0.0, 0.0), start, 1.0, 0.0, start, 0)


def stages_of(
    trajectory: Trajectory, obstacle: EllipticCylinder | None, pass_margin: float
) -> tuple[Stage, ...]:
    """The plan's stages: one per segment, then the rest at the final waypoint
    (``pass_margin``: AO's, ``ControllerConfig.ao_pass_margin``)."""
    times, points = trajectory.times, trajectory.points
    count = len(times)
    rooms = [free_room(obstacle, point) for point in points]
    aims = [
        NO_OBSTACLE if obstacle is None else obstacle.grown(aim_margin(pass_margin, room)).section()
        for room in rooms
    ]
    clear_ways = [max(min(CLEAR_WAY, room), ROOM_FLOOR) for room in rooms]
    loop_radii = [max(min(LOOP_RADIUS, LOOP_ROOM * room), ROOM_FLOOR) for room in rooms]
    leaving = [_leaving(trajectory, index) for index in range(count)]
    windows = []
    for start, end in itertools.pairwise(times):
        half = (end - start) / 2.0
        windows.append(
            (min(GATE_APPROACH, half), min(GATE_RELEASE, half), min(GOAL_HANDOVER, half))
        )
    stages = []
    for stage in range(count):
        index = min(stage + 1, count - 1)
        if stage < count - 1:
            coefficients = [trajectory.segment(stage, axis).coefficients for axis in range(3)]
            k0, k1, k2, k3 = (tuple(axis[k] for axis in coefficients) for k in range(4))
            # On the last segment up to and including the final waypoint's time.
            end = times[stage + 1] if stage < count - 2 else math.nextafter(times[-1], math.inf)
            start = times[stage]
        else:
            k0, k1, k2, k3 = points[-1], (0.0,) * 3, (0.0,) * 3, (0.0,) * 3
            start, end = times[-1], math.inf
        point = points[index]
        following = points[index + 1] if index + 1 < count else point
        stages.append(
            Stage(
                start,
                end,
                (k0[0], k0[1], k0[2]),
                (k1[0], k1[1], k1[2]),
                (k2[0], k2[1], k2[2]),
                (k3[0], k3[1], k3[2]),
                index,
                (point[0], point[1], point[2]),
                (points[index - 1][0], points[index - 1][1], points[index - 1][2]),
                times[index],
                times[index - 1],
                rooms[index],
                rooms[index - 1],
                aims[index],
                clear_ways[index],
                clear_ways[index - 1],
                loop_radii[index],
                loop_radii[index - 1],
                leaving[index],
                leaving[index - 1],
                leaving[index] == (0.0, 0.0),
                index < count - 1,
                index >= 2,
                *windows[index - 1],
                (following[0] - point[0], following[1] - point[1]),
            )
        )
    return tuple(stages)


def step(
    ops: Ops, law: Law, plan: Plan, state: LawState, t: Real, joints: Point3
) -> tuple[ControlOutput, LawState]:
    """One tick at the plan's clock ``t`` (it stops while the node holds), the joints measured
    at ``joints``: the command and what led to it, and the state for the next tick."""
    config = law.config
    progress = state.progress + state.rate * ops.max(t - state.last_t, 0.0)
    stage = plan.at(progress)
    theta1, theta2, d3 = joints
    trig = arm_trig(ops, theta1, theta2)
    tcp = tool_position(law.robot, trig, d3)
    tau = progress - stage.start
    k0, k1, k2, k3 = stage.k0, stage.k1, stage.k2, stage.k3
    along_x = cubic(k0[0], k1[0], k2[0], k3[0], tau)
    along_y = cubic(k0[1], k1[1], k2[1], k3[1], tau)
    along_z = cubic(k0[2], k1[2], k2[2], k3[2], tau)
    reference = (along_x[0], along_y[0], along_z[0])
    velocity = (along_x[1], along_y[1], along_z[1])
    acceleration = (along_x[2], along_y[2], along_z[2])
    index, side, reached = stage.index, state.side, state.reached
    # The waypoint passed (within PASSED): AO forgets its TL/TR choice, made on the way to
    # it, and chooses afresh on the way to the next.
    for candidate, point in ((index - 1, stage.point_before), (index, stage.point)):
        ahead = candidate > reached
        if ops.any(ahead):
            passed = ahead & (distance(ops, tcp, point) <= PASSED)
            reached = ops.where(passed, candidate, reached)
            side = ops.where(passed, 0, side)
    # Plane distances several parts of the law use: the TCP's to p_j and p_j-1, the
    # reference's to p_j.
    to_next = length(ops, tcp[0] - stage.point[0], tcp[1] - stage.point[1])
    to_before = length(ops, tcp[0] - stage.point_before[0], tcp[1] - stage.point_before[1])
    reference_to_next = length(ops, reference[0] - stage.point[0], reference[1] - stage.point[1])
    behind = ops.where(
        index <= reached,
        -math.inf,
        0.5
        * (to_next + length(ops, tcp[0] - reference[0], tcp[1] - reference[1]) - reference_to_next),
    )
    # Away from p_j-1 in space, as its passing is judged: in the plane alone, an arm over the
    # waypoint but above it let the plan creep on, and the height, led by the reference away
    # from the waypoint's, never came within PASSED of it.
    away_passed = ops.branch(index - 1 > reached, distance, -math.inf, ops, tcp, stage.point_before)
    wanted = _wanted_rate(ops, stage, progress, behind, away_passed)
    rate, rate_slope = ops.branch(
        (wanted != state.rate) | (state.rate_slope != 0.0),
        rate_towards,
        (state.rate, state.rate_slope),  # at the wanted rate, and staying there
        ops,
        config.period,
        state.rate,
        state.rate_slope,
        wanted,
    )
    # The reference moves at rate times the plan's velocity: the path's curvature, and with
    # it the turn rate PT feeds forward, stay those of the plan.
    reference_velocity = (rate * velocity[0], rate * velocity[1], rate * velocity[2])
    plan_speed = length(ops, velocity[0], velocity[1])  # the plan's own, in the plane
    squared = rate * rate
    depth_next = _depth(ops, stage.room, to_next)
    depth_before = _depth(ops, stage.room_before, to_before)
    # The waypoint the plan waits for: p_j-1 until the TCP has passed it, then p_j.
    waiting_next = ops.max(index - 1, ops.min(reached + 1, index)) == index
    waited = ops.where(waiting_next, stage.point, stage.point_before)
    to_waited = ops.where(waiting_next, to_next, to_before)
    goal = _goal(ops, stage, progress, behind, tcp, to_next)
    heading = state.heading
    heading_cos, heading_sin = ops.cos(heading), ops.sin(heading)
    left_x, left_y = -heading_sin, heading_cos  # across the heading, kept if it turns round
    measurement = sense(
        ops, law.obstacle, config.sensing_range, tcp, goal, (heading_cos, heading_sin)
    )
    # How far the TCP is past the waypoint the plan waits for (not passed), along the plan's
    # way at the reference (:func:`approach_pull`).
    # (Where the plan stands still, its velocity is nothing and so is this.)
    beyond = ((tcp[0] - waited[0]) * velocity[0] + (tcp[1] - waited[1]) * velocity[1]) / ops.where(
        plan_speed > 0.0, plan_speed, 1.0
    )
    pull = approach_pull(
        ops,
        rate,
        ops.where(waiting_next, depth_next, depth_before),
        to_waited,
        measurement.clearance,
        ops.where(waiting_next, stage.room, stage.room_before),
        ops.where(waiting_next, stage.clear_way, stage.clear_way_before),
        beyond,
        law.obstacle,
        ((tcp[0] + waited[0]) / 2.0, (tcp[1] + waited[1]) / 2.0),
    )
    min_distance = ops.min(measurement.d_left, measurement.d_right)

    passed_next = index <= reached
    past_waypoint: tuple[Real, Real] = (0.0, 0.0)
    last_speed: Real = 0.0  # the TCP's speed in the plane as last commanded, where needed
    if ops.any(passed_next):
        last_speed = _last_speed(ops, law.robot, trig, state.previous)
        past_waypoint = (
            ops.where(passed_next, plan_speed, 0.0),
            ops.where(passed_next, ops.min(last_speed, plan_speed), 0.0),
        )
    tracking = plan_tracking(
        ops,
        config,
        heading,
        (tcp[0], tcp[1]),
        (reference[0], reference[1]),
        (reference_velocity[0], reference_velocity[1]),
        (squared * acceleration[0], squared * acceleration[1]),
        (stage.point[0], stage.point[1], stage.rests),
        past_waypoint,
    )
    avoiding, side = avoid_obstacle(
        ops,
        config,
        law.robot,
        stage.aim,
        law.obstacle,
        measurement,
        min_distance,
        side,
        heading,
        (tcp[0], tcp[1]),
        goal,
        ops.where(theta2 >= 0.0, 1.0, -1.0),
        # A side chosen on the way to p_j-1 (an arm there ahead of the plan) is checked again
        # for p_j when the plan moves on to it: kept, it took an arm round the far side of an
        # obstacle near the outer reach, where the way was closed (outer seed 5,000,000, 518).
        _near_stop(ops, law.robot, theta1, theta2) | (state.progress < stage.start),
    )
    at_waypoint = _at_waypoint(
        ops,
        stage,
        progress,
        (to_next, to_before),
        (depth_next, depth_before),
        measurement.clearance,
    )
    k_t, k_c = weights(
        ops,
        law.coordination,
        law.fuzzy,
        measurement,
        min_distance,
        at_waypoint,
        law.obstacle.top - tcp[2],
    )
    total = k_t + k_c
    blended = Command(
        (k_t * tracking.v + k_c * avoiding.v) / total,
        (k_t * tracking.omega + k_c * avoiding.omega) / total,
    )
    # PT alone or all but alone (AO at most BACKWARD_AO_SHARE of the blend), its way behind
    # the heading (v 0): an arm all but still goes that way backwards, the heading turned half
    # round, instead of turning on the spot while the plan moves on (where the plan turns back
    # at a waypoint, the hard switch hands an arm back, or AO fades out).
    backward = (
        (k_c <= BACKWARD_AO_SHARE * total) & (tracking.v == 0.0) & (tracking.speed > BACKWARD_SPEED)
    )
    if ops.any(backward):
        if not ops.any(passed_next):
            last_speed = _last_speed(ops, law.robot, trig, state.previous)
        backward = backward & (last_speed < PLANNED_REST_SPEED)
        reversed_command = backward_tracking(ops, config, tracking)
        # AO's share, as it moves the arm, in the turned heading's terms: its way along the
        # heading reversed, its turn rate the same.
        share = k_c / total
        blended = Command(
            ops.where(
                backward,
                reversed_command.v + share * (-avoiding.v - reversed_command.v),
                blended.v,
            ),
            ops.where(
                backward,
                reversed_command.omega + share * (avoiding.omega - reversed_command.omega),
                blended.omega,
            ),
        )
        heading = ops.where(backward, wrap_angle(heading + math.pi), heading)
        heading_cos = ops.where(backward, -heading_cos, heading_cos)
        heading_sin = ops.where(backward, -heading_sin, heading_sin)

    across = across_heading(
        ops,
        tracking,
        crawl_speed(ops, rate * plan_speed),
        k_t / total,
        blended.v,
    )
    vx, vy = approach_limited(
        ops,
        config,
        blended.v * heading_cos + across * left_x,
        blended.v * heading_sin + across * left_y,
        measurement,
        (reference_velocity[0], reference_velocity[1]),
    )
    omega = blended.omega
    if ops.any(pull > 0.0):
        approach_x, approach_y, looping = final_approach(
            ops,
            config.position_gain,
            waited,
            ops.where(waiting_next, stage.leaving, stage.leaving_before),
            to_waited,
            tcp,
            ops.where(waiting_next, stage.loop_radius, stage.loop_radius_before),
        )
        last = tool_velocity(law.robot, trig, state.previous[0], state.previous[1])
        vx, vy = turned_towards(ops, (vx, vy), (approach_x, approach_y), pull, last)
        # On a loop the heading turns with the TCP's way round, so that it points along the
        # plan, not back at the waiting reference, when the arm comes onto the waypoint.
        omega = ops.branch(
            looping > 0.0,
            _turn_with_loop,
            omega,
            ops,
            config.heading_gain,
            omega,
            heading,
            pull * looping,
            approach_x,
            approach_y,
        )
    vx, vy = reach_limited(
        ops,
        config.reach_rate,
        law.full_reach,
        vx,
        vy,
        tcp,
        (reference_velocity[0], reference_velocity[1]),
    )
    lead = height_lead(ops, waiting_next, to_next, reference_to_next)
    vz = height_rate(
        ops,
        config.height_gain,
        (reference[2], reference_velocity[2]),
        waited[2],
        tcp[2],
        ops.max(pull, lead),
    )
    rate1, rate2 = joint_rates(ops, law.robot, theta2, trig, vx, vy, config.damping)
    wanted, limited = _limit(ops, law, (rate1, rate2, -vz), state.previous)
    command, no_safe_motion = filtered(
        ops,
        wanted,
        box(ops, law.limits, joints, state.previous),
        barrier(ops, law.robot, config, law.obstacle, trig, tcp, measurement, state.previous),
    )
    limited = limited | (command[0] != wanted[0]) | (command[1] != wanted[1])
    limited = limited | (command[2] != wanted[2])

    heading = wrap_angle(heading + omega * config.period)
    output = ControlOutput(
        command,
        tcp,
        reference,
        plan_speed,
        measurement,
        tracking,
        avoiding,
        k_t,
        k_c,
        blended,
        heading,
        limited,
        progress,
        no_safe_motion,
        waited,
    )
    return output, LawState(heading, side, command, progress, rate, rate_slope, t, reached)


def _near_stop(ops: Ops, robot: RobotConfig, theta1: Real, theta2: Real) -> Mask:
    """theta1 or theta2 within NEAR_STOP of a stop, or theta2 of 0 (full reach, which the
    elbow cannot pass), where a way round the obstacle may close."""
    return (
        (theta1 - robot.theta1_min < NEAR_STOP)
        | (robot.theta1_max - theta1 < NEAR_STOP)
        | (theta2 - robot.theta2_min < NEAR_STOP)
        | (robot.theta2_max - theta2 < NEAR_STOP)
        | (abs(theta2) < NEAR_STOP)
    )


def _turn_with_loop(
    ops: Ops,
    heading_gain: float,
    omega: Real,
    heading: Real,
    steer: Real,
    approach_x: Real,
    approach_y: Real,
) -> Real:
    """The turn rate of an arm on a loop (``steer``: how far, 0..1)."""
    turn = wrap_angle(ops.atan2(approach_y, approach_x) - heading)
    return omega + steer * (heading_gain * turn - omega)


def rate_towards(
    ops: Ops, period: float, rate: Real, slope: Real, wanted: Real
) -> tuple[Real, Real]:
    """The plan's rate and its slope a tick on, moving towards ``wanted`` by at most 1 per
    RATE_CHANGE. Down at once, so that the plan waits where the gate closes; up with the slope
    changing by at most that per RATE_RAMP, and no steeper than lets the rate still come to
    ``wanted`` without passing it (where it would pass, it lands there, the slope the one
    that lands)."""
    steepest = 1.0 / RATE_CHANGE
    bend = steepest / RATE_RAMP
    step = bend * period
    gap = wanted - rate
    # From this slope, lowered by a step a tick, the rate covers the gap and no more.
    half = 0.5 * step
    braking = ops.min(steepest, ops.sqrt(half * half + 2.0 * bend * ops.max(gap, 0.0)) - half)
    upward = ops.max(slope, 0.0)  # a rate falling stops falling at once, as it began
    rising = ops.clip(braking, upward - step, upward + step)
    slope = ops.where(gap > 0.0, rising, ops.max(gap / period, -steepest))
    moved = rate + slope * period
    landed = (moved - wanted) * gap >= 0.0
    return ops.where(landed, wanted, moved), ops.where(landed, gap / period, slope)


def _last_speed(ops: Ops, robot: RobotConfig, trig: ArmTrig, previous: Point3) -> Real:
    """The TCP's speed in the plane at the joint rates last commanded, ``previous``."""
    return length(ops, *tool_velocity(robot, trig, previous[0], previous[1]))


def _wanted_rate(ops: Ops, stage: Stage, progress: Real, behind: Real, away_passed: Real) -> Real:
    """How fast the plan's time should run: 1, except near an inner waypoint while the arm
    is off the way to it (:func:`_behind`'s ``behind``) or, once the waypoint's time is past,
    away from it in space (``away_passed``, -inf once passed), where the plan slows down to
    wait.

    The gate of waypoint p_j closes over the GATE_APPROACH before its time and stays closed
    after it for as long as the arm, not yet past p_j, is away from it: a waypoint is a task,
    and the plan does not move on from it undone. How much it holds the plan back grows
    across BEHIND with how far off the arm is; both are smoothsteps, and :func:`step` limits
    how fast the rate changes (RATE_CHANGE).
    """
    low, high = BEHIND
    approach = stage.approach
    gate = smoothstep(ops, (progress - stage.time + approach) / approach)
    hold = ops.where(stage.inner, gate * smoothstep(ops, (behind - low) / (high - low)), 0.0)
    hold = ops.where(
        stage.inner_before,
        ops.max(hold, smoothstep(ops, (away_passed - low) / (high - low))),
        hold,
    )
    return 1.0 - hold


def _goal(
    ops: Ops,
    stage: Stage,
    progress: Real,
    behind: Real,
    tcp: tuple[Real, Real, Real],
    to_next: Real,
) -> tuple[Real, Real]:
    """The next waypoint p_j that DM looks towards.

    ``behind``: how far the arm is off the way from the reference to p_j (half of what going
    by the TCP adds to the distance, -inf once p_j is passed). Over the last GOAL_HANDOVER of
    a segment the point slides from p_j to p_j+1, so that the direction DM measures from does
    not jump when the plan moves on; but only as far as the arm keeps to the way to p_j
    (GOAL_KEPT): an arm still on its way round the obstacle keeps looking at p_j; and not
    where p_j+1 lies back the way the arm comes in (GOAL_BACK; ``tcp``, ``to_next``: the
    TCP and its plane distance to p_j).
    """
    low, high = GOAL_KEPT
    handover = stage.handover
    share = smoothstep(ops, (progress - stage.time + handover) / handover) * (
        1.0 - smoothstep(ops, (behind - low) / (high - low))
    )
    slide_x, slide_y = stage.goal_slide
    if ops.any(share > 0.0):
        back = (slide_x * (tcp[0] - stage.point[0]) + slide_y * (tcp[1] - stage.point[1])) / (
            ops.max(length(ops, slide_x, slide_y) * to_next, 1e-9)
        )
        low, high = GOAL_BACK
        turned_back = smoothstep(ops, (back - low) / (high - low))
        share = share * (1.0 - ops.where(behind > -math.inf, turned_back, 0.0))
    goal_x, goal_y = stage.point[0], stage.point[1]
    return (
        ops.where(stage.inner, goal_x + share * slide_x, goal_x),
        ops.where(stage.inner, goal_y + share * slide_y, goal_y),
    )


def _depth(ops: Ops, room: Real, to_waypoint: Real) -> Real:
    """How deep a TCP ``to_waypoint`` from a waypoint (in the plane) is in its free room
    ``room``, 0..1."""
    half = room / 2.0
    inside = 1.0 - smoothstep(ops, (to_waypoint - half) / ops.where(room <= 0.0, 1.0, half))
    return ops.where(room <= 0.0, 0.0, inside)


def _at_waypoint(
    ops: Ops,
    stage: Stage,
    progress: Real,
    to_waypoints: tuple[Real, Real],
    depths: tuple[Real, Real],
    clearance: Real,
) -> Real:
    """How deep the TCP is in the free room of the waypoint it heads for, 0..1.

    Inside the circle the obstacle leaves free around p_j the straight way to p_j cannot
    touch it, so AO is not needed there: 1 within half its radius, fading to 0 at its edge.
    The TCP also counts as in the free room of p_j as far as the obstacle (``clearance``) is
    farther than p_j (over CLEAR_WAY): no straight way to p_j inside that disc round the TCP
    can touch it, and AO would only take the arm round an obstacle beyond p_j. Over the
    GATE_RELEASE after p_j-1's time the room of p_j-1 hands over to that of p_j, so that k_C
    never jumps when the plan moves on (``to_waypoints``: the TCP's plane distances to p_j
    and p_j-1; ``depths``: their :func:`_depth`).
    """
    share = smoothstep(ops, (progress - stage.time_before) / stage.release)
    depth_next, depth_before = depths
    present = clearance < math.inf
    if ops.any(present):
        to_next, to_before = to_waypoints
        clear_next = smoothstep(ops, (clearance - to_next) / stage.clear_way)
        clear_before = smoothstep(ops, (clearance - to_before) / stage.clear_way_before)
        depth_next = ops.where(present, ops.max(depth_next, clear_next), depth_next)
        depth_before = ops.where(present, ops.max(depth_before, clear_before), depth_before)
    return ops.max(share * depth_next, (1.0 - share) * depth_before)


def final_approach(
    ops: Ops,
    gain: float,
    point: Point3,
    leaving: tuple[Real, Real],
    away: Real,
    tcp: Point3,
    loop_radius: Real,
) -> tuple[Real, Real, Real]:
    """The planar velocity that brings the TCP onto the waypoint the plan waits for
    (``point``; ``away``: the TCP's plane distance to it; ``leaving``: the plan's way out of
    it; ``loop_radius``: its LOOP_RADIUS), and how far it is a loop, 0..1.

    Straight at the waypoint, ``gain`` times the way to it, wherever that way does not point
    against the plan's way out: an arm on the far side, brought straight back, would come
    onto the waypoint against the plan and have to turn round on it when the plan moved on (a
    stop). There the arm goes round the circle of ``loop_radius`` that touches the plan's way at
    the waypoint on the arm's side, in the sense that comes round to the waypoint along the
    plan, at the same speed, until the straight way no longer points against the plan; it
    then comes in across the plan. The two hand over by the angle between the straight way
    and the plan's way out (LOOP_AGAINST), not by where the arm is: handed over along the
    plan, the loop's way out and the straight way back cancelled just past the waypoint. The
    handover turns the way the arm goes from the one to the other at the same speed: added
    as vectors, the two nearly cancelled where they pointed apart, and an arm a few
    millimetres off the waypoint stood still.
    """
    to_x, to_y = point[0] - tcp[0], point[1] - tcp[1]
    straight_x, straight_y = gain * to_x, gain * to_y
    out_x, out_y = leaving
    against = -(to_x * out_x + to_y * out_y) / ops.where(away == 0.0, 1.0, away)
    share = ops.where(away == 0.0, 0.0, smoothstep(ops, against / LOOP_AGAINST))
    return ops.branch(
        share != 0.0,
        _loop,
        (straight_x, straight_y, 0.0),
        ops,
        gain,
        share,
        (to_x, to_y),
        leaving,
        point,
        tcp,
        away,
        loop_radius,
    )


def _loop(
    ops: Ops,
    gain: float,
    share: Real,
    to_point: tuple[Real, Real],
    leaving: tuple[Real, Real],
    point: Point3,
    tcp: Point3,
    away: Real,
    loop_radius: Real,
) -> tuple[Real, Real, Real]:
    """:func:`final_approach` where it is a loop, ``share`` of the way."""
    to_x, to_y = to_point
    out_x, out_y = leaving
    side = ops.where(out_x * to_y - out_y * to_x <= 0.0, 1.0, -1.0)
    radial_x = tcp[0] - (point[0] - side * loop_radius * out_y)
    radial_y = tcp[1] - (point[1] + side * loop_radius * out_x)
    radius = length(ops, radial_x, radial_y)
    off = (radius - loop_radius) / loop_radius
    # Round the circle, and in towards it or out as far as the arm is off it.
    way_x = -side * radial_y - off * radial_x
    way_y = side * radial_x - off * radial_y
    share = ops.where(radius != 0.0, share, 0.0)
    straight = ops.atan2(to_y, to_x)
    angle = straight + share * wrap_angle(ops.atan2(way_y, way_x) - straight)
    speed = gain * away
    return (speed * ops.cos(angle), speed * ops.sin(angle), share)


def turned_towards(
    ops: Ops,
    start: tuple[Real, Real],
    end: tuple[Real, Real],
    share: Real,
    last: tuple[Real, Real],
) -> tuple[Real, Real]:
    """``share`` of the way from planar velocity ``start`` to ``end``: the two added as
    vectors where they point the same way within 90 degrees; where they point apart, up to
    TURN_SHARE of the way from that to the way turned and the speed changed apart (in full
    from TURN_APART), so that an arm pulled back the way it came swings round instead of
    standing while the two cancel.

    Where they point all but opposite (more than TURN_KEEP apart), the way turns round the
    side the velocity last commanded, ``last``, lies on, where it lies to a side (TURN_ASIDE):
    the short way round changes side from one tick to the next there, and the arm's way
    flipped with it, through a stop (``user`` seed 8,000,000, 999, the hard switch)."""
    added_x = start[0] + share * (end[0] - start[0])
    added_y = start[1] + share * (end[1] - start[1])
    start_speed = length(ops, start[0], start[1])
    end_speed = length(ops, end[0], end[1])
    sizes = start_speed * end_speed
    cosine = (start[0] * end[0] + start[1] * end[1]) / ops.where(sizes > 0.0, sizes, 1.0)
    apart = ops.where(sizes > 0.0, smoothstep(ops, -cosine / TURN_APART), 0.0)
    return ops.branch(
        apart > 0.0,
        _turned,
        (added_x, added_y),
        ops,
        start,
        end,
        (start_speed, end_speed),
        share,
        TURN_SHARE * apart,
        (added_x, added_y),
        last,
    )


def _turned(
    ops: Ops,
    start: tuple[Real, Real],
    end: tuple[Real, Real],
    speeds: tuple[Real, Real],
    share: Real,
    turning: Real,
    added: tuple[Real, Real],
    last: tuple[Real, Real],
) -> tuple[Real, Real]:
    """:func:`turned_towards` where the two point apart: ``turning`` of the way from their
    sum, ``added``, to the way turned."""
    start_angle = ops.atan2(start[1], start[0])
    turn = wrap_angle(ops.atan2(end[1], end[0]) - start_angle)
    last_side = start[0] * last[1] - start[1] * last[0]  # > 0: last lies to start's left
    aside = abs(last_side) > TURN_ASIDE * speeds[0] * length(ops, last[0], last[1])
    other_side = (abs(turn) > TURN_KEEP) & (last_side * turn < 0.0) & aside
    turn = ops.where(other_side, turn - ops.where(turn > 0.0, 2.0 * math.pi, -2.0 * math.pi), turn)
    angle = start_angle + share * turn
    speed = speeds[0] + share * (speeds[1] - speeds[0])
    return (
        added[0] + turning * (speed * ops.cos(angle) - added[0]),
        added[1] + turning * (speed * ops.sin(angle) - added[1]),
    )


def approach_pull(
    ops: Ops,
    rate: Real,
    depth: Real,
    away: Real,
    clearance: Real,
    room: Real,
    clear_way: Real,
    beyond: Real,
    obstacle: Section,
    midway: tuple[Real, Real],
) -> Real:
    """How far the final approach takes over from the blended command, 0..1: as far as the
    plan waits (1 - ``rate``), in the waited waypoint's free room (``depth``, :func:`_depth`)
    and, once the plan all but waits (``rate`` below WAITING_RATE) for an arm within
    WAITING_REACH of it (``away``), wherever the straight way to it is clear. So too, however
    far, for an arm ``beyond`` the waypoint (m past it along the plan's way) within
    WAITING_REACH of the plan's line there: AO brings arms out past a waypoint the plan comes
    to from the other side, and PT, seeing them ahead of a reference short of it, crawled on
    away from the waypoint until they stood.

    The straight way is clear where the discs the obstacle leaves free round the TCP
    (``clearance``) and round the waypoint (``room``) cover it: their radii add up to more than
    the way, by ``clear_way`` in full. Without this an arm carried just past a waypoint near
    the obstacle, outside its free room, was left to PT, which saw it ahead of a reference
    waiting short of the waypoint and crawled on at a share of a plan's speed that the wait
    took to nothing: a stop, until the plan had nearly stopped. Or those two discs cover it
    with the one round the point ``midway`` between them (its clearance from ``obstacle``, the
    inflated section): an arm carried 15 mm past a waypoint 8 mm from the obstacle, 7 mm from
    it, had a way back along the obstacle that the two alone did not cover, and crawled away
    until it stood (``edge_obstacle`` seed 5,000,000, 639 fuzzy).
    """
    in_room = (1.0 - rate) * depth
    return ops.branch(
        (rate < WAITING_RATE) & ((away < WAITING_REACH[1]) | (beyond > 0.0)),
        _waiting_pull,
        in_room,
        ops,
        rate,
        in_room,
        away,
        (clearance, room),
        clear_way,
        beyond,
        obstacle,
        midway,
    )


def _waiting_pull(
    ops: Ops,
    rate: Real,
    in_room: Real,
    away: Real,
    free: tuple[Real, Real],
    clear_way: Real,
    beyond: Real,
    obstacle: Section,
    midway: tuple[Real, Real],
) -> Real:
    """:func:`approach_pull` where the plan all but waits for an arm within WAITING_REACH,
    or past the waypoint (``free``: the radii of the free discs round the TCP and round the
    waypoint)."""
    clearance, room = free
    midway_clearance = nearest_to(ops, obstacle, *midway)[0]
    covered = ops.max(
        clearance + room - away,
        midway_clearance + ops.min(clearance, room) - away / 2.0,
    )
    low, high = WAITING_REACH
    # Past the waypoint, the way to the plan's line there: the same as to the waypoint as
    # the arm comes past it, so the pull does not jump.
    off = ops.where(beyond > 0.0, ops.sqrt(ops.max(away * away - beyond * beyond, 0.0)), away)
    waiting = (1.0 - smoothstep(ops, rate / WAITING_RATE)) * (
        1.0 - smoothstep(ops, (off - low) / (high - low))
    )
    clear = smoothstep(ops, covered / clear_way)
    return ops.max(in_room, (1.0 - rate) * waiting * clear)


def height_rate(
    ops: Ops, gain: float, reference: tuple[Real, Real], waited: Real, tcp: Real, aim: Real
) -> Real:
    """The height loop's vertical speed: to the reference's height (``reference``: it and
    its vertical speed, fed forward), or ``aim`` (0..1) of the way to the height of the
    waypoint waited for, where the final approach pulls or the height leads
    (:func:`height_lead`): a fixed point, so only ``1 - aim`` of the plan's vertical speed is
    fed forward. Fed forward in full, it carried an arm the plan held at a waypoint 2 mm
    below it, and the arm stood in the plane while it came back (``edge_speed`` seed 4, 823)."""
    height, speed = reference
    return (1.0 - aim) * speed + gain * (height + aim * (waited - height) - tcp)


def height_lead(ops: Ops, ahead: Mask, to_next: Real, reference_to_next: Real) -> Real:
    """How far the height loop aims from the reference's height to that of the waypoint p_j
    it heads for, 0..1: the share of the way from the reference to p_j (in the plane) that
    the TCP has already come, once it is HEIGHT_LEAD nearer p_j than the reference.

    AO may carry the arm far ahead of the plan, and PT lets the plan catch up at a crawl
    (AHEAD_SPEED_FRACTION); the height, which follows the reference, would lag, and an arm
    over a waypoint in the plane but above it would stand there while it came down. Led so,
    the height is about the plan's at the TCP's place on the way to p_j. Within
    HEIGHT_LEAD_NEAR of p_j it leads from a few millimetres ahead. ``ahead``: p_j is the
    waypoint waited for (not p_j-1); ``to_next`` and ``reference_to_next``: |TCP p_j| and
    |ref p_j| in the plane.
    """
    ahead_by = reference_to_next - to_next
    leading = ahead & (ahead_by > 0.0)
    low, high = HEIGHT_LEAD
    far, near = HEIGHT_LEAD_NEAR
    ahead_low, ahead_high = HEIGHT_LEAD_NEAR_AHEAD
    gate = ops.max(
        smoothstep(ops, (ahead_by - low) / (high - low)),
        smoothstep(ops, (far - to_next) / (far - near))
        * smoothstep(ops, (ahead_by - ahead_low) / (ahead_high - ahead_low)),
    )
    divisor = ops.where(leading, reference_to_next, 1.0)
    return ops.where(leading, ahead_by / divisor * gate, 0.0)


def capped_along(
    ops: Ops, vx: Real, vy: Real, nx: Real, ny: Real, allowed: Real, planned: tuple[Real, Real]
) -> tuple[Real, Real]:
    """``(vx, vy)`` with its part along the unit vector ``(nx, ny)`` (towards a boundary) cut
    to at most ``allowed``, the rest of it kept, and some of what is cut turned into motion
    along the boundary the way the plan goes (``planned``: the reference's planar velocity).

    An arm whose way pointed straight at a boundary (PT's, back to a plan that bends through
    the obstacle's margin; AO's, tilted out towards full reach) stood there while the plan
    moved on, or slid along it the wrong way, into the corner between the two. So what is
    cut slides it, up to PT's crawl (AHEAD_SPEED_FRACTION of the plan's speed, no slower than
    CRAWL_SPEED_MIN) the plan's way along: in full where the plan goes along the boundary
    at that fraction of its speed or more; where it heads more nearly straight at it, the
    share it goes along, and none where it heads straight at it.
    """
    excess = vx * nx + vy * ny - allowed
    cut = excess > 0.0
    if not ops.any(cut):
        return vx, vy
    capped_x = ops.where(cut, vx - excess * nx, vx)
    capped_y = ops.where(cut, vy - excess * ny, vy)
    planned_along = planned[1] * nx - planned[0] * ny
    way = ops.where(planned_along >= 0.0, 1.0, -1.0)
    along_x, along_y = -ny * way, nx * way  # along the boundary, the way the plan goes
    planned_speed = length(ops, planned[0], planned[1])
    share = ops.clip(
        abs(planned_along) / ops.max(AHEAD_SPEED_FRACTION * planned_speed, 1e-9), 0.0, 1.0
    )
    slide = share * crawl_speed(ops, planned_speed)
    slid = ops.clip(
        slide - (capped_x * along_x + capped_y * along_y), 0.0, ops.max(excess, 0.0) * share
    )
    return capped_x + slid * along_x, capped_y + slid * along_y


def approach_limited(
    ops: Ops,
    config: ControllerConfig,
    vx: Real,
    vy: Real,
    measurement: ObstacleMeasurement,
    planned: tuple[Real, Real],
) -> tuple[Real, Real]:
    """The TCP's planar velocity without what moves it towards the obstacle's margin faster
    than ``approach_rate`` times its clearance less the safety filter's ``safety_buffer`` (or
    at all, once within the buffer); motion along the obstacle is kept, and what is cut
    slides the arm along it the way the plan goes (``capped_along``).

    Eq. 30 blends turn rates as well as speeds: where PT and AO pull the heading opposite
    ways, the heading turns slowly while both speeds carry the arm on, and the heading can
    sweep across the obstacle. With the approach cut so, the clearance falls at most
    exponentially, and the arm slides along the margin until the heading has turned. (Cut
    along the heading instead, the arm stalled where the two turn rates cancelled.) Both
    modes have it: it is a limit on the output, like the joint limits, not part of the blend.

    It aims at the floor the safety filter keeps: aimed at the margin itself, it left the
    arm moving in at 5 mm/s a millimetre out, and the filter's push back, in joint rates,
    took most of the motion along the obstacle as well. The slide: an arm whose way pointed
    straight into the margin stood there while the plan moved on (``edge_obstacle`` seed 4,
    431 and seed 6,000,000, 877, the hard switch).
    """
    to_x, to_y = measurement.to_nearest
    gap = length(ops, to_x, to_y)
    valid = measurement.present & (gap > 0.0)
    if not ops.any(valid):
        return vx, vy
    clearance = measurement.clearance
    divisor = ops.where(valid, gap, 1.0)
    inside = clearance < 0.0
    nx = ops.where(inside, -to_x, to_x) / divisor
    ny = ops.where(inside, -to_y, to_y) / divisor
    allowed = config.approach_rate * ops.max(clearance - config.safety_buffer, 0.0)
    limited_x, limited_y = capped_along(ops, vx, vy, nx, ny, allowed, planned)
    return ops.where(valid, limited_x, vx), ops.where(valid, limited_y, vy)


def reach_limited(
    ops: Ops,
    reach_rate: float,
    full_reach: float,
    vx: Real,
    vy: Real,
    tcp: Point3,
    planned: tuple[Real, Real],
) -> tuple[Real, Real]:
    """The TCP's planar velocity without what moves it outwards faster than ``reach_rate``
    times its distance from the arm's full reach; motion along the reach circle is kept, and
    what is cut slides the arm along it the way the plan goes (``capped_along``).

    At full stretch the arm cannot move inwards (the radial row of the Jacobian vanishes
    with sin theta2, and the damped inverse gives nothing there), so an arm carried outwards
    past a waypoint near full reach would stay stretched beyond it and be slid back onto it
    (a stop). With this limit the arm comes to the boundary only exponentially, and the
    heading has time to turn along it. The slide: AO's way round an obstacle reaching in
    from beyond full reach, tilted outwards, was cut to the reach circle's way into the
    corner with the obstacle, where the arm stood (``edge_obstacle`` seed 8,000,000, 805).
    """
    radius = length(ops, tcp[0], tcp[1])
    valid = radius > 0.0
    divisor = ops.where(valid, radius, 1.0)
    allowed = reach_rate * ops.max(full_reach - radius, 0.0)
    limited_x, limited_y = capped_along(
        ops, vx, vy, tcp[0] / divisor, tcp[1] / divisor, allowed, planned
    )
    return ops.where(valid, limited_x, vx), ops.where(valid, limited_y, vy)


def _limit(ops: Ops, law: Law, wanted: Point3, previous: Point3) -> tuple[Point3, Mask]:
    """Joint speed, then acceleration limits, each by one common scale factor.

    Scaling all joints together keeps the direction the TCP moves in (speed limit) and the
    direction of the change (acceleration limit), unlike clipping each joint on its own.
    """
    # (A size that is 0 is never over its limit: + (size == 0.0) only keeps its unused
    # quotient finite.)
    # (Written out: the loops over the three joints cost the scalar step 2 % more.)
    (w0, w1, w2), (p0, p1, p2) = wanted, previous
    speed0, speed1, speed2 = law.speed_limits
    step0, step1, step2 = law.step_limits
    scale = 1.0
    size = abs(w0)
    scale = ops.where(size * scale > speed0, speed0 / (size + (size == 0.0)), scale)
    size = abs(w1)
    scale = ops.where(size * scale > speed1, speed1 / (size + (size == 0.0)), scale)
    size = abs(w2)
    scale = ops.where(size * scale > speed2, speed2 / (size + (size == 0.0)), scale)
    step_scale = 1.0
    change = abs(w0 * scale - p0)
    step_scale = ops.where(
        change * step_scale > step0, step0 / (change + (change == 0.0)), step_scale
    )
    change = abs(w1 * scale - p1)
    step_scale = ops.where(
        change * step_scale > step1, step1 / (change + (change == 0.0)), step_scale
    )
    change = abs(w2 * scale - p2)
    step_scale = ops.where(
        change * step_scale > step2, step2 / (change + (change == 0.0)), step_scale
    )
    command = (
        p0 + (w0 * scale - p0) * step_scale,
        p1 + (w1 * scale - p1) * step_scale,
        p2 + (w2 * scale - p2) * step_scale,
    )
    return command, (scale < 1.0) | (step_scale < 1.0)


def _leaving(trajectory: Trajectory, index: int) -> tuple[float, float]:
    """The plan's unit direction of travel in the plane at waypoint ``index``; (0, 0) at the
    first and last waypoint and where the plan passes slower than PLANNED_REST_SPEED: the
    way an arm on a loop enters it."""
    if index == 0 or index == len(trajectory.times) - 1:
        return (0.0, 0.0)
    velocity = trajectory.evaluate(trajectory.times[index])[1]
    speed = length(SCALAR, velocity[0], velocity[1])
    if speed < PLANNED_REST_SPEED:
        return (0.0, 0.0)
    return (velocity[0] / speed, velocity[1] / speed)


class ControlLaw:
    """The controller's law for one scenario: call :meth:`step` once per tick."""

    def __init__(
        self,
        robot: RobotConfig,
        config: ControllerConfig,
        trajectory: Trajectory,
        obstacle: EllipticCylinder | None,
        mode: Mode,
        coordination: Coordination | None = None,
    ) -> None:
        self.trajectory = trajectory
        self.stages = stages_of(trajectory, obstacle, config.ao_pass_margin)
        coordination = coordination or Coordination.of(config.sensing_range, config.switch_distance)
        self.law = law_of(robot, config, obstacle, mode is Mode.FUZZY, coordination)
        self.reset()

    @classmethod
    def for_scenario(cls, scenario: Scenario) -> ControlLaw:
        """The law of ``scenario``: its robot, gains, plan, obstacle and coordination mode."""
        return cls(
            scenario.robot,
            scenario.controller,
            plan_of(scenario),
            scenario.obstacle,
            scenario.mode,
        )

    def reset(self) -> None:
        """Back to the state before the first tick."""
        self.state = first_state(self.trajectory)
        self._stage = 0

    def resume_from_rest(self) -> None:
        """Take up control again after zero was commanded (a hold): the next command ramps up
        from zero within the acceleration limit instead of jumping back to the last one."""
        self.state = self.state._replace(previous=(0.0, 0.0, 0.0))

    def at(self, progress: float) -> Stage:
        """The stage the reference is on at plan time ``progress`` (never going back)."""
        stages = self.stages
        while progress >= stages[self._stage].end:
            self._stage += 1
        return stages[self._stage]

    def step(self, t: float, joint_position: tuple[float, float, float]) -> ControlOutput:
        """One tick at the plan's clock ``t`` (it stops while the node holds)."""
        output, self.state = step(SCALAR, self.law, self, self.state, t, joint_position)
        return output

    @property
    def progress(self) -> float:
        """The plan's time the reference stands at."""
        return float(self.state.progress)

    @property
    def side(self) -> int:
        """AO's TL/TR choice (+1, -1; 0: none)."""
        return int(self.state.side)
