"""What a task may ask (controller/task_rules.py): each rule at its edge, just inside (taken,
and done in both modes) and just outside (refused by that rule, its number in the message and
its reason on the wire), and a property test over the same edges."""

from __future__ import annotations

import dataclasses
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import ROOT

from controller.task_rules import (
    JOINT_MARGIN,
    RULES,
    WAYPOINT_CLEARANCE,
    accept,
    check_task,
    load_task,
    rule_of,
)
from protocol.errors import (
    ConfigError,
    NoWayRoundError,
    PathOutsideWorkspaceError,
    PlanTooFastError,
    UnreachableWaypointError,
    WaypointInObstacleError,
    WaypointNearLimitError,
    WaypointNearObstacleError,
)
from protocol.kinematics import Elbow, forward, reach_radii
from protocol.messages import Reason, reason_of
from protocol.scenario import Mode, Scenario, Waypoint, load_scenario, task_document
from sim.simulation import simulate

REFERENCE = load_scenario("reference")
ROBOT = REFERENCE.robot


def beside(clearance: float, angle: float = -math.pi / 2) -> tuple[float, float]:
    """The point ``clearance`` outside the reference's inflated obstacle, seen from its
    centre at ``angle`` (bisection along the ray)."""
    obstacle = REFERENCE.obstacle
    assert obstacle is not None
    low, high = 0.0, 0.3
    for _ in range(80):
        middle = (low + high) / 2.0
        x = obstacle.x + middle * math.cos(angle)
        y = obstacle.y + middle * math.sin(angle)
        low, high = (middle, high) if obstacle.clearance(x, y) < clearance else (low, middle)
    return obstacle.x + high * math.cos(angle), obstacle.y + high * math.sin(angle)


def with_waypoint(index: int, x: float, y: float, scenario: Scenario = REFERENCE) -> Scenario:
    waypoints = list(scenario.waypoints)
    waypoints[index] = dataclasses.replace(waypoints[index], x=x, y=y)
    return dataclasses.replace(scenario, waypoints=tuple(waypoints))


def refusal(task: Scenario) -> ConfigError:
    with pytest.raises(ConfigError) as refused:
        check_task(task)
    return refused.value


def done_in_both_modes(task: Scenario) -> None:
    for mode in Mode:
        measures = simulate(task, mode).measures
        assert measures.outcome == "done", (mode, measures.outcome)
        assert measures.max_waypoint_miss <= 0.002 and measures.stops == 0, (mode, measures)


def test_every_rule_is_numbered_in_order_and_docs_usage_says_each_as_the_gate_does() -> None:
    assert [rule.number for rule in RULES] == list(range(1, len(RULES) + 1))
    usage = (ROOT / "docs" / "usage.md").read_text()
    section = usage.split("## What a task may ask", 1)[1].split("\n## ", 1)[0]
    for rule in RULES:
        assert f"{rule.number}. {rule.says}" in section, rule.number


@pytest.mark.parametrize("angle", [-math.pi / 2, math.pi])
def test_rule_4_a_waypoint_8_mm_from_the_obstacle_is_reached_and_one_nearer_refused(
    angle: float,
) -> None:
    inside = with_waypoint(1, *beside(WAYPOINT_CLEARANCE + 0.0002, angle))
    done_in_both_modes(check_task(inside))
    error = refusal(with_waypoint(1, *beside(WAYPOINT_CLEARANCE - 0.0002, angle)))
    assert isinstance(error, WaypointNearObstacleError) and reason_of(error) is Reason.NEAR_OBSTACLE
    assert error.field == "waypoints[1]"
    assert "7.8 mm from the inflated obstacle; a waypoint must be 8 mm or more" in str(error)
    assert str(error).endswith("(rule 4)")
    error = refusal(with_waypoint(1, REFERENCE.obstacle.x, REFERENCE.obstacle.y))  # type: ignore[union-attr]
    assert isinstance(error, WaypointInObstacleError) and rule_of(error).number == 4
    assert reason_of(error) is Reason.INSIDE_OBSTACLE


def test_rule_4_does_not_hold_a_waypoint_above_the_obstacle_back() -> None:
    obstacle = REFERENCE.obstacle
    assert obstacle is not None
    low = dataclasses.replace(REFERENCE, obstacle=dataclasses.replace(obstacle, height=0.15))
    check_task(with_waypoint(1, *beside(0.001), low))  # the waypoints at 0.22 m pass over


def at_joints(theta1: float, theta2: float) -> tuple[float, float]:
    x, y, _ = forward(ROBOT, theta1, theta2, 0.1)
    return x, y


@pytest.mark.parametrize(
    ("near", "name"),
    [
        (lambda left: (math.radians(-20.0), ROBOT.theta2_max - left), "theta2"),
        (lambda left: (ROBOT.theta1_min + left, math.radians(60.0)), "theta1"),
    ],
)
def test_rule_3_a_waypoint_1_degree_inside_its_stops_is_reached_and_one_nearer_refused(
    near: object, name: str
) -> None:
    place = near  # (left) -> (theta1, theta2)
    start = at_joints(*place(math.radians(12.0)))  # type: ignore[operator]
    free = Scenario(
        "limits",
        (Waypoint(0.0, *start, 0.25), Waypoint(2.0, 0.0, 0.0, 0.25)),
        None,
        settle_time=1.0,
    )
    inside = with_waypoint(1, *at_joints(*place(JOINT_MARGIN + math.radians(0.02))), free)  # type: ignore[operator]
    done_in_both_modes(check_task(inside))
    outside = with_waypoint(1, *at_joints(*place(JOINT_MARGIN - math.radians(0.02))), free)  # type: ignore[operator]
    error = refusal(outside)
    assert isinstance(error, WaypointNearLimitError) and reason_of(error) is Reason.NEAR_JOINT_LIMIT
    assert f"{name} " in str(error) and "must be 1 deg or more inside" in str(error)
    assert str(error).endswith("(rule 3)")


