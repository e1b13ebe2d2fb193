"""One control step: measure, behave, coordinate, map to joints, limit (Fig. 6 end to end).

:class:`ControlLaw` is pure in the simple-pid sense: it owns the few values a controller
must remember between ticks (the unicycle heading, the TL/TR choice, the last command, where
on the plan the reference stands and how fast it moves on, the last waypoint passed) and is
handed the time and the measured joints; it knows nothing of buses or clocks.

Near an inner waypoint the plan waits for an arm that a detour has held off the way to it
(time scaling, ``docs/study.md``): the reference moves on past the waypoint once the arm has
come to it, instead of pulling the arm across the corner.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from controller.behaviours import (
    PLANNED_REST_SPEED,
    STOP,
    Command,
    avoid_obstacle,
    choose_side,
    plan_tracking,
)
from controller.coordination import AHEAD_NONE, Coordinator, make_coordinator, smoothstep
from controller.obstacle import ObstacleMeasurement, measure
from controller.planner import Trajectory, plan_of
from protocol.config import ControllerConfig, RobotConfig
from protocol.geometry import EllipticCylinder, distance, length, wrap_angle
from protocol.kinematics import forward, joint_rates_for, reach_radii
from protocol.scenario import Scenario

Point3 = tuple[float, float, float]

GOAL_HANDOVER = 0.5
"""s of plan: how long before a waypoint's time DM starts looking towards the one after it."""
BEHIND = (0.0005, 0.001)
"""m: how far the arm may be off the way from the reference to the next waypoint (see
:meth:`ControlLaw._behind`). Near the waypoint the plan slows as that grows across this span
and waits beyond it."""
PASSED = 0.0019
"""m: a waypoint the TCP came this close to counts as passed (:attr:`ControlLaw.reached`):
just inside the 2 mm a waypoint must be passed within. At 1.5 mm an arm that went by 1.6 to
1.8 mm off, within the task's tolerance, was still waited for and slid back onto the
waypoint, and that reversal was a stop (``gen-1-488``, ``gen-2026-271``, ``gen-0-2425``)."""
GATE_APPROACH = 0.4
"""s of plan before a waypoint over which the gate closes (the reference may slow to wait)."""
GATE_RELEASE = 0.2
"""s of plan after a waypoint over which its free room hands over to the next one's (see
:meth:`ControlLaw._at_waypoint`)."""
RATE_CHANGE = 0.1
"""s: the plan's rate goes from 1 to 0 or back in no less than this, so the reference never
brakes or starts harder than the arm can follow (an arm overshooting a waiting reference
would have to turn back: a stop)."""
CLEAR_WAY = 0.01
"""m: AO gives way once the obstacle is this much farther from the TCP than p_j (see
:meth:`ControlLaw._at_waypoint`). On the last segment only, an inner waypoint at the
obstacle's doorstep, approached head on, had AO take the arm round the obstacle (``gen-0-8669``:
the plan waited 3.5 s); on every segment, two of the jerk exceptions went (``gen-0-21``,
``gen-0-798``)."""
ROOM_MAX = 0.05
"""m: the free room around a waypoint (see :meth:`ControlLaw._at_waypoint`) is at most this."""
HEIGHT_LEAD = (0.01, 0.02)
"""m: how much nearer the next waypoint than the reference the TCP is when the height loop
starts to lead (see :meth:`ControlLaw._height_lead`), and when it leads in full. Led from
the first millimetre, the height changed 265 of the 286 doorstep runs of the first 1000 of
seed 0 and raised some peaks of jerk 2.3 times (``gen-0-73``); from 10 mm, 83, none by more
than 5 %."""
HEIGHT_LEAD_NEAR = (0.008, 0.002)
"""m: near p_j the height leads sooner: from this far from p_j in the plane, in full from
this near, once the TCP is HEIGHT_LEAD_NEAR_AHEAD nearer p_j than the reference. As the
reference caught up with an arm slowing onto p_j, the lead faded out below 10 mm ahead, and
the arm went by p_j 0.3 mm off in the plane but 3.7 mm below it (``gen-13-3580``: it held
still in the plane while it rose, a stop)."""
HEIGHT_LEAD_NEAR_AHEAD = (0.002, 0.004)
"""m: see HEIGHT_LEAD_NEAR. From the first millimetre ahead, the lead changed most runs and
raised the peak jerk of open ones up to 6.5 times: with the reference a millimetre or two from
p_j, that millimetre is a large share of the way, and the aim jumps."""
LOOP_RADIUS = 0.003
"""m: the radius of the circle the final approach takes an arm round, when the straight way
onto the waypoint would point against the plan (see :meth:`ControlLaw._final_approach`):
more than PASSED, and the circle stays within 6 mm of the waypoint, well inside its free
room (a waypoint is at least 20 mm clear of the inflated obstacle)."""
LOOP_AGAINST = 0.5
"""How far the straight way onto a waypoint points against the plan's way out of it (the
cosine of the angle between them, negated) where the final approach is a loop in full. From
90 degrees the straight way hands over to the loop, and from 120 degrees it loops."""
GOAL_KEPT = (0.005, 0.03)
"""m: how far off the way to p_j (as in BEHIND) the arm is when DM's look-ahead to the
following waypoint is undone: an arm still on its way round the obstacle keeps looking at
p_j."""


