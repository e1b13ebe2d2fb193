"""Fuzzing the scenario and task parsers (``protocol/scenario.py``).

Inputs: the packaged scenario files as TOML text edited as bytes and as lines (cut, repeated,
keys given twice), their tables with values replaced anywhere (huge integers, NaN and
infinities, wrong types, empty or deep tables) written back as TOML, and task documents and
transfers broken the same way. Properties: :func:`load_scenario`, :func:`parse_scenario`,
:func:`parse_task` and :func:`read_task` raise only :class:`ConfigError`, naming a field;
what they take is a scenario the controller's planned-path check and the wire accept.
"""

from __future__ import annotations

import json
import math
import tempfile
import tomllib
from pathlib import Path
from typing import Any

import pytest
from fuzzing import fuzz, json_texts, json_values, mutated, mutated_json
from hypothesis import given
from hypothesis import strategies as st

from controller.planner import check_plan
from protocol.errors import ConfigError
from protocol.scenario import (
    SCENARIO_DIR,
    Scenario,
    encode_task,
    load_scenario,
    parse_scenario,
    parse_task,
    read_task,
    scenario_document,
    task_document,
)

pytestmark = pytest.mark.fuzz

FILES = sorted(SCENARIO_DIR.glob("*.toml"))
TEXTS = [path.read_bytes() for path in FILES]
TABLES = [tomllib.loads(text.decode()) for text in TEXTS]
BASE = Scenario("fuzz", (), None)
TASKS = [task_document(load_scenario(path)) for path in FILES]


def toml_value(value: Any) -> str | None:
    """``value`` as a TOML value (inline tables and arrays); None where TOML has none."""
    if value is None:
        return None
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return repr(value) if math.isfinite(value) else ("-inf" if value < 0 else "inf")
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        items = [toml_value(item) for item in value]
        return "[" + ", ".join(item for item in items if item is not None) + "]"
    pairs = [(json.dumps(str(key)), toml_value(inner)) for key, inner in value.items()]
    return "{" + ", ".join(f"{key} = {inner}" for key, inner in pairs if inner is not None) + "}"


def toml_text(document: Any) -> bytes:
    """A document as TOML: top-level keys as lines (a document that is no table becomes one
    key)."""
    if not isinstance(document, dict):
        document = {"value": document}
    lines = []
    for key, value in document.items():
        written = toml_value(value)
        if written is not None:
            lines.append(f"{json.dumps(str(key))} = {written}")
    return "\n".join(lines).encode("utf-8", errors="surrogatepass")


@st.composite
def scenario_texts(draw: st.DrawFn) -> bytes:
    """A scenario file: a packaged one edited as bytes or lines, or its tables edited and
    written back, or anything at all."""
    kind = draw(st.sampled_from(["bytes", "lines", "tables", "tables", "deep", "any"]))
    if kind == "deep":  # tomllib reads nested arrays and inline tables recursively
        opener, closer = draw(st.sampled_from([(b"[", b"]"), (b"{a = ", b"}")]))
        depth = draw(st.sampled_from([2, 100, 1000, 5000]))
        return draw(st.sampled_from(TEXTS)) + b"\nx = " + opener * depth + closer * depth
    if kind == "bytes":
        return draw(mutated(draw(st.sampled_from(TEXTS)), max_edits=6))
    if kind == "lines":
        lines = draw(st.sampled_from(TEXTS)).splitlines()
        for _ in range(draw(st.integers(1, 4))):
            at = draw(st.integers(0, len(lines) - 1))
            edit = draw(st.sampled_from(["drop", "repeat", "move"]))
            line = lines.pop(at)
            if edit != "drop":
                lines.insert(draw(st.integers(0, len(lines))), line)
                if edit == "repeat":
                    lines.insert(at, line)
        return b"\n".join(lines)
    if kind == "tables":
        return toml_text(draw(mutated_json(draw(st.sampled_from(TABLES)), max_edits=4)))
    return draw(st.one_of(st.binary(max_size=200), st.builds(toml_text, json_values)))


def well_formed(scenario: Scenario) -> None:
    """What a taken scenario must be: its waypoints in order, its planned path inside the
    workspace checked (a ConfigError at worst), its task document read back the same."""
    assert len(scenario.waypoints) >= 2
    assert all(a.t < b.t for a, b in zip(scenario.waypoints, scenario.waypoints[1:], strict=False))
    try:
        check_plan(scenario)
    except ConfigError as error:
        assert error.field.startswith("waypoints[")
    document = json.loads(json.dumps(scenario_document(scenario)))
    again = parse_scenario(document)
    assert again.waypoints == scenario.waypoints and again.robot == scenario.robot


@fuzz(200)
@given(scenario_texts())
def test_a_scenario_file_loads_or_is_refused_naming_the_field(text: bytes) -> None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "fuzzed.toml"
        path.write_bytes(text)
        try:
            scenario = load_scenario(path)
        except ConfigError as error:
            assert error.field, error
            return
    well_formed(scenario)


@fuzz(150)
@given(st.one_of(st.sampled_from(TABLES).flatmap(mutated_json), json_values))
def test_a_scenario_document_is_taken_or_refused_naming_the_field(document: Any) -> None:
    """The tables of a scenario file, as JSON gives them too (a run's results carry them)."""
    try:
        scenario = parse_scenario(document)
    except ConfigError as error:
        assert error.field, error
        return
    well_formed(scenario)


@fuzz(200)
@given(json_texts(st.one_of(st.sampled_from(TASKS).flatmap(mutated_json), json_values)))
def test_a_transfer_is_a_task_or_is_refused_naming_the_field(payload: bytes) -> None:
    """What the controller does with a transfer: read it, parse it, check its path."""
    try:
        ticket, document = read_task(payload)
        task = parse_task(document, BASE)
        check_plan(task)
    except ConfigError as error:
        assert error.field, error
        return
    assert 0 <= ticket <= 255
    described = encode_task(task, 255)  # and it can describe it back in one transfer
    assert parse_task(read_task(described)[1], BASE).waypoints == task.waypoints


@pytest.mark.parametrize(
    ("source", "field"),
    [
        (b"\xff\xfe not UTF-8", "fuzzed.toml"),  # a UnicodeDecodeError
        (None, "fuzzed.toml"),  # a directory: an IsADirectoryError
        (b"x = " + b"[" * 5000 + b"]" * 5000, "fuzzed.toml"),  # a RecursionError in tomllib
    ],
    ids=["not-utf8", "directory", "deep"],
)
def test_what_the_fuzzing_found_in_scenario_files_is_a_config_error(
    source: bytes | None, field: str
) -> None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "fuzzed.toml"
        if source is None:
            path.mkdir()
        else:
            path.write_bytes(source)
        with pytest.raises(ConfigError) as error:
            load_scenario(path)
        assert error.value.field.endswith(field)
