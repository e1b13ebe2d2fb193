"""Scenarios and tasks: the packaged ones load; bad ones, from a file or over the wire, fail
before anything moves, naming the field; a task of as many waypoints as the schema allows fits
one transfer."""

from __future__ import annotations

import copy
import json
import math
import tomllib
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from protocol.errors import ConfigError
from protocol.scenario import (
    MAX_DURATION,
    MAX_TASK_BYTES,
    SCENARIO_DIR,
    Mode,
    Scenario,
    encode_task,
    load_scenario,
    parse_scenario,
    parse_task,
    read_task,
    scenario_document,
)
from protocol.validation import shipped_schemas

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
        (
            _set(["waypoints"], [{"t": t / 10, "x": 0.3, "y": 0.0, "z": 0.2} for t in range(33)]),
            "waypoints",
        ),
        (_set(["waypoints", 0], [0.0, 0.3, -0.25, 0.25]), "waypoints[0]"),
        (_set(["waypoints", 2, "z"], True), "waypoints[2].z"),
        (_set(["settle_time"], -1.0), "settle_time"),
        (_set(["settle_time"], 4000.0), "waypoints"),
        (_set(["timeout"], 0.0), "timeout"),
        (_set(["timeout"], -3.0), "timeout"),
        (_set(["timeout"], math.inf), "timeout"),
        (_set(["timeout"], "late"), "timeout"),
        (_set(["timeout"], 6.4), "timeout"),  # below the plan's 5.5 s span + 1 s settling
        (_set(["timeout"], 3600.5), "timeout"),
        (_set(["name"], 7), "name"),
        (_set(["obstacle"], 0.3), "obstacle"),
        (_set(["obstacle", "margin"], -0.01), "obstacle.margin"),
        (_set(["obstacle", "yaw_deg"], math.nan), "obstacle.yaw_deg"),
        (_set(["obstacle", "height"], -0.1), "obstacle.height"),
        (_set(["obstacle", "long_diameter"], math.inf), "obstacle.long_diameter"),
        (_set(["obstacle", "short_diameter"], 0.5), "obstacle.short_diameter"),
        (_set(["obstacle", "colour"], "red"), "obstacle.colour"),
        (_set(["mode"], "psychic"), "mode"),
        (_set(["elbow"], "sideways"), "elbow"),
        (_set(["controller"], {"rate_hz": 0.0}), "controller.rate_hz"),
        (_set(["controller"], {"gain": 1.0}), "controller.gain"),
        (_set(["robot"], {"a1": -1.0}), "robot.a1"),
        (_set(["robot"], {"theta1_min_deg": "low"}), "robot.theta1_min_deg"),
        (_set(["robot"], {"theta1_min": -2.0}), "robot.theta1_min"),
        (_set(["robot"], {"d3_min": 0.3}), "robot.d3_min"),
        (_set(["plant"], {"substeps": 4.0}), "plant.substeps"),
        (_set(["controller"], {"ao_speed_min": 0.5}), "controller.ao_speed_min"),
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


def test_the_timeout_defaults_to_twice_the_plan_and_round_trips_when_set() -> None:
    default = parse_scenario(REFERENCE)
    assert default.timeout is None and default.time_limit == 2 * 5.5 + 1.0 + 10.0
    assert "timeout" not in scenario_document(default)
    longest = parse_scenario(broken(_set(["settle_time"], MAX_DURATION - 5.5)))
    assert longest.time_limit == MAX_DURATION  # the default never exceeds the bound
    for timeout in (6.5, 30.0, MAX_DURATION):
        scenario = parse_scenario(broken(_set(["timeout"], timeout)))
        assert scenario.time_limit == timeout
        again = parse_scenario(json.loads(json.dumps(scenario_document(scenario))))
        assert again == replace(scenario, description="")  # a document has no description
        task = parse_task(read_task(encode_task(scenario, 9))[1], BASE)
        assert task.timeout == timeout


def test_unknown_scenario_name_lists_the_packaged_ones() -> None:
    with pytest.raises(ConfigError, match="reference"):
        load_scenario("no-such-scenario")


BASE = Scenario("operator", (), None)


def _wire(document: Any) -> bytes:
    return json.dumps({"ticket": 3} | document).encode()


@pytest.mark.parametrize(
    ("payload", "field"),
    [
        (b"NaN", "document"),
        (b"{", "document"),
        (_wire({"waypoints": REFERENCE["waypoints"], "speed": 2}), "speed"),
        (_wire({"waypoints": REFERENCE["waypoints"][:1]}), "waypoints"),
        (_wire({"mode": "fuzzy"}), "waypoints"),
        (
            _wire(
                {
                    "waypoints": [
                        REFERENCE["waypoints"][0],
                        REFERENCE["waypoints"][1] | {"x": math.nan},
                    ]
                }
            ),
            "waypoints[1].x",
        ),
        (
            _wire(
                {
                    "waypoints": REFERENCE["waypoints"],
                    "obstacle": REFERENCE["obstacle"] | {"height": math.inf},
                }
            ),
            "obstacle.height",
        ),
        (_wire({"waypoints": REFERENCE["waypoints"], "robot": {"a1": 0.3}}), "robot"),
        (_wire({"waypoints": REFERENCE["waypoints"], "elbow": None}), "elbow"),
        (json.dumps({"ticket": 256, "waypoints": REFERENCE["waypoints"]}).encode(), "ticket"),
    ],
)
def test_bad_tasks_over_the_wire_name_the_field(payload: bytes, field: str) -> None:
    """Python's json reads NaN and Infinity, which JSON does not have: refused like a string."""
    with pytest.raises(ConfigError) as error:
        parse_task(read_task(payload)[1], BASE)
    assert error.value.field == field, str(error.value)


def _circle(count: int) -> list[dict[str, float]]:
    """``count`` reachable waypoints on an arc, a second apart, each value a long decimal."""
    return [
        {
            "t": index + 0.123456789012345,
            "x": 0.4 * math.cos(-1.5 + 3.0 * index / count) + 1.23456789e-9,
            "y": 0.4 * math.sin(-1.5 + 3.0 * index / count) - 1.23456789e-9,
            "z": 0.250000000000001,
        }
        for index in range(count)
    ]


def test_a_task_of_as_many_waypoints_as_the_schema_allows_fits_one_transfer() -> None:
    """The schema's cap is the parser's, and what keeps a task within one ISO-TP transfer."""
    cap = shipped_schemas()["definitions"]["$defs"]["waypoints"]["maxItems"]
    obstacle = REFERENCE["obstacle"] | {"x": 0.15, "y": 0.0}  # inside the arc, clear of it
    document = {"name": "longest", "waypoints": _circle(cap), "obstacle": obstacle}
    longest = parse_task(document, BASE)
    assert len(longest.waypoints) == cap
    assert len(encode_task(longest, 255)) <= MAX_TASK_BYTES
    with pytest.raises(ConfigError) as error:
        parse_task(document | {"waypoints": _circle(cap + 1)}, BASE)
    assert error.value.field == "waypoints" and f"at most {cap}" in str(error.value)
