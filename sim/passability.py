"""Whether a segment has any way round the obstacle: a brute-force search in joint space.

A study tool, not part of the controller: it checks the controller's refusals
(:class:`protocol.errors.NoWayRoundError`) and the generator's families against the plain
question "is there any path from waypoint ``i`` to waypoint ``i + 1`` that stays outside the
obstacle grown by the pass margin (``ControllerConfig.ao_pass_margin``: where AO steers) and
inside the joint limits by the room rule 6 keeps (``controller.detour.LIMIT_ROOM``), with the
scenario's elbow?" The arm keeps its elbow for a whole run (it never passes theta2 = 0), so
the search space is theta1 x theta2 on that elbow's side; the height joint is left to the
plan, and the obstacle blocks the plane only if the planned heights of the segment dip below
its inflated top.

The search is a grid over the joints (:data:`RESOLUTION` apart) flood-filled from the first
waypoint. A grid can only bound the answer, so both claims are made with the grid's own error
(how far the tool can move between neighbouring nodes, :class:`FreeSpace`): a way is claimed
only along nodes far enough clear that the moves between them stay clear too, and no way only
if even the nodes that some clear pose is near do not connect. Between the two, the answer is
:attr:`Verdict.UNSURE`: a gap about as narrow as the grid's step; a finer resolution decides.

``python -m sim.passability FILE...`` gives each segment's verdict for scenario files (a
refused task written out, for instance).
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
from bisect import bisect_left, bisect_right
from collections.abc import Sequence
from enum import Enum
from functools import cached_property

import numpy as np
import numpy.typing as npt

from controller.detour import LIMIT_ROOM
from controller.planner import plan_of
from protocol.errors import ConfigError, ScaraError
from protocol.geometry import Section, nearest_point, to_local
from protocol.kinematics import Elbow, arm_trig, inverse, tool_position
from protocol.ops import ARRAY
from protocol.scenario import Scenario, load_scenario

RESOLUTION = math.radians(0.5)
"""rad between grid nodes on each joint: the tool moves at most about 4 mm between neighbours."""
HEIGHT_SAMPLES = 200
"""Planned points of a segment whose heights are compared with the obstacle's top."""

Grid = npt.NDArray[np.float64]
Mask = npt.NDArray[np.bool_]


class Verdict(Enum):
    """The answer for one segment."""

    WAY = "way"
    """A path exists: the search found one whose every move stays clear."""
    NO_WAY = "no way"
    """No path exists, not even one squeezing between the nodes (or a waypoint is itself
    inside the grown obstacle, so no path can start or end outside it)."""
    UNSURE = "unsure"
    """The only gaps are about as narrow as the grid's error: ask at a finer resolution."""