def capped_along(vx: float, vy: float, nx: float, ny: float, allowed: float) -> tuple[float, float]:
    """``(vx, vy)`` with its part along the unit vector ``(nx, ny)`` cut to at most
    ``allowed``; the rest of it kept (the limits on the output towards a boundary)."""
    excess = vx * nx + vy * ny - allowed
    if excess > 0.0:
        return vx - excess * nx, vy - excess * ny
    return vx, vy


def _leaving(trajectory: Trajectory, index: int) -> tuple[float, float]:
    """The plan's unit direction of travel in the plane at waypoint ``index``; (0, 0) at the
    first and last waypoint and where the plan passes slower than PLANNED_REST_SPEED."""
    if index == 0 or index == len(trajectory.times) - 1:
        return (0.0, 0.0)
    velocity = trajectory.evaluate(trajectory.times[index])[1]
    speed = length(velocity[0], velocity[1])
    if speed < PLANNED_REST_SPEED:
        return (0.0, 0.0)
    return (velocity[0] / speed, velocity[1] / speed)


@dataclass(frozen=True, slots=True)
class Windows:
    """The spans of plan, in s, over which the law's smooth changes near the end of one
    segment (and the start of the next) take place: GATE_APPROACH, GATE_RELEASE and
    GOAL_HANDOVER, each at most half the segment so that those of its two ends never
    overlap. Fixed by the plan, so worked out once, not every tick."""

    approach: float
    release: float
    handover: float

    @classmethod
    def of_segment(cls, start: float, end: float) -> Windows:
        """The windows of the segment from plan time ``start`` to ``end``."""
        half = (end - start) / 2.0
        return cls(min(GATE_APPROACH, half), min(GATE_RELEASE, half), min(GOAL_HANDOVER, half))


@dataclass(frozen=True, slots=True)
class ControlOutput:
    """The joint velocity command of one tick and what led to it (for logs and figures)."""

    command: tuple[float, float, float]
    tcp: tuple[float, float, float]
    reference: tuple[float, float, float]
    reference_speed: float
    measurement: ObstacleMeasurement
    tracking: Command
    avoiding: Command
    k_t: float
    k_c: float
    blended: Command
    heading: float
    limited: bool
    progress: float


