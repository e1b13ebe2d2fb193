"""The world a plant simulates, as it travels on WorldUpload: read back as sent, and anything
else refused naming the field."""

from __future__ import annotations

import json

import pytest

from protocol.errors import ConfigError
from protocol.scenario import load_scenario
from protocol.world import LAST_WORLD, STARTUP_WORLD, World, next_world, read_world

REFERENCE = load_scenario("reference")


def test_a_world_reads_back_as_it_was_sent_with_or_without_an_obstacle() -> None:
    world = World.of(REFERENCE, 7)
    assert read_world(world.encode()) == world
    empty = World(8, None, 0.01)
    assert read_world(empty.encode()) == empty
    assert empty.touched() is None


def test_the_touched_obstacle_is_grown_by_the_tool_radius_only() -> None:
    touched = World.of(REFERENCE, 1).touched()
    assert touched is not None and REFERENCE.obstacle is not None
    assert touched.inflation == pytest.approx(REFERENCE.tool_radius)
    assert touched.long_diameter == REFERENCE.obstacle.long_diameter


def test_world_numbers_go_round_1_to_255_leaving_0_to_the_start_up_world() -> None:
    assert next_world(STARTUP_WORLD) == 1
    assert next_world(LAST_WORLD) == 1
    assert {next_world(number) for number in range(256)} == set(range(1, 256))


@pytest.mark.parametrize(
    ("payload", "field"),
    [
        (b"\xff", "world"),
        (b"[" * 40 + b"]" * 40, "world"),
        (json.dumps({"world": 0, "obstacle": None}).encode(), "world"),
        (json.dumps({"world": 3}).encode(), "obstacle"),
        (json.dumps({"world": 3, "obstacle": {"x": 0.4}}).encode(), "obstacle"),
        (json.dumps({"world": 3, "obstacle": None, "colour": 1}).encode(), "colour"),
    ],
    ids=["not-utf8", "too-deep", "world-0", "no-obstacle", "bad-obstacle", "unknown-field"],
)
def test_anything_else_is_refused_naming_the_field(payload: bytes, field: str) -> None:
    with pytest.raises(ConfigError) as refused:
        read_world(payload)
    assert refused.value.field.startswith(field), refused.value
