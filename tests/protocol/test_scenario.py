"""Scenarios: the packaged ones load; bad ones fail before anything moves, naming the field."""

from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path
from typing import Any

import pytest

from protocol.errors import ConfigError
from protocol.scenario import SCENARIO_DIR, Mode, load_scenario, parse_scenario

REFERENCE = tomllib.loads((SCENARIO_DIR / "reference.toml").read_text())


def broken(change: Any) -> dict[str, Any]:
    document = copy.deepcopy(REFERENCE)
    change(document)
    return document


@pytest.mark.parametrize("path", sorted(SCENARIO_DIR.glob("*.toml")), ids=lambda p: p.stem)
def test_packaged_scenarios_load(path: Path) -> None:
    scenario = load_scenario(path)
    assert len(scenario.waypoints) >= 2
    assert scenario.duration > 0


def test_reference_by_name() -> None:
    scenario = load_scenario("reference")
    assert scenario.mode is Mode.FUZZY
    assert scenario.obstacle is not None
    # The straight line between waypoints 2 and 3 crosses the inflated obstacle.
    second, third = scenario.waypoints[1], scenario.waypoints[2]
    crossings = scenario.obstacle.line_crossings(second.x, second.y, third.x, third.y)
    assert crossings is not None and 0.0 < crossings[0] < 1.0


def _set(path: list[Any], value: Any) -> Any:
    def change(document: dict[str, Any]) -> None:
        target: Any = document
        for key in path[:-1]:
            target = target[key]
        target[path[-1]] = value

    return change


@pytest.mark.parametrize(
    ("change", "field"),
    [
        (_set(["waypoints", 2, "x"], math.nan), "waypoints[2].x"),
        (_set(["waypoints", 1, "t"], "soon"), "waypoints[1].t"),
        (_set(["waypoints", 2, "t"], 1.0), "waypoints[2].t"),
        (_set(["waypoints", 3, "x"], 0.9), "waypoints[3]"),
        (_set(["waypoints", 3, "x"], -0.55), "waypoints[3]"),
        (_set(["waypoints", 0, "z"], 0.05), "waypoints[0]"),
        (_set(["waypoints", 1], {"t": 1.5, "x": 0.455, "y": -0.01, "z": 0.22}), "waypoints[1]"),
        (_set(["waypoints", 1, "w"], 1.0), "waypoints[1].w"),
        (_set(["waypoints"], [{"t": 0.0, "x": 0.3, "y": 0.0, "z": 0.2}]), "waypoints"),
        (_set(["obstacle", "height"], -0.1), "obstacle.height"),
        (_set(["obstacle", "long_diameter"], math.inf), "obstacle.long_diameter"),
        (_set(["obstacle", "short_diameter"], 0.5), "obstacle.short_diameter"),
        (_set(["obstacle", "colour"], "red"), "obstacle.colour"),
        (_set(["mode"], "psychic"), "mode"),
        (_set(["elbow"], "sideways"), "elbow"),
        (_set(["controller"], {"rate_hz": 0.0}), "controller.rate_hz"),
        (_set(["controller"], {"gain": 1.0}), "controller.gain"),
        (_set(["robot"], {"a1": -1.0}), "robot.a1"),
        (_set(["plant"], {"substeps": 0}), "plant.substeps"),
        (_set(["robot"], {"speed_limit_theta2": 20.0}), "robot.speed_limit_theta2"),
        (_set(["robot"], {"theta1_max_deg": 200.0}), "robot.theta1_max"),
        (_set(["speed"], 3), "speed"),
    ],
)
def test_bad_scenarios_name_the_field(change: Any, field: str) -> None:
    with pytest.raises(ConfigError) as error:
        parse_scenario(broken(change))
    assert error.value.field == field, str(error.value)
    assert field in str(error.value)


def test_unknown_scenario_name_lists_the_packaged_ones() -> None:
    with pytest.raises(ConfigError, match="reference"):
        load_scenario("no-such-scenario")