def segment(speed_peak: float) -> Scenario:
    """Two waypoints 0.3 m apart timed so that the cubic's peak speed (1.5 times its mean
    between rests) is ``speed_peak``."""
    distance = 0.3
    return Scenario(
        "speed",
        (Waypoint(0.0, 0.25, -0.15, 0.25), Waypoint(1.5 * distance / speed_peak, 0.25, 0.15, 0.25)),
        None,
        settle_time=1.0,
    )


def test_rule_7_a_plan_at_the_speed_cap_is_done_and_one_above_it_refused() -> None:
    done_in_both_modes(check_task(segment(0.599)))
    error = refusal(segment(0.601))
    assert isinstance(error, PlanTooFastError) and reason_of(error) is Reason.TOO_FAST
    assert error.field == "waypoints[0..1]" and "0.601 m/s" in str(error)
    assert str(error).endswith("(rule 7)")


def test_rule_2_a_waypoint_just_within_reach_is_taken_and_one_beyond_refused() -> None:
    _, outer = reach_radii(ROBOT)
    angle = math.radians(-30.0)

    def at(radius: float) -> Scenario:
        return with_waypoint(1, radius * math.cos(angle), radius * math.sin(angle))

    check_task(at(outer - 0.001))
    error = refusal(at(outer + 0.001))
    assert isinstance(error, UnreachableWaypointError) and str(error).endswith("(rule 2)")
    assert reason_of(error) is Reason.UNREACHABLE


def test_rules_1_5_and_6_are_numbered_where_the_document_and_the_plan_refuse() -> None:
    document = task_document(REFERENCE)
    document["waypoints"][2]["t"] = document["waypoints"][1]["t"]
    with pytest.raises(ConfigError, match=r"^waypoints\[2\]\.t: .*\(rule 1\)$"):
        accept(document, REFERENCE)
    across_the_base = with_waypoint(1, -0.3, -0.1)  # the path swings through the inner hole
    error = refusal(across_the_base)
    assert isinstance(error, PathOutsideWorkspaceError) and str(error).endswith("(rule 5)")
    obstacle = REFERENCE.obstacle
    assert obstacle is not None
    # 0.9 m by 0.06 m leaves a way round the end nearer the base, sliding round the hole
    # inside the inner reach (the brute force finds it too): done; 0.1 m wide, it is closed.
    slid = dataclasses.replace(
        REFERENCE, obstacle=dataclasses.replace(obstacle, long_diameter=0.9, short_diameter=0.06)
    )
    done_in_both_modes(check_task(slid))
    sealed = dataclasses.replace(
        REFERENCE, obstacle=dataclasses.replace(obstacle, long_diameter=0.9, short_diameter=0.1)
    )
    error = refusal(sealed)
    assert isinstance(error, NoWayRoundError) and str(error).endswith("(rule 6)")
    assert reason_of(error) is Reason.NO_WAY_ROUND


def test_a_file_comes_through_the_same_gate(tmp_path: object) -> None:
    assert load_task("reference") == REFERENCE


@settings(max_examples=60, deadline=None)
@given(
    clearance=st.floats(0.0005, 0.016),
    angle=st.floats(-math.pi, math.pi),
)
def test_a_waypoint_is_refused_exactly_when_nearer_the_obstacle_than_rule_4_allows(
    clearance: float, angle: float
) -> None:
    task = with_waypoint(1, *beside(clearance, angle))
    try:
        check_task(task)
    except (WaypointNearObstacleError, WaypointInObstacleError):
        assert clearance < WAYPOINT_CLEARANCE + 1e-6
    except ConfigError as error:  # another rule (the path, the way round): not this one's
        assert rule_of(error).number != 4
    else:
        assert clearance >= WAYPOINT_CLEARANCE - 1e-6


@settings(max_examples=60, deadline=None)
@given(
    left=st.floats(0.0, math.radians(3.0)),
    theta1=st.floats(math.radians(-120.0), math.radians(120.0)),
    elbow=st.sampled_from([Elbow.DOWN, Elbow.UP]),
)
def test_a_waypoint_is_refused_exactly_when_nearer_theta2s_stop_than_rule_3_allows(
    left: float, theta1: float, elbow: Elbow
) -> None:
    theta2 = elbow.value * (ROBOT.theta2_max - left)
    x, y, _ = forward(ROBOT, theta1, theta2, 0.1)
    task = Scenario(
        "limit", (Waypoint(0.0, 0.35, 0.0, 0.25), Waypoint(2.0, x, y, 0.25)), None, elbow=elbow
    )
    try:
        check_task(task)
    except WaypointNearLimitError:
        assert left < JOINT_MARGIN + 1e-9
    except ConfigError as error:
        assert rule_of(error).number not in (3,), error
    else:
        assert left >= JOINT_MARGIN - 1e-9


@settings(max_examples=60, deadline=None)
@given(peak=st.floats(0.3, 0.9))
def test_a_plan_is_refused_exactly_when_faster_than_rule_7_allows(peak: float) -> None:
    try:
        check_task(segment(peak))
    except PlanTooFastError:
        assert peak > REFERENCE.controller.speed_max - 1e-3
    else:
        assert peak <= REFERENCE.controller.speed_max + 1e-3
