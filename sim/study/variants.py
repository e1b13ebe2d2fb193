"""The settings the study compares: the baseline, and one variant per value of a ``--sweep``.

A variant sets controller gains or replaces the fuzzy rule base (one input term's points, or
one output's peaks, in the shipped Table 2), and names the modes it concerns: a switching gain
only the conventional mode, a rule base only the fuzzy one. Each value is checked as a
scenario's gains or the rule file are (their schemas, then their own checks).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields, replace
from importlib import resources

from controller.fuzzy import INPUT_NAMES, OUTPUT_NAMES, OUTPUT_TERMS, RuleBase
from protocol.config import ControllerConfig
from protocol.errors import ConfigError
from protocol.scenario import Mode


@dataclass(frozen=True, slots=True)
class Variant:
    """One setting of the study: the gains and the rule base, and the modes it concerns."""

    name: str
    modes: tuple[Mode, ...]
    controller: dict[str, float]
    rule_base: RuleBase | None = None


BASELINE = Variant("baseline", tuple(Mode), {})
"""The shipped gains and rule base, in both modes."""


def parse_sweep(text: str) -> list[Variant]:
    """``NAME=V1,V2,...``: one variant per value; a ConfigError names what is wrong.

    NAME is a controller gain (``switch_distance``, ``sensing_range``, ...: a number each),
    a term of a fuzzy input (``min_distance.near``, ``beta.small``, ...: ``a:b:c:d``) or the
    output peaks (``k_T.peaks``, ``k_C.peaks``: ``small:medium:big``).
    """
    name, equals, values = text.partition("=")
    if not equals or not values:
        raise ConfigError("--sweep", f"expected NAME=V1,V2,..., got {text!r}")
    gains = {spec.name for spec in fields(ControllerConfig)}
    variants = []
    for value in values.split(","):
        label = f"{name}={value}"
        if name in gains:
            number = _number(value, label)
            replace(ControllerConfig(), **{name: number})  # checked as a scenario's gains are
            modes = (Mode.CONVENTIONAL,) if name == "switch_distance" else tuple(Mode)
            variants.append(Variant(label, modes, {name: number}))
        else:
            variants.append(Variant(label, (Mode.FUZZY,), {}, _rule_base(name, value, label)))
    return variants


def _rule_base(name: str, value: str, label: str) -> RuleBase:
    """Table 2 with one term's points or one output's peaks replaced."""
    document = json.loads(
        resources.files("controller").joinpath("data/fuzzy_rules.json").read_text()
    )
    part, _, term = name.partition(".")
    numbers = [_number(v, label) for v in value.split(":")]
    if part in INPUT_NAMES and term in document["inputs"][part]["terms"]:
        document["inputs"][part]["terms"][term] = numbers
    elif part in OUTPUT_NAMES and term == "peaks":
        if len(numbers) != len(OUTPUT_TERMS):
            raise ConfigError(label, "peaks are small:medium:big (three numbers)")
        document["outputs"][part]["peaks"] = dict(zip(OUTPUT_TERMS, numbers, strict=True))
    else:
        terms = [f"{i}.{t}" for i in INPUT_NAMES for t in document["inputs"][i]["terms"]]
        known = ", ".join([*sorted(f.name for f in fields(ControllerConfig)), *terms])
        raise ConfigError(
            "--sweep", f"unknown parameter {name!r}; known: {known}, k_T.peaks, k_C.peaks"
        )
    try:
        return RuleBase.from_mapping(document)
    except ConfigError as error:
        raise ConfigError(label, str(error)) from error


def _number(text: str, label: str) -> float:
    """The number ``text`` (whether it fits is for the schema of what it sets to say)."""
    try:
        return float(text)
    except ValueError:
        raise ConfigError(label, f"{text!r} is not a number") from None