class ControlLaw:
    """The controller's law for one scenario: call :meth:`step` once per tick."""

    def __init__(
        self,
        robot: RobotConfig,
        config: ControllerConfig,
        trajectory: Trajectory,
        obstacle: EllipticCylinder | None,
        coordinator: Coordinator,
    ) -> None:
        self.robot = robot
        self.config = config
        self.trajectory = trajectory
        self.obstacle = obstacle
        self._aim = obstacle.grown(config.ao_pass_margin) if obstacle is not None else None
        self.coordinator = coordinator
        self._room = tuple(self._free_room(point) for point in trajectory.points)
        self.leaving = tuple(_leaving(trajectory, index) for index in range(len(trajectory.times)))
        """Per waypoint, the plan's direction of travel in the plane there (unit), or (0, 0)
        at the ends and where the plan comes to rest: the way an arm on a loop enters it."""
        self.windows = tuple(
            Windows.of_segment(start, end) for start, end in itertools.pairwise(trajectory.times)
        )
        """Per segment i (from waypoint i to i + 1), its :class:`Windows`."""
        self.period = config.period
        self._speed_limits = robot.speed_limits
        self._step_limits = tuple(limit * self.period for limit in robot.accel_limits)
        self._rate_step = self.period / RATE_CHANGE
        self._full_reach = reach_radii(robot)[1]
        self.reset()

    @classmethod
    def for_scenario(cls, scenario: Scenario) -> ControlLaw:
        """The law of ``scenario``: its robot, gains, plan, obstacle and coordination mode."""
        config = scenario.controller
        return cls(
            scenario.robot,
            config,
            plan_of(scenario),
            scenario.obstacle,
            make_coordinator(scenario.mode, config.switch_distance, config.sensing_range),
        )

    def reset(self) -> None:
        """Back to the state before the first tick."""
        points = self.trajectory.points
        self.heading = math.atan2(points[1][1] - points[0][1], points[1][0] - points[0][0])
        self.side = 0
        self.previous_command: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.progress = self.trajectory.times[0]
        """The plan's time the reference stands at: advances by :attr:`rate` times t's."""
        self.rate = 1.0
        """How fast the plan's time runs against t, 0..1 (see :meth:`_wanted_rate`)."""
        self._last_t = self.progress
        self.reached = 0
        """The last waypoint the TCP has come within PASSED of."""

    def resume_from_rest(self) -> None:
        """Take up control again after zero was commanded (a hold): the next command ramps up
        from zero within the acceleration limit instead of jumping back to the last one."""
        self.previous_command = (0.0, 0.0, 0.0)

    def step(self, t: float, joint_position: tuple[float, float, float]) -> ControlOutput:
        """One tick at the plan's clock ``t`` (it stops while the node holds)."""
        config = self.config
        self.progress += self.rate * max(t - self._last_t, 0.0)
        self._last_t = t
        progress = self.progress
        theta1, theta2, d3 = joint_position
        tcp = forward(self.robot, theta1, theta2, d3)
        reference, velocity, acceleration = self.trajectory.evaluate(progress)
        index = self.trajectory.segment_index(progress)
        self._mark_reached(index, tcp)
        # Plane distances several parts of the law use: the TCP's to p_j and p_j-1, the
        # reference's to p_j.
        to_next, to_before = self._to_waypoint(index, tcp), self._to_waypoint(index - 1, tcp)
        reference_to_next = self._to_waypoint(index, reference)
        behind = self._behind(index, to_next, reference_to_next, tcp, reference)
        wanted = self._wanted_rate(progress, index, behind, self._away(index - 1, to_before))
        step = self._rate_step
        rate = self.rate = min(max(wanted, self.rate - step), self.rate + step)
        # The reference moves at rate times the plan's velocity: the path's curvature, and
        # with it the turn rate PT feeds forward, stay those of the plan.
        reference_velocity = (rate * velocity[0], rate * velocity[1], rate * velocity[2])
        squared = rate * rate
        # How deep the TCP is in the free rooms of p_j and p_j-1: for the pull and for AO.
        depth_next, depth_before = self._depth(index, to_next), self._depth(index - 1, to_before)
        waited_index = self._waited_for(index)
        waited = self.trajectory.points[waited_index]
        waiting_next = waited_index == index
        pull = (1.0 - rate) * (depth_next if waiting_next else depth_before)
        goal = self._goal(progress, index, behind)
        measurement = measure(self.obstacle, tcp, goal, config.sensing_range, self.heading)

        tracking = plan_tracking(
            config,
            self.heading,
            (tcp[0], tcp[1]),
            (reference[0], reference[1]),
            (reference_velocity[0], reference_velocity[1]),
            (squared * acceleration[0], squared * acceleration[1]),
        )
        avoiding = self._avoid(measurement, (tcp[0], tcp[1]))
        at_waypoint = self._at_waypoint(
            progress, index, (to_next, to_before), (depth_next, depth_before), measurement.clearance
        )
        k_t, k_c = self.coordinator.weights(measurement, at_waypoint)
        total = k_t + k_c
        blended = Command(
            (k_t * tracking.v + k_c * avoiding.v) / total,
            (k_t * tracking.omega + k_c * avoiding.omega) / total,
        )

        vx, vy = self._approach_limited(
            blended.v * math.cos(self.heading), blended.v * math.sin(self.heading), measurement
        )
        approach_x, approach_y, looping = self._final_approach(
            waited_index, tcp, to_next if waiting_next else to_before
        )
        vx += pull * (approach_x - vx)
        vy += pull * (approach_y - vy)
        vx, vy = self._reach_limited(vx, vy, tcp)
        lead = self._height_lead(waiting_next, to_next, reference_to_next)
        vz = (1.0 - lead) * reference_velocity[2] + config.height_gain * (
            reference[2] + max(pull, lead) * (waited[2] - reference[2]) - tcp[2]
        )
        rate1, rate2 = joint_rates_for(self.robot, theta1, theta2, vx, vy, config.damping)
        command, limited = self._limit((rate1, rate2, -vz))

        # On a loop the heading turns with the TCP's way round, so that it points along the
        # plan, not back at the waiting reference, when the arm comes onto the waypoint.
        omega = blended.omega
        if looping > 0.0:
            turn = wrap_angle(math.atan2(approach_y, approach_x) - self.heading)
            omega += pull * looping * (config.heading_gain * turn - omega)
        self.heading = wrap_angle(self.heading + omega * self.period)
        self.previous_command = command
        return ControlOutput(
            command=command,
            tcp=tcp,
            reference=(reference[0], reference[1], reference[2]),
            reference_speed=length(velocity[0], velocity[1]),
            measurement=measurement,
            tracking=tracking,
            avoiding=avoiding,
            k_t=k_t,
            k_c=k_c,
            blended=blended,
            heading=self.heading,
            limited=limited,
            progress=progress,
        )

    def _final_approach(self, index: int, tcp: Point3, away: float) -> tuple[float, float, float]:
        """The planar velocity that brings the TCP onto waypoint ``index`` (the one the plan
        waits for; ``away``: the TCP's plane distance to it), and how far it is a loop, 0..1.

        Straight at the waypoint, ``position_gain`` times the way to it, wherever that way
        does not point against the plan's way out of the waypoint (:attr:`leaving`). An arm on
        the far side, brought straight back, came onto the waypoint against the plan and had
        to turn round on it when the plan moved on: a stop (``gen-11-4651``, ``gen-13-2173``,
        ``gen-13-248``, ``gen-7-3048``). There the arm goes round the circle of LOOP_RADIUS
        that touches the plan's way at the waypoint on the arm's side, in the sense that
        comes round to the waypoint along the plan, at the same speed, until the straight
        way no longer points against the plan; it then comes in across the plan. The two
        hand over by the angle between the straight way and the plan's way out (LOOP_AGAINST),
        not by where the arm is: handed over along the plan, the loop's way out and the
        straight way back cancelled just past the waypoint, and arms that had slid back onto
        it 2 mm off stood still there instead (``gen-17-4048``).
        """
        gain = self.config.position_gain
        point = self.trajectory.points[index]
        to_x, to_y = point[0] - tcp[0], point[1] - tcp[1]
        straight_x, straight_y = gain * to_x, gain * to_y
        out_x, out_y = self.leaving[index]
        if away == 0.0:
            return straight_x, straight_y, 0.0
        share = smoothstep(-(to_x * out_x + to_y * out_y) / away / LOOP_AGAINST)
        if share == 0.0:
            return straight_x, straight_y, 0.0
        side = 1.0 if out_x * to_y - out_y * to_x <= 0.0 else -1.0
        centre_x = point[0] - side * LOOP_RADIUS * out_y
        centre_y = point[1] + side * LOOP_RADIUS * out_x
        radial_x, radial_y = tcp[0] - centre_x, tcp[1] - centre_y
        radius = length(radial_x, radial_y)
        if radius == 0.0:
            return straight_x, straight_y, 0.0
        off = (radius - LOOP_RADIUS) / LOOP_RADIUS
        way_x = (-side * radial_y - off * radial_x) / radius
        way_y = (side * radial_x - off * radial_y) / radius
        speed = gain * away / length(way_x, way_y)
        return (
            straight_x + share * (speed * way_x - straight_x),
            straight_y + share * (speed * way_y - straight_y),
            share,
        )

    def _free_room(self, point: tuple[float, ...]) -> float:
        """The radius around a waypoint that the obstacle leaves free (at most ROOM_MAX)."""
        obstacle = self.obstacle
        if obstacle is None or point[2] >= obstacle.height + obstacle.inflation:
            return ROOM_MAX
        return min(max(obstacle.clearance(point[0], point[1]), 0.0), ROOM_MAX)

    def _at_waypoint(
        self,
        progress: float,
        index: int,
        to_waypoints: tuple[float, float],
        depths: tuple[float, float],
        clearance: float,
    ) -> float:
        """How deep the TCP is in the free room of the waypoint it heads for, 0..1.

        Inside the circle the obstacle leaves free around p_j the straight way to p_j cannot
        touch it, so AO is not needed there: 1 within half its radius, fading to 0 at its
        edge. The TCP also counts as in the free room of p_j as far as the obstacle
        (``clearance``) is farther than p_j (over CLEAR_WAY): no straight way to p_j inside
        that disc round the TCP can touch it, and AO would only take the arm round an
        obstacle beyond p_j. Over the GATE_RELEASE after p_j-1's time the room of p_j-1
        hands over to that of p_j, so that k_C never jumps when the plan moves on
        (``to_waypoints``: the TCP's plane distances to p_j and p_j-1; ``depths``: their
        :meth:`_depth`, which the pull uses too).
        """
        share = smoothstep(
            (progress - self.trajectory.times[index - 1]) / self.windows[index - 1].release
        )
        depth_next, depth_before = depths
        if clearance < math.inf:
            to_next, to_before = to_waypoints
            depth_next = max(depth_next, smoothstep((clearance - to_next) / CLEAR_WAY))
            depth_before = max(depth_before, smoothstep((clearance - to_before) / CLEAR_WAY))
        return max(share * depth_next, (1.0 - share) * depth_before)

    def _to_waypoint(self, index: int, position: tuple[float, ...]) -> float:
        """The plane distance from ``position`` to waypoint ``index``."""
        point = self.trajectory.points[index]
        return length(position[0] - point[0], position[1] - point[1])

    def _depth(self, index: int, to_waypoint: float) -> float:
        """How deep a TCP ``to_waypoint`` from waypoint ``index`` (in the plane) is in its
        free room, 0..1."""
        room = self._room[index]
        if room <= 0.0:
            return 0.0
        return 1.0 - smoothstep((to_waypoint - room / 2.0) / (room / 2.0))

    def _waited_for(self, index: int) -> int:
        """The waypoint a waiting plan waits for: p_j-1 until the TCP has passed it, then p_j.

        The TCP is steered to it by ``pull`` = 1 - rate (rate limited, so smoothly) times how
        deep the TCP is in its free room (:meth:`_depth`, 0 far from it): the height loop aims
        that share of the way from the reference's height to the waypoint's, and in the plane
        the velocity goes that share of the way from the unicycle's to the final approach's
        (:meth:`_final_approach`: straight at the waypoint, or round it). A waiting reference
        stands short of the waypoint, and an arm held to it, or beside the waypoint with a
        heading it cannot reverse without stopping, would never come within PASSED while the
        plan waits for just that. Under the unicycle the arm is holonomic, the straight way to
        the centre of the free room and the loop stay in it, and the heading stays PT's
        (turning with a loop), pointing along the plan for when it moves on.
        """
        return max(index - 1, min(self.reached + 1, index))

    def _mark_reached(self, index: int, tcp: Point3) -> None:
        """Note when the TCP passes waypoint ``index - 1`` or ``index`` (within PASSED).

        AO then forgets its TL/TR choice, made on the way to that waypoint, and chooses afresh
        on the way to the next: held for the whole run, a choice made on the first segment
        took the arm the long way round an obstacle it met again on a later one, past the
        run's settling time (``gen-0-1312``, ``gen-1-987``).
        """
        points = self.trajectory.points
        for candidate in (index - 1, index):
            if candidate > self.reached and distance(tcp, points[candidate]) <= PASSED:
                self.reached = candidate
                self.side = 0

    def _behind(
        self,
        index: int,
        to_next: float,
        reference_to_next: float,
        tcp: Point3,
        reference: tuple[float, ...],
    ) -> float:
        """How far the TCP is off the way from the reference to waypoint ``index`` in the plane
        (height is the height loop's): half of what going by the TCP adds to the distance,
        (|TCP p_j| + |TCP ref| - |ref p_j|) / 2.

        It is the lag for an arm right behind the reference, zero for one on the way between
        them (ahead of the plan), and counts an arm beside the path (coming round an
        obstacle) long before the reference reaches p_j. -inf once the TCP has passed p_j
        (:attr:`reached`): nothing holds the plan back there any more. ``to_next`` and
        ``reference_to_next``: |TCP p_j| and |ref p_j|.
        """
        if index <= self.reached:
            return -math.inf
        return 0.5 * (
            to_next + length(tcp[0] - reference[0], tcp[1] - reference[1]) - reference_to_next
        )

    def _away(self, index: int, to_waypoint: float) -> float:
        """How far the TCP is from waypoint ``index`` in the plane (``to_waypoint``); -inf
        once passed.

        What holds the plan at a waypoint whose time it has passed: an arm between it and
        the reference has :meth:`_behind` near 0 without ever having been to it.
        """
        if index <= self.reached:
            return -math.inf
        return to_waypoint

    def _wanted_rate(self, progress: float, index: int, behind: float, away_passed: float) -> float:
        """How fast the plan's time should run: 1, except near an inner waypoint while the arm
        is off the way to it (:meth:`_behind`) or, once the waypoint's time is past, away from
        it (:meth:`_away`), where the plan slows down to wait for it.

        The gate of waypoint p_j closes over the GATE_APPROACH before its time and stays
        closed after it for as long as the arm, not yet past p_j, is away from it; how much
        it holds the plan back grows across BEHIND with how far off the arm is. Both are
        smoothsteps, and :meth:`step` limits how fast the rate changes (RATE_CHANGE). A gate
        that opened again over the GATE_RELEASE after p_j's time let the plan creep on while
        it waited (a hold short of 1 runs the plan's time, which opened the gate further),
        and it left an arm the final approach was bringing in 2.02 mm off (``gen-11-4085``):
        a waypoint is a task, and the plan does not move on from it undone.
        """
        times = self.trajectory.times
        low, high = BEHIND
        hold = 0.0
        if index < len(times) - 1:  # approaching inner waypoint p_j
            approach = self.windows[index - 1].approach
            gate = smoothstep((progress - times[index] + approach) / approach)
            hold = gate * smoothstep((behind - low) / (high - low))
        if index >= 2:  # past inner waypoint p_j-1's time, the arm not yet past it
            hold = max(hold, smoothstep((away_passed - low) / (high - low)))
        return 1.0 - hold

    def _goal(self, progress: float, index: int, behind: float) -> tuple[float, float]:
        """The next waypoint p_j that DM looks towards.

        Over the last GOAL_HANDOVER of a segment (at most half of it) the point slides from
        p_j to p_j+1, so that the direction DM measures from does not jump when the plan
        moves on to the next segment; but only as far as the arm keeps to the way to p_j
        (GOAL_KEPT): an arm still on its way round the obstacle keeps looking at p_j.
        """
        trajectory = self.trajectory
        goal = trajectory.points[index]
        if index + 1 >= len(trajectory.points):
            return (goal[0], goal[1])
        end = trajectory.times[index]
        handover = self.windows[index - 1].handover
        low, high = GOAL_KEPT
        share = smoothstep((progress - end + handover) / handover) * (
            1.0 - smoothstep((behind - low) / (high - low))
        )
        following = trajectory.points[index + 1]
        return (
            goal[0] + share * (following[0] - goal[0]),
            goal[1] + share * (following[1] - goal[1]),
        )

    def _avoid(self, measurement: ObstacleMeasurement, position: tuple[float, float]) -> Command:
        """AO with its TL/TR choice, held while the obstacle is ahead, or the TCP moves towards
        it (or is inside it)."""
        if (
            self._aim is None
            or not measurement.present
            or (
                max(measurement.ahead, measurement.toward) <= AHEAD_NONE
                and measurement.clearance > 0.0
            )
        ):
            self.side = 0
            return STOP
        if self.side == 0:
            self.side = choose_side(measurement)
        return avoid_obstacle(
            self.config, self._aim, measurement, self.side, self.heading, position
        )

    def _height_lead(self, ahead: bool, to_next: float, reference_to_next: float) -> float:
        """How far the height loop aims from the reference's height to that of the waypoint
        p_j it heads for, 0..1: the share of the way from the reference to p_j (in the plane)
        that the TCP has already come, once it is HEIGHT_LEAD nearer p_j than the reference.

        AO may carry the arm far ahead of the plan, and PT lets the plan catch up at a crawl
        (AHEAD_SPEED_FRACTION). The height, which follows the reference, then lags: an arm
        over a waypoint in the plane but 11 mm above it stood there while it came down, a
        stop (``gen-0-5519``). Led so, the height is about the plan's at the TCP's place on
        the way to p_j. Within HEIGHT_LEAD_NEAR of p_j it leads from a few millimetres
        ahead. ``ahead``: p_j is the waypoint waited for (not p_j-1); ``to_next`` and
        ``reference_to_next``: |TCP p_j| and |ref p_j| in the plane.
        """
        if not ahead:
            return 0.0
        ahead_by = reference_to_next - to_next
        if ahead_by <= 0.0:
            return 0.0
        low, high = HEIGHT_LEAD
        far, near = HEIGHT_LEAD_NEAR
        ahead_low, ahead_high = HEIGHT_LEAD_NEAR_AHEAD
        gate = max(
            smoothstep((ahead_by - low) / (high - low)),
            smoothstep((far - to_next) / (far - near))
            * smoothstep((ahead_by - ahead_low) / (ahead_high - ahead_low)),
        )
        return ahead_by / reference_to_next * gate

    def _approach_limited(
        self, vx: float, vy: float, measurement: ObstacleMeasurement
    ) -> tuple[float, float]:
        """The TCP's planar velocity without what moves it towards the obstacle's margin faster
        than ``approach_rate`` times its clearance (or at all, once inside the margin); motion
        along the obstacle is kept.

        Eq. 30 blends turn rates as well as speeds: where PT and AO pull the heading opposite
        ways, the heading turns slowly while both speeds carry the arm on, AO's at least
        ``ao_speed_min``, and the heading can sweep across the obstacle (``gen-0-5173``: 1 mm
        into the margin). Since AO chooses afresh at each waypoint (:meth:`_mark_reached`) the
        fuzzy mode did not collide with the limit all but off on the 11,000 generated scenarios
        tried (seed 1, and 10,000 of seed 0): it is its safety net, and it is what keeps the
        hard switch out of the margin. With the approach cut so, the clearance falls at most
        exponentially; the arm slides along the margin until the heading has turned. Cutting
        the speed along the heading instead stalled the arm against the margin where the two
        turn rates cancelled (``gen-1-553``). Both modes have it: it is a limit on the output,
        like the joint limits, not part of the blend.
        """
        if not measurement.present:
            return vx, vy
        clearance = measurement.clearance
        nx, ny = measurement.to_nearest
        gap = length(nx, ny)
        if gap == 0.0:
            return vx, vy
        if clearance < 0.0:
            nx, ny = -nx, -ny
        return capped_along(
            vx, vy, nx / gap, ny / gap, self.config.approach_rate * max(clearance, 0.0)
        )

    def _reach_limited(self, vx: float, vy: float, tcp: Point3) -> tuple[float, float]:
        """The TCP's planar velocity without what moves it outwards faster than ``reach_rate``
        times its distance from the arm's full reach; motion along the reach circle is kept.

        At full stretch the arm cannot move inwards (the radial row of the Jacobian vanishes
        with sin theta2, and the damped inverse gives nothing there), so an arm that PT's
        unicycle carries outwards past a waypoint near full reach stays stretched, 2 mm
        beyond it, and is slid back onto it: a stop (``gen-1-138``, ``gen-0-9476``: the arm
        came back to its path at a steep angle after a detour). With this limit the arm
        comes to the boundary only exponentially, and the heading has time to turn along it.
        At 5/s it slowed the way to waypoints near full reach in twice as many scenarios.
        """
        radius = length(tcp[0], tcp[1])
        if radius == 0.0:
            return vx, vy
        allowed = self.config.reach_rate * max(self._full_reach - radius, 0.0)
        return capped_along(vx, vy, tcp[0] / radius, tcp[1] / radius, allowed)

    def _limit(self, wanted: tuple[float, float, float]) -> tuple[tuple[float, float, float], bool]:
        """Joint speed, then acceleration limits, each by one common scale factor.

        Scaling all joints together keeps the direction the TCP moves in (speed limit) and the
        direction of the change (acceleration limit), unlike clipping each joint on its own.
        """
        scale = 1.0
        for rate, limit in zip(wanted, self._speed_limits, strict=True):
            if abs(rate) * scale > limit:
                scale = limit / abs(rate)
        step_scale = 1.0
        for rate, previous, limit in zip(
            wanted, self.previous_command, self._step_limits, strict=True
        ):
            change = abs(rate * scale - previous)
            if change * step_scale > limit:
                step_scale = limit / change
        command = (
            self.previous_command[0] + (wanted[0] * scale - self.previous_command[0]) * step_scale,
            self.previous_command[1] + (wanted[1] * scale - self.previous_command[1]) * step_scale,
            self.previous_command[2] + (wanted[2] * scale - self.previous_command[2]) * step_scale,
        )
        return command, scale < 1.0 or step_scale < 1.0
