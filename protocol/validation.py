"""The one validation path of the project's documents: JSON Schemas, then what they cannot say.

A scenario file, a task (over ISO-TP or from the bridge's commands), the fuzzy rule base and
every configuration are checked against the JSON Schemas shipped in ``protocol/schemas/``
(draft 2020-12). The schemas share their shapes (a finite number, a waypoint, an obstacle, the
robot, the gains, ...) through ``definitions.schema.json``, referenced with ``$ref`` and
resolved here through a :mod:`referencing` registry of every shipped schema; a reader that
gets one schema alone (a Zenoh subscriber, an MCAP file) gets it :func:`bundled`. What a schema
cannot say (times increasing, reach, ordered points, ...) the code that builds the value checks,
once, after the schema.

Two choices make the schemas fit what the project reads, TOML and Python's ``json``: a number
of format ``finite`` must be one (JSON has no NaN or infinity, but both readers accept them),
and an integer is an ``int`` (TOML tells 4 from 4.0; JSON Schema itself does not).

The first (most relevant) error becomes a :class:`ConfigError` naming the field as the rest of
the project does (``waypoints[3].x``, ``obstacle.height``) with a message in the project's words
(``must be positive, got -0.1``).
"""

from __future__ import annotations

import json
import math
import re
import reprlib
from collections.abc import Iterator, Mapping
from functools import cache
from importlib import resources
from typing import Any, Final
from urllib.parse import urljoin

import jsonschema
from jsonschema.exceptions import ValidationError, best_match
from referencing import Registry
from referencing.jsonschema import DRAFT202012

from protocol.errors import ConfigError

SCHEMA_BASE: Final = "https://scara-fuzzy.example/schemas/"
"""Where the shipped schemas' ``$id`` place them; their references are relative to it."""
SUFFIX: Final = ".schema.json"

_TYPE_NAMES: Final = {
    "object": "an object (a TOML table)",
    "array": "a list",
    "string": "a string",
    "integer": "an integer",
    "number": "a number",
    "boolean": "true or false",
    "null": "null",
}


@cache
def shipped_schemas() -> dict[str, dict[str, Any]]:
    """Every schema of ``protocol/schemas/`` as written, by name (``task``, ``cmd-mode``, ...)."""
    folder = resources.files("protocol").joinpath("schemas")
    return {
        entry.name.removesuffix(SUFFIX): json.loads(entry.read_text())
        for entry in sorted(folder.iterdir(), key=lambda entry: entry.name)
        if entry.name.endswith(SUFFIX)
    }


@cache
def bundled(name: str) -> dict[str, Any]:
    """Schema ``name`` with every shipped schema it refers to embedded under ``$defs`` (a
    draft 2020-12 compound document): valid on its own, for any validator or reader."""
    schemas = shipped_schemas()
    embedded: dict[str, dict[str, Any]] = {}
    pending = _referenced(schemas[name])
    while pending:
        other = pending.pop()
        if other != name and f"{other}{SUFFIX}" not in embedded:
            embedded[f"{other}{SUFFIX}"] = schemas[other]
            pending |= _referenced(schemas[other])
    document = dict(schemas[name])
    if embedded:
        document["$defs"] = document.get("$defs", {}) | embedded
    return document


def check(document: object, reference: str, field: str = "", root: str = "document") -> None:
    """Refuse ``document`` with a :class:`ConfigError` unless it fits the schema at
    ``reference``, relative to the schemas' folder (``task.schema.json``,
    ``definitions.schema.json#/$defs/controller``); ``field`` names where the document sits
    (``controller``), so that the error names the whole path (``controller.rate_hz``), and
    ``root`` the document itself where it is wrong as a whole (``payload``)."""
    try:
        error = best_match(_validator(reference).iter_errors(document))
        if error is None:
            return
        refusal = _config_error(error, field, root)
    except RecursionError:  # a document nested deeper than Python's stack (JSON allows it)
        refusal = ConfigError(field or root, "nested too deeply")
    raise refusal