class FreeSpace:
    """A scenario's joint grid with each node's clearance from the grown obstacle, built once
    and asked about each segment (:meth:`verdict`).

    Moving theta1 by ``d1`` and theta2 by ``d2`` moves the tool by at most
    ``(a1 + a2) |d1| + a2 |d2|`` (the Jacobian's columns are at most that long). Hence:

    - a move between neighbouring nodes stays clear if both nodes are at least half its
      length clear (``clear``: the nodes a way is searched along);
    - every pose lies within half a step of a node on each joint, so a clear pose makes that
      node at least ``-slack`` clear (``near``: if these do not connect, nothing does).
    """

    def __init__(self, scenario: Scenario, resolution: float = RESOLUTION) -> None:
        if not resolution > 0.0:
            raise ConfigError("resolution", f"must be positive, got {resolution!r}")
        robot = scenario.robot
        self.scenario = scenario
        low2, high2 = robot.theta2_min + LIMIT_ROOM, robot.theta2_max - LIMIT_ROOM
        if scenario.elbow is Elbow.DOWN:
            low2 = max(low2, 0.0)
        else:
            high2 = min(high2, 0.0)
        self.theta1 = _nodes(
            robot.theta1_min + LIMIT_ROOM, robot.theta1_max - LIMIT_ROOM, resolution
        )
        self.theta2 = _nodes(low2, high2, resolution)
        step1 = float(self.theta1[1] - self.theta1[0])
        step2 = float(self.theta2[1] - self.theta2[0])
        self.reach = robot.a1 + robot.a2
        """The longest the tool's lever on theta1 gets."""
        self.half_move = max(self.reach * step1, robot.a2 * step2) / 2.0
        self.slack = (self.reach * step1 + robot.a2 * step2) / 2.0
        obstacle = scenario.obstacle
        self.grown = (
            None if obstacle is None else obstacle.grown(scenario.controller.ao_pass_margin)
        )
        self.clearance = self._clearances()
        self._plan = plan_of(scenario)

    def _clearances(self) -> Grid:
        """Each node's signed clearance from the grown section (inf: no obstacle). Exact only
        where it matters: elsewhere the distance from the centre less the long semi-axis, a
        lower bound that is already above every threshold (twice the slack)."""
        shape = (len(self.theta1), len(self.theta2))
        if self.grown is None:
            return np.full(shape, math.inf)
        theta1, theta2 = (g.ravel() for g in np.meshgrid(self.theta1, self.theta2, indexing="ij"))
        x, y, _ = tool_position(self.scenario.robot, arm_trig(ARRAY, theta1, theta2), 0.0)
        section = self.grown.section()
        bound = np.hypot(x - section.x, y - section.y) - section.a
        near = np.flatnonzero(bound < 2.0 * self.slack)
        per_node = Section(*(np.full(len(near), value) for value in section))
        local = to_local(per_node, x[near], y[near])
        bound[near] = nearest_point(ARRAY, per_node, *local)[0]
        return np.asarray(bound.reshape(shape))

    def verdict(self, segment: int) -> Verdict:
        """Whether a way from waypoint ``segment`` to the next one exists."""
        waypoints = self.scenario.waypoints
        if not 0 <= segment < len(waypoints) - 1:
            raise ConfigError("segment", f"must be 0 to {len(waypoints) - 2}, got {segment}")
        if self.grown is None or not self._blocks(segment):
            return Verdict.WAY
        ends = []
        for point in waypoints[segment : segment + 2]:
            clearance = self.grown.clearance(point.x, point.y)
            if clearance < 0.0:
                return Verdict.NO_WAY
            joints = inverse(self.scenario.robot, point.x, point.y, point.z, self.scenario.elbow)
            ends.append((joints, clearance))
        nodes = [self._nearest(joints) for joints, _ in ends]
        if not self._near.connected(*nodes):
            return Verdict.NO_WAY
        joined = all(self._joins(j, c, n) for (j, c), n in zip(ends, nodes, strict=True))
        if joined and self._clear.connected(*nodes):
            return Verdict.WAY
        return Verdict.UNSURE

    @cached_property
    def _near(self) -> _Regions:
        """The nodes that a clear pose may be near."""
        return _Regions(self.clearance >= -self.slack)

    @cached_property
    def _clear(self) -> _Regions:
        """The nodes between which every move stays clear."""
        return _Regions(self.clearance >= self.half_move)

    def _blocks(self, segment: int) -> bool:
        """Whether the planned heights of the segment dip below the obstacle's inflated top."""
        obstacle = self.scenario.obstacle
        assert obstacle is not None
        start, end = (w.t for w in self.scenario.waypoints[segment : segment + 2])
        heights = self._plan.sample(np.linspace(start, end, HEIGHT_SAMPLES))[0][:, 2]
        return bool(heights.min() < obstacle.height + obstacle.inflation)

    def _nearest(self, joints: tuple[float, float, float]) -> tuple[int, int]:
        return (_nearest_node(self.theta1, joints[0]), _nearest_node(self.theta2, joints[1]))

    def _joins(
        self, joints: tuple[float, float, float], clearance: float, node: tuple[int, int]
    ) -> bool:
        """Whether the straight move from a waypoint (its joints and clearance) to its nearest
        node stays clear: the two clearances cover the move's length."""
        turn1 = abs(joints[0] - self.theta1[node[0]])
        turn2 = abs(joints[1] - self.theta2[node[1]])
        length = self.reach * turn1 + self.scenario.robot.a2 * turn2
        return bool(clearance + self.clearance[node] >= length)


