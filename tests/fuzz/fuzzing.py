"""What the fuzz tests share: their hypothesis settings and saved examples, and strategies for
bytes, JSON and CAN frames that start from valid inputs and break them.

The saved examples. Hypothesis keeps every input that once failed a fuzz test in
``tests/fuzz/.examples/`` (a :class:`DirectoryBasedExampleDatabase`, committed; hidden, as
hypothesis's own ``.hypothesis/``, its folders being hashes no reader needs): each run
replays them before it generates new inputs, so a bug found once stays tested. Locally the
directory only grows: a new counterexample is written there (the smallest: commit it with
the fix), and an example that passes again is never deleted (:class:`KeptExamples`). In CI
it is read only (:class:`ReadOnlyDatabase`): a run never changes the tree.

Determinism. The ``ci`` profile (``tests/conftest.py``, when ``CI`` is set) derandomizes:
the inputs are derived from each test, and a red run is repeatable. Hypothesis takes
``derandomize=True`` to mean "no database" when both are given to one ``settings``; here the
database is given to a child of the loaded profile, which keeps both: the saved examples
replayed in a fixed order (hypothesis sorts them), then the derived ones.
``test_fuzz_examples.py`` checks that this still holds after a hypothesis upgrade.

Editing a fuzz test's body changes the key hypothesis files its examples under (a hash of
its source): the inputs that found a bug are also pinned, as plain tests or ``@example``,
which survive that.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.database import (
    DirectoryBasedExampleDatabase,
    ExampleDatabase,
    ReadOnlyDatabase,
)

EXAMPLES = Path(__file__).resolve().parent / ".examples"
"""The saved examples (committed)."""
IN_CI = bool(os.environ.get("CI"))


class KeptExamples(ExampleDatabase):
    """The saved examples as a local run should change them: a new counterexample is added
    (the smallest one hypothesis found, not the steps of its shrinking nor its secondary
    corpus), and an example that was there before the run (committed) is never deleted,
    though it passes now: it is a regression test."""

    def __init__(self, path: Path) -> None:
        super().__init__()
        self.directory = DirectoryBasedExampleDatabase(path)
        self._added: set[tuple[bytes, bytes]] = set()

    def fetch(self, key: bytes) -> Iterable[bytes]:
        return self.directory.fetch(key)

    def save(self, key: bytes, value: bytes) -> None:
        if key.endswith((b".secondary", b".pareto")):
            return
        if value not in set(self.directory.fetch(key)):
            self._added.add((key, value))
        self.directory.save(key, value)

    def delete(self, key: bytes, value: bytes) -> None:
        if (key, value) in self._added:  # a step of this run's shrinking
            self._added.discard((key, value))
            self.directory.delete(key, value)

    def move(self, src: bytes, dest: bytes, value: bytes) -> None:
        self.delete(src, value)
        self.save(dest, value)

    def __repr__(self) -> str:
        return f"KeptExamples({self.directory.path!s})"


def examples_database(ci: bool = IN_CI) -> ExampleDatabase:
    """The saved examples: read only in CI, kept (never deleted) elsewhere."""
    if ci:
        return ReadOnlyDatabase(DirectoryBasedExampleDatabase(EXAMPLES))
    return KeptExamples(EXAMPLES)


def fuzz(max_examples: int, **options: Any) -> settings:
    """The settings of one fuzz test: the loaded profile's (derandomized in CI), the saved
    examples, ``max_examples`` new inputs."""
    return settings(
        settings.default,
        database=examples_database(),
        max_examples=max_examples,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
        **options,
    )


# --- bytes ---------------------------------------------------------------------------------


@st.composite
def mutated(draw: st.DrawFn, original: bytes, max_edits: int = 4) -> bytes:
    """``original`` after a few random edits: bits flipped, bytes set, inserted or deleted, a
    slice cut out, repeated or truncated."""
    data = bytearray(original)
    for _ in range(draw(st.integers(1, max_edits), label="edits")):
        kind = draw(
            st.sampled_from(["flip", "set", "insert", "delete", "truncate", "repeat", "splice"])
        )
        if not data and kind not in ("insert", "splice"):
            kind = "insert"
        if kind == "flip":
            bit = draw(st.integers(0, 8 * len(data) - 1))
            data[bit // 8] ^= 1 << (bit % 8)
        elif kind == "set":
            data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
        elif kind == "insert":
            at = draw(st.integers(0, len(data)))
            data[at:at] = draw(st.binary(min_size=1, max_size=8))
        elif kind == "delete":
            at = draw(st.integers(0, len(data) - 1))
            del data[at : at + draw(st.integers(1, 8))]
        elif kind == "truncate":
            del data[draw(st.integers(0, len(data) - 1)) :]
        elif kind == "repeat":
            start = draw(st.integers(0, len(data) - 1))
            end = draw(st.integers(start + 1, min(len(data), start + 64)))
            data[end:end] = data[start:end]
        else:
            at = draw(st.integers(0, len(data)))
            data[at:at] = draw(st.sampled_from(SPLICES))
    return bytes(data)


SPLICES = [
    b"NaN", b"Infinity", b"-Infinity", b"1e999", b"-0", b"1" * 5000, b"null", b"[", b"]",
    b"{", b"}", b'"', b"\\", b"\\ud800", b",", b":", b"\xff", b"\xc3", b"\xef\xbb\xbf",
    b"\x00", '"\U0001f916"'.encode(), b'"a":1,"a":2', b"[" * 2000, b"{}" * 10,
]  # fmt: skip
"""Byte strings that break parsers: JSON's non-numbers, huge and deep values, lone
surrogates, invalid UTF-8, a BOM, NUL, duplicate keys."""


# --- JSON ----------------------------------------------------------------------------------

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(),
    st.integers(min_value=10**300, max_value=10**400),  # past what a float holds
    st.floats(),  # NaN and infinities included: Python's json writes and reads them
    st.sampled_from([0, -0.0, 1e308, -1e308, 5e-324, 2**53 + 1, 4.0, True, ""]),
    st.text(),
    st.text(st.characters(codec="utf-8", categories=["Cs", "Co", "So", "Zs"])),
)
"""JSON scalars and the values that stress a reader: huge integers, NaN, infinities, subnormals,
lone surrogates, private-use and symbol characters."""

json_values: st.SearchStrategy[Any] = st.recursive(
    scalars,
    lambda children: st.one_of(
        st.lists(children, max_size=6),
        st.dictionaries(st.text(max_size=12), children, max_size=6),
    ),
    max_leaves=24,
)


def _paths(value: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every path to a value inside ``value`` (the root included)."""
    found = [prefix]
    if isinstance(value, dict):
        for key, inner in value.items():
            found += _paths(inner, (*prefix, key))
    elif isinstance(value, list):
        for index, inner in enumerate(value):
            found += _paths(inner, (*prefix, index))
    return found


