"""The one validation path: every shipped schema is valid and its references resolve, alone or
bundled; the schemas share their shapes through the definitions rather than copy them; the
configurations and the Python names agree with the schemas; and an error names the field as
the rest of the project does, saying what the value must be."""

from __future__ import annotations

import json
import math
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import fields
from typing import Any
from urllib.parse import urljoin

import jsonschema
import pytest
from referencing import Registry
from referencing.jsonschema import DRAFT202012

from controller.fuzzy import INPUT_NAMES, OUTPUT_NAMES, OUTPUT_TERMS
from protocol.config import ControllerConfig, PlantConfig, RobotConfig
from protocol.errors import ConfigError
from protocol.scenario import Mode, load_scenario, task_document
from protocol.validation import SCHEMA_BASE, bundled, check, field_name, shipped_schemas

SCHEMAS = shipped_schemas()
DEFINITIONS = SCHEMAS["definitions"]["$defs"]
TABLES = "definitions.schema.json#/$defs/"


def references(node: Any, base: str) -> Iterator[str]:
    """Every ``$ref`` in ``node`` as an absolute URI (the base changing with each ``$id``)."""
    if isinstance(node, dict):
        base = urljoin(base, node.get("$id", ""))
        if "$ref" in node:
            yield urljoin(base, node["$ref"])
        for key, value in node.items():
            if key != "$ref":
                yield from references(value, base)
    elif isinstance(node, list):
        for value in node:
            yield from references(value, base)


def shapes(node: Any, where: str) -> Iterator[tuple[str, str]]:
    """(canonical JSON, where) of every subschema that is a shape, not a bare type or a
    reference: an object or a list with what it holds, a choice, or a type with bounds."""
    if isinstance(node, dict):
        core = {key: value for key, value in node.items() if key not in ("description", "title")}
        if "$id" not in core and (
            len(core) >= 2 or core.keys() & {"properties", "items", "enum", "const"}
        ):
            yield json.dumps(core, sort_keys=True), where
        for key, value in node.items():
            yield from shapes(value, f"{where}/{key}")
    elif isinstance(node, list):
        for index, value in enumerate(node):
            yield from shapes(value, f"{where}/{index}")


@pytest.mark.parametrize("name", sorted(SCHEMAS))
def test_every_schema_is_valid_and_its_references_resolve(name: str) -> None:
    document = SCHEMAS[name]
    jsonschema.Draft202012Validator.check_schema(document)
    assert document["$id"] == f"{SCHEMA_BASE}{name}.schema.json"
    registry: Registry[Any] = Registry().with_resources(
        (schema["$id"], DRAFT202012.create_resource(schema)) for schema in SCHEMAS.values()
    )
    resolver = registry.resolver()
    for uri in references(document, ""):
        resolver.lookup(uri)  # raises Unresolvable for a reference to nothing


@pytest.mark.parametrize("name", sorted(SCHEMAS))
def test_a_bundled_schema_stands_alone(name: str) -> None:
    """What a Zenoh subscriber or an MCAP file gets: no reference leaves the document."""
    document = bundled(name)
    jsonschema.Draft202012Validator.check_schema(document)
    alone: Registry[Any] = Registry().with_resource(
        document["$id"], DRAFT202012.create_resource(document)
    )
    resolver = alone.resolver()
    for uri in references(document, ""):
        resolver.lookup(uri)  # the empty registry retrieves nothing: embedded or unresolvable


def test_no_shape_is_written_in_two_schemas() -> None:
    places: dict[str, set[str]] = defaultdict(set)
    for name, document in SCHEMAS.items():
        for shape, where in shapes(document, name):
            places[shape].add(where)
    copied = {
        shape: sorted(where)
        for shape, where in places.items()
        if len({place.split("/")[0] for place in where}) > 1
    }
    assert not copied, (
        f"shapes written in more than one schema, for definitions.schema.json: {copied}"
    )


def test_every_definition_is_used() -> None:
    used = {
        uri.partition("#/$defs/")[2]
        for document in SCHEMAS.values()
        for uri in references(document, "")
        if uri.startswith(f"{SCHEMA_BASE}definitions.schema.json#")
    }
    assert used == set(DEFINITIONS)