def way_round(scenario: Scenario, segment: int, resolution: float = RESOLUTION) -> Verdict:
    """Whether any way from waypoint ``segment`` to the next stays clear (:class:`FreeSpace`)."""
    return FreeSpace(scenario, resolution).verdict(segment)


def _nodes(low: float, high: float, resolution: float) -> Grid:
    """Nodes from ``low`` to ``high``, both included, at most ``resolution`` apart."""
    return np.linspace(low, high, max(2, math.ceil((high - low) / resolution) + 1))


def _nearest_node(nodes: Grid, value: float) -> int:
    return int(np.clip(np.rint((value - nodes[0]) / (nodes[1] - nodes[0])), 0, len(nodes) - 1))


class _Regions:
    """The 4-connected regions of a grid's free nodes, found over the runs of free nodes along
    each row: a few thousand runs rather than 10^5 nodes."""

    def __init__(self, free: Mask) -> None:
        self.free = free
        edges = np.diff(np.pad(free.astype(np.int8), ((0, 0), (1, 1))), axis=1)
        rows, begins = np.nonzero(edges == 1)
        ends = np.nonzero(edges == -1)[1]
        first = np.searchsorted(rows, np.arange(len(free) + 1)).tolist()
        spans = list(itertools.pairwise(first))
        self.begins: list[list[int]] = [begins[low:high].tolist() for low, high in spans]
        self.ends: list[list[int]] = [ends[low:high].tolist() for low, high in spans]
        self.labels: list[list[int]] = [[-1] * len(row) for row in self.begins]
        count = 0
        for row, labels in enumerate(self.labels):
            for run, label in enumerate(labels):
                if label < 0:
                    self._flood(row, run, count)
                    count += 1

    def _flood(self, row: int, run: int, label: int) -> None:
        """Give ``label`` to the run and every run connected to it."""
        self.labels[row][run] = label
        stack = [(row, run)]
        while stack:
            row, run = stack.pop()
            begin, end = self.begins[row][run], self.ends[row][run]
            for other in (row - 1, row + 1):
                if not 0 <= other < len(self.labels):
                    continue
                # The runs of the other row overlapping [begin, end).
                head = bisect_right(self.ends[other], begin)
                for neighbour in range(head, bisect_left(self.begins[other], end)):
                    if self.labels[other][neighbour] < 0:
                        self.labels[other][neighbour] = label
                        stack.append((other, neighbour))

    def connected(self, first: tuple[int, int], second: tuple[int, int]) -> bool:
        """Whether both nodes are free and in one region."""
        return bool(self.free[first] and self.free[second]) and self._label(first) == self._label(
            second
        )

    def _label(self, node: tuple[int, int]) -> int:
        row, column = node
        return self.labels[row][bisect_right(self.begins[row], column) - 1]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m sim.passability",
        description="Whether each segment of scenario files has any way round the obstacle "
        "grown by the pass margin, within the joint limits by the room rule 6 keeps, and "
        "with the scenario's elbow: a brute-force search over a grid of the joints.",
    )
    parser.add_argument("scenarios", nargs="+", help="scenario TOML files or packaged names")
    parser.add_argument(
        "--resolution",
        type=float,
        default=math.degrees(RESOLUTION),
        metavar="DEG",
        help=f"degrees between grid nodes (default {math.degrees(RESOLUTION):g}); finer "
        "settles an 'unsure'",
    )
    args = parser.parse_args(argv)
    status = 0
    for source in args.scenarios:
        try:
            scenario = load_scenario(source)
            space = FreeSpace(scenario, math.radians(args.resolution))
            for segment in range(len(scenario.waypoints) - 1):
                verdict = space.verdict(segment)
                print(f"{scenario.name}: waypoints[{segment}..{segment + 1}]: {verdict.value}")
        except ScaraError as error:
            print(f"{source}: {error}", file=sys.stderr)
            status = 2
    return status


if __name__ == "__main__":
    raise SystemExit(main())