def _replace(value: Any, path: tuple[Any, ...], change: Callable[[Any], Any]) -> Any:
    if not path:
        return change(value)
    head, *rest = path
    copy = dict(value) if isinstance(value, dict) else list(value)
    copy[head] = _replace(value[head], tuple(rest), change)
    return copy


@st.composite
def mutated_json(draw: st.DrawFn, document: Any, max_edits: int = 3) -> Any:
    """``document`` with a few values anywhere in it replaced (by any JSON value, or a number
    nudged, scaled or made not finite), removed, or with keys added."""
    for _ in range(draw(st.integers(1, max_edits), label="edits")):
        path = draw(st.sampled_from(_paths(document)), label="at")
        kind = draw(st.sampled_from(["replace", "number", "remove", "add", "wrap"]))
        if kind == "replace":
            new = draw(json_values, label="value")
            document = _replace(document, path, lambda _, new=new: new)
        elif kind == "number":
            factor = draw(st.sampled_from([-1.0, 0.0, 1e-9, 0.5, 1.0001, 2.0, 1e3, 1e300]))
            shift = draw(st.sampled_from([0.0, 1e-12, 0.01, 0.5, -1.0, math.inf, math.nan]))
            document = _replace(document, path, lambda old, f=factor, s=shift: _nudged(old, f, s))
        elif kind == "remove" and path:
            parent, last = path[:-1], path[-1]

            def remove(container: Any, last: Any = last) -> Any:
                copy = dict(container) if isinstance(container, dict) else list(container)
                del copy[last]
                return copy

            document = _replace(document, parent, remove)
        elif kind == "add":
            key = draw(st.text(max_size=12), label="key")
            new = draw(json_values, label="value")
            document = _replace(
                document,
                path,
                lambda old, k=key, v=new: (
                    old | {k: v}
                    if isinstance(old, dict)
                    else [*old, v]
                    if isinstance(old, list)
                    else v
                ),
            )
        else:
            in_a_list = draw(st.booleans())
            document = _replace(
                document, path, lambda old, listed=in_a_list: [old] if listed else {"": old}
            )
    return document


def _nudged(value: Any, factor: float, shift: float) -> Any:
    """A number scaled and shifted (anything else replaced by the shift)."""
    if not isinstance(value, int | float) or isinstance(value, bool):
        return shift
    try:
        return value * factor + shift
    except OverflowError:  # an integer past what a float holds
        return shift


@st.composite
def json_texts(draw: st.DrawFn, documents: st.SearchStrategy[Any]) -> bytes:
    """A document of ``documents`` as JSON text, written in one of the ways a sender may:
    compact or spaced, ASCII or UTF-8, NaN and Infinity as Python writes them, with
    duplicate keys, padded, or cut and edited as bytes."""
    document = draw(documents)
    spaced = draw(st.booleans())
    text = json.dumps(
        document,
        ensure_ascii=draw(st.booleans()),
        separators=(", ", ": ") if spaced else (",", ":"),
        indent=draw(st.sampled_from([None, None, 2])),
    )
    encoded = text.encode("utf-8", errors="surrogatepass")
    style = draw(st.sampled_from(["plain", "plain", "duplicate", "padded", "bytes"]))
    if style == "duplicate" and isinstance(document, dict) and document:
        key = draw(st.sampled_from(sorted(document, key=repr)))
        again = json.dumps({key: draw(json_values)})[1:-1].encode("utf-8", "surrogatepass")
        encoded = encoded[:-1] + b"," + again + b"}"
    elif style == "padded":
        encoded = b" \t\r\n" * draw(st.integers(0, 2000)) + encoded
    elif style == "bytes":
        encoded = draw(mutated(encoded))
    return encoded


def deep(depth: int, opener: bytes = b"[", closer: bytes = b"]") -> bytes:
    """JSON nested ``depth`` levels deep."""
    return opener * depth + closer * depth
