"""The brute-force passability checker: a way past an obstacle in open space, none where it seals
the annulus between the inner limit and the outer reach, and a gap at the inner limit found
exactly as wide as the grid can tell."""

from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path

import networkx as nx
import numpy as np
import pytest

from controller.detour import LIMIT_ROOM
from protocol.config import ControllerConfig
from protocol.geometry import EllipticCylinder
from protocol.kinematics import Elbow, reach_radii
from protocol.scenario import Scenario, Waypoint, check_scenario
from sim.passability import FreeSpace, Verdict, _Regions, main, way_round

INFLATION = 0.02
MARGIN = ControllerConfig().ao_pass_margin


def across_x_axis(
    centre: float, long_diameter: float, height: float = 0.45, elbow: Elbow = Elbow.DOWN
) -> Scenario:
    """A segment from y = -0.15 to y = 0.15 at x = 0.4, across a thin obstacle lying along
    the x axis (so along the arm's radius) from ``centre``."""
    sign = 1.0 if elbow is Elbow.DOWN else -1.0
    scenario = Scenario(
        "across",
        (
            Waypoint(0.0, 0.4, -0.15 * sign, 0.3),
            Waypoint(3.0, 0.4, 0.15 * sign, 0.3),
            Waypoint(5.0, 0.3, 0.3 * sign, 0.3),
        ),
        EllipticCylinder(centre, 0.0, long_diameter, 0.04, height, 0.0, INFLATION),
        elbow=elbow,
    )
    check_scenario(scenario)
    return scenario


def with_inner_gap(gap: float) -> Scenario:
    """The obstacle reaching past the outer reach, its grown inner end ``gap`` from the
    radius where theta2 is LIMIT_ROOM inside its stop (the room rule 6 keeps)."""
    robot = Scenario("", (), None).robot
    room = dataclasses.replace(
        robot, theta2_min=robot.theta2_min + LIMIT_ROOM, theta2_max=robot.theta2_max - LIMIT_ROOM
    )
    inner = reach_radii(room)[0]
    long_diameter = 0.5
    half = long_diameter / 2.0 + INFLATION + MARGIN
    return across_x_axis(inner + gap + half, long_diameter)


def test_an_obstacle_in_open_space_leaves_a_way() -> None:
    assert way_round(across_x_axis(0.4, 0.06), 0) is Verdict.WAY


def test_an_obstacle_sealing_the_annulus_leaves_none() -> None:
    sealed = across_x_axis(0.4, 0.5)  # grown, from 0.115 to 0.685 m: the reach is 0.187-0.6
    assert way_round(sealed, 0) is Verdict.NO_WAY
    assert way_round(sealed, 1) is Verdict.WAY  # the next segment does not cross it


def test_the_elbow_up_arm_is_searched_on_its_own_side() -> None:
    assert way_round(across_x_axis(0.4, 0.06, elbow=Elbow.UP), 0) is Verdict.WAY
    assert way_round(across_x_axis(0.4, 0.5, elbow=Elbow.UP), 0) is Verdict.NO_WAY


def test_an_obstacle_below_the_path_blocks_nothing() -> None:
    assert way_round(across_x_axis(0.4, 0.5, height=0.1), 0) is Verdict.WAY


def test_a_gap_at_the_inner_limit_is_found_if_wide_enough() -> None:
    assert way_round(with_inner_gap(0.03), 0) is Verdict.WAY
    assert way_round(with_inner_gap(-0.005), 0) is Verdict.NO_WAY


def test_a_gap_within_the_room_rule_6_keeps_from_a_stop_is_no_way() -> None:
    """1 mm short of the room's circle (1.5 mm beyond the stop's): no way, at any grid."""
    assert way_round(with_inner_gap(-0.001), 0, math.radians(0.05)) is Verdict.NO_WAY
    assert way_round(with_inner_gap(0.001), 0, math.radians(0.05)) is Verdict.WAY


def test_a_gap_narrower_than_the_grid_can_tell_is_unsure_until_the_grid_is_finer() -> None:
    narrow = with_inner_gap(0.002)
    coarse = FreeSpace(narrow)
    assert coarse.half_move > 0.002  # the grid's error is wider than the gap
    assert coarse.verdict(0) is Verdict.UNSURE
    assert way_round(narrow, 0, math.radians(0.2)) is Verdict.WAY


def test_a_waypoint_inside_the_grown_obstacle_has_no_way_out() -> None:
    scenario = across_x_axis(0.4, 0.06)
    moved = EllipticCylinder(0.4, -0.105, 0.06, 0.04, 0.45, 0.0, INFLATION)
    near = Scenario(scenario.name, scenario.waypoints, moved)
    check_scenario(near)  # outside the inflated obstacle ...
    assert moved.grown(MARGIN).contains(0.4, -0.15)  # ... but inside the grown one
    assert way_round(near, 0) is Verdict.NO_WAY


def test_bad_segments_and_resolutions_are_refused() -> None:
    scenario = across_x_axis(0.4, 0.06)
    with pytest.raises(ValueError, match="segment"):
        way_round(scenario, 2)
    with pytest.raises(ValueError, match="resolution"):
        FreeSpace(scenario, 0.0)


@pytest.mark.parametrize("seed", range(20))
def test_the_flood_fill_agrees_with_a_graph_search(seed: int) -> None:
    rng = np.random.default_rng(seed)
    free = rng.random((14, 9)) < rng.uniform(0.4, 0.8)
    graph = nx.grid_2d_graph(*free.shape)
    graph.remove_nodes_from([node for node in list(graph) if not free[node]])
    nodes = list(itertools.product(range(free.shape[0]), range(free.shape[1])))
    regions = _Regions(free)
    for first, second in rng.choice(len(nodes), (10, 2)):
        start, end = nodes[first], nodes[second]
        expected = start in graph and end in graph and nx.has_path(graph, start, end)
        assert regions.connected(start, end) == expected


def test_the_command_prints_each_segments_verdict(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "sealed.toml"
    path.write_text(
        'name = "sealed"\n'
        "[obstacle]\nx = 0.4\ny = 0.0\nlong_diameter = 0.5\nshort_diameter = 0.04\n"
        "height = 0.45\n"
        + "".join(
            f"[[waypoints]]\nt = {t}\nx = {x}\ny = {y}\nz = 0.3\n"
            for t, x, y in ((0.0, 0.4, -0.15), (3.0, 0.4, 0.15), (5.0, 0.3, 0.3))
        )
    )
    assert main([str(path)]) == 0
    assert capsys.readouterr().out.splitlines() == [
        "sealed: waypoints[0..1]: no way",
        "sealed: waypoints[1..2]: way",
    ]
    assert main([str(tmp_path / "missing.toml")]) == 2
