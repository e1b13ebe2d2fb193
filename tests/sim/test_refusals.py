"""The plan check's refusals (no way round the obstacle) against the brute force of
``sim/passability.py``, on tasks across obstacles of every size anywhere in the annulus: a
task with no way round is always refused, and the study's report counts the refusals and
names those the brute force finds a way for."""

from __future__ import annotations

import math
import random

from controller.planner import check_plan
from protocol.config import RobotConfig
from protocol.errors import ConfigError, NoWayRoundError
from protocol.geometry import EllipticCylinder
from protocol.kinematics import reach_radii
from protocol.scenario import Scenario, Waypoint, check_scenario
from sim.passability import Verdict, way_round
from sim.study.refusals import Check, brute_force, refusal_report, refused_segment

INNER, OUTER = reach_radii(RobotConfig())


def crossings(count: int, seed: int) -> list[Scenario]:
    """Tasks of one segment across an obstacle 5-45 cm long standing across the annulus."""
    draws, tasks = random.Random(seed), []
    while len(tasks) < count:
        angle, radius = draws.uniform(-1.5, 1.5), draws.uniform(INNER + 0.02, OUTER - 0.05)
        long = draws.uniform(0.05, 0.45)
        short = draws.uniform(0.03, min(long, 0.1))
        x, y = radius * math.cos(angle), radius * math.sin(angle)
        away = long / 2.0 + 0.05
        ends = [
            (x - side * away * math.sin(angle), y + side * away * math.cos(angle), 0.2)
            for side in (-1, 1)
        ]
        task = Scenario(
            name=f"crossing-{len(tasks)}",
            waypoints=(Waypoint(0.0, *ends[0]), Waypoint(3.0, *ends[1])),
            obstacle=EllipticCylinder(x, y, long, short, 0.3, angle, 0.02),
        )
        try:
            check_scenario(task)
        except ConfigError:
            continue
        tasks.append(task)
    return tasks


def test_a_task_with_no_way_round_is_always_refused() -> None:
    refused: list[tuple[Scenario, NoWayRoundError]] = []
    verdicts = []
    for task in crossings(60, seed=1):
        try:
            check_plan(task)
        except NoWayRoundError as error:
            refused.append((task, error))
            assert refused_segment(error) == 0
        verdict = way_round(task, 0)
        verdicts.append(verdict)
        if verdict is Verdict.NO_WAY:
            assert refused and refused[-1][0] is task, f"{task.name}: no way round, accepted"
    assert any(verdict is Verdict.NO_WAY for verdict in verdicts)
    assert any(verdict is Verdict.WAY for verdict in verdicts)
    report = refusal_report(60, refused, checked=len(refused))
    assert f"refused: {len(refused)} (rule 6: {len(refused)})" in report
    named = {
        line.split(": ")[1].split(" (")[0]
        for line in report.splitlines()
        if "though the rule holds" in line
    }
    assert named == {
        task.name for task, error in refused if brute_force(task, error) is Check.WRONG
    }