MAX_NESTING: Final = 32
"""The deepest a JSON document the project reads may nest (a task nests 3 deep): deeper is
refused before it is parsed, the same way in every process (Python's own limit, hit while
parsing, depends on the caller's stack)."""
_TOKENS: Final = re.compile(rb'"(?:[^"\\]|\\.|\\\Z)*+(?:"|\Z)|[\[\]{}]', re.DOTALL)
"""A JSON string (to its end, or to the end of the text if it has none: never a failed match,
so one pass), or a bracket."""


def read_json(payload: bytes, field: str) -> Any:
    """The JSON document in ``payload`` (UTF-8); :class:`ConfigError` naming ``field`` if it
    is not UTF-8 JSON, or nests deeper than :data:`MAX_NESTING`."""
    depth = deepest = 0
    for token in _TOKENS.findall(payload):
        if token in (b"[", b"{"):
            depth += 1
            deepest = max(deepest, depth)
        elif token in (b"]", b"}"):
            depth -= 1
    if deepest > MAX_NESTING:
        raise ConfigError(field, f"nested {deepest} deep, at most {MAX_NESTING}")
    try:
        return json.loads(payload.decode())
    except RecursionError:  # cannot happen within MAX_NESTING; kept as a guard
        raise ConfigError(field, "nested too deeply") from None
    except ValueError as error:  # not UTF-8, not JSON, or an integer of 4300+ digits
        raise ConfigError(field, f"not UTF-8 JSON: {error}") from None


def field_name(*parts: str | int) -> str:
    """``waypoints[3].x`` from ``("waypoints", 3, "x")``; empty parts are left out."""
    text = ""
    for part in parts:
        if isinstance(part, int):
            text += f"[{part}]"
        elif part:
            text += f".{part}" if text else part
    return text


def _is_int(checker: object, instance: object) -> bool:
    return isinstance(instance, int) and not isinstance(instance, bool)


_Validator: Any = jsonschema.validators.extend(
    jsonschema.Draft202012Validator,
    type_checker=jsonschema.Draft202012Validator.TYPE_CHECKER.redefine("integer", _is_int),
)


def _is_finite(instance: object) -> bool:
    """A float that is not NaN or infinite, or an integer a float holds (JSON and TOML
    integers have no bound: 10**400 would overflow where the value is used)."""
    if isinstance(instance, float):
        return math.isfinite(instance)
    if isinstance(instance, int):
        try:
            float(instance)
        except OverflowError:
            return False
    return True


_FORMATS: Final = jsonschema.FormatChecker(formats=())
_FORMATS.checks("finite")(_is_finite)


@cache
def _registry() -> Registry[Any]:
    """Every shipped schema under its ``$id``, as draft 2020-12 but without its ``$schema``:
    jsonschema would otherwise validate inside it with its own 2020-12 validator, without the
    integer rule."""
    return Registry().with_resources(
        (
            schema["$id"],
            DRAFT202012.create_resource({k: v for k, v in schema.items() if k != "$schema"}),
        )
        for schema in shipped_schemas().values()
    )


@cache
def _validator(reference: str) -> Any:
    return _Validator(
        {"$ref": urljoin(SCHEMA_BASE, reference)},
        registry=_registry(),
        format_checker=_FORMATS,
    )


def _referenced(schema: object) -> set[str]:
    """The names of the other schemas ``schema`` refers to."""
    return {
        reference.partition("#")[0].removesuffix(SUFFIX)
        for reference in _references(schema)
        if not reference.startswith("#")
    }


def _references(schema: object) -> Iterator[str]:
    if isinstance(schema, Mapping):
        for key, value in schema.items():
            if key == "$ref":
                yield value
            else:
                yield from _references(value)
    elif isinstance(schema, list):
        for value in schema:
            yield from _references(value)


