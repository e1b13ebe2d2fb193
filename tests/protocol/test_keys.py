"""The key space and its JSON Schemas: one schema per state key, per command and per reply
(beside those of the project's documents), each a closed Draft 2020-12 schema shipped with the
package."""

from __future__ import annotations

import jsonschema
import pytest

from protocol.keys import (
    COMMANDS,
    STATE_KEYS,
    alive_key,
    check_robot,
    command_key,
    schema,
    schema_names,
    state_key,
)

DOCUMENTS = {"definitions", "task", "scenario-file", "fuzzy-rules", "world"}
"""The schemas of the project's documents and their shared definitions."""


def test_every_key_command_and_reply_has_a_schema_and_nothing_else_does() -> None:
    expected = {*STATE_KEYS, *(f"cmd-{name}" for name in COMMANDS), "reply", "error"}
    assert set(schema_names()) == expected | DOCUMENTS


@pytest.mark.parametrize("name", sorted(set(schema_names()) - {"definitions"}))
def test_each_schema_is_a_valid_closed_draft_2020_12_schema(name: str) -> None:
    document = schema(name)
    jsonschema.Draft202012Validator.check_schema(document)
    assert document["$schema"].endswith("2020-12/schema")
    closed = document.get("additionalProperties", document.get("unevaluatedProperties"))
    assert closed is False  # a typo in a field is an error
    assert document["$id"].endswith(f"/{name}.schema.json")


def test_keys_are_built_under_the_robot_name() -> None:
    assert state_key("arm2", "joints") == "scara/arm2/joints"
    assert command_key("arm2", "estop") == "scara/arm2/cmd/estop"
    assert alive_key("arm2", "plant") == "scara/arm2/alive/plant"
    with pytest.raises(ValueError, match="not a state key"):
        state_key("arm2", "cmd")
    with pytest.raises(ValueError, match="not a command"):
        command_key("arm2", "fly")


@pytest.mark.parametrize("robot", ["", "arm/1", "arm*", "a b", "$*"])
def test_a_robot_name_is_one_plain_key_chunk(robot: str) -> None:
    with pytest.raises(ValueError, match="robot name"):
        check_robot(robot)