def test_the_configurations_and_names_in_the_code_are_those_of_the_schemas() -> None:
    assert set(DEFINITIONS["robot"]["properties"]) == set(RobotConfig().table())
    assert set(DEFINITIONS["controller"]["properties"]) == {
        spec.name for spec in fields(ControllerConfig)
    }
    assert set(DEFINITIONS["plant"]["properties"]) == {spec.name for spec in fields(PlantConfig)}
    assert DEFINITIONS["mode"]["enum"] == [mode.value for mode in Mode]
    rules = SCHEMAS["fuzzy-rules"]
    assert tuple(rules["properties"]["inputs"]["properties"]) == INPUT_NAMES
    assert tuple(rules["properties"]["outputs"]["properties"]) == OUTPUT_NAMES
    assert tuple(rules["$defs"]["output_term"]["enum"]) == OUTPUT_TERMS
    peaks = rules["$defs"]["output"]["properties"]["peaks"]["properties"]
    assert tuple(peaks) == OUTPUT_TERMS


def test_what_the_project_writes_fits_its_schemas() -> None:
    reference = load_scenario("reference")
    task = task_document(reference)
    check(task, "task.schema.json")
    check(task, "scenario.schema.json")  # what the bridge publishes on scara/<robot>/scenario
    check(RobotConfig().table(), f"{TABLES}robot")


@pytest.mark.parametrize(
    ("document", "table", "error"),
    [
        ({"time_constant": -0.01}, "plant", "plant.time_constant: must be positive, got -0.01"),
        (
            {"time_constant": math.nan},
            "plant",
            "plant.time_constant: must be a finite number, got nan",
        ),
        (
            {"time_constant": "fast"},
            "plant",
            "plant.time_constant: must be a finite number, got 'fast'",
        ),
        ({"substeps": 4.0}, "plant", "plant.substeps: must be an integer, got 4.0"),
        ({"substeps": True}, "plant", "plant.substeps: must be an integer, got True"),
        ({"substeps": 101}, "plant", "plant.substeps: must be from 1 to 100, got 101"),
        ({"rate_hz": 50}, "controller", "controller.rate_hz: must be from 100 to 1000, got 50"),
        ({"damping": -1.0}, "controller", "controller.damping: must not be negative, got -1.0"),
        (
            {"gain": 1.0},
            "plant",
            "plant.gain: unknown field; known: substeps, time_constant",
        ),
        ([1.0], "plant", "plant: must be an object (a TOML table), got [1.0]"),
        ({"x": 0.4}, "obstacle", "obstacle.y: missing"),
        ("up", "mode", "mode: must be 'fuzzy' or 'conventional', got 'up'"),
        (
            [{"t": 0.0, "x": 0.3, "y": 0.0, "z": 0.2}],
            "waypoints",
            "waypoints: must hold at least 2 entries, got 1",
        ),
        (
            [{"t": float(t), "x": 0.3, "y": 0.0, "z": 0.2} for t in range(33)],
            "waypoints",
            "waypoints: must hold at most 32 entries, got 33",
        ),
        (
            [{"t": 0.0, "x": 0.3, "y": 0.0, "z": 0.2}, {"t": 1.0, "x": 0.3, "y": 0.0}],
            "waypoints",
            "waypoints[1].z: missing",
        ),
    ],
)
def test_an_error_names_the_field_and_says_what_the_value_must_be(
    document: Any, table: str, error: str
) -> None:
    with pytest.raises(ConfigError) as raised:
        check(document, f"{TABLES}{table}", table)
    assert str(raised.value) == error
    assert raised.value.field == error.partition(": ")[0]


def test_field_names_are_written_as_the_project_writes_them() -> None:
    assert field_name("waypoints", 3, "x") == "waypoints[3].x"
    assert field_name("", "obstacle", "height") == "obstacle.height"
    assert field_name("rules", 0) == "rules[0]"
    assert field_name() == ""