def _known_properties(schema: Mapping[str, Any]) -> set[str]:
    """The properties ``schema`` names, with those of the schema it refers to."""
    known = set(schema.get("properties", {}))
    if "$ref" in schema:
        target = urljoin(schema.get("$id", SCHEMA_BASE), schema["$ref"])
        known |= _known_properties(_registry().resolver().lookup(target).contents)
    return known


def _config_error(error: ValidationError, field: str, root: str) -> ConfigError:
    where = field_name(field, *error.absolute_path)
    keyword, instance, schema = error.validator, error.instance, error.schema
    if keyword == "required":
        missing = next(name for name in error.validator_value if name not in instance)
        return ConfigError(field_name(where, missing), "missing")
    if keyword in ("additionalProperties", "unevaluatedProperties"):
        known = _known_properties(schema)
        unknown = sorted(str(name) for name in instance if name not in known)[0]
        listed = f"known: {', '.join(sorted(known))}" if known else "none is known"
        return ConfigError(field_name(where, _key(unknown)), f"unknown field; {listed}")
    return ConfigError(where or root, _message(error))


_KEY_LENGTH: Final = 64


def _key(name: str) -> str:
    """A document's own key as a field name: as written, or quoted (and cut short) where it
    is empty, long or not printable, so that the error still names it."""
    if name and len(name) <= _KEY_LENGTH and name.isprintable():
        return name
    return json.dumps(name[:_KEY_LENGTH]) + ("..." if len(name) > _KEY_LENGTH else "")


_SHOWN: Final = reprlib.Repr()
"""How a wrong value is shown in a message: a sentence, not the document (cut short, and
not nested deeper than a few levels)."""
_SHOWN.maxlevel = 3
_SHOWN.maxstring = _SHOWN.maxother = _SHOWN.maxlong = 60
_SHOWN.maxlist = _SHOWN.maxdict = 6
_MESSAGE_LENGTH: Final = 200


def _message(error: ValidationError) -> str:
    """What the value must be, in the project's words (jsonschema's own for the rest)."""
    keyword, bound, instance, schema = (
        error.validator,
        error.validator_value,
        error.instance,
        error.schema,
    )
    got = f"got {_SHOWN.repr(instance)}"
    if keyword == "format" or (keyword == "type" and schema.get("format") == "finite"):
        return f"must be a finite number, {got}"
    if keyword == "type":
        expected = [bound] if isinstance(bound, str) else bound
        return f"must be {' or '.join(_TYPE_NAMES[name] for name in expected)}, {got}"
    if keyword == "enum":
        choices = [repr(choice) for choice in bound]
        listed = ", ".join(choices[:-1]) + f" or {choices[-1]}" if len(choices) > 1 else choices[0]
        return f"must be {listed}, {got}"
    if keyword == "exclusiveMinimum":
        return f"must be positive, {got}" if bound == 0 else f"must be above {bound:g}, {got}"
    if keyword in ("minimum", "maximum"):
        if "minimum" in schema and "maximum" in schema:
            return f"must be from {schema['minimum']:g} to {schema['maximum']:g}, {got}"
        if keyword == "minimum":
            return (
                f"must not be negative, {got}"
                if bound == 0
                else f"must be at least {bound:g}, {got}"
            )
        return f"must be at most {bound:g}, {got}"
    if keyword == "minItems" and bound == 1:
        return "must not be empty"
    if keyword in ("minItems", "maxItems"):
        count = f"got {len(instance)}"
        if schema.get("minItems") == schema.get("maxItems"):
            return f"must hold {bound} entries, {count}"
        side = "at least" if keyword == "minItems" else "at most"
        return f"must hold {side} {bound} entries, {count}"
    if keyword == "minProperties":
        return "must not be empty"
    message = str(error.message)  # jsonschema's, which may hold the whole value
    return message if len(message) <= _MESSAGE_LENGTH else message[:_MESSAGE_LENGTH] + "..."
