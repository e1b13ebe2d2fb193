"""The saved examples and CI's determinism (``fuzzing.py``), checked against the installed
hypothesis: a saved counterexample is replayed first, also when the examples are derived
from the test (CI), in the same order every run, without writing to the saved examples; and
a local run adds new counterexamples but never deletes one.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from fuzzing import EXAMPLES, KeptExamples, examples_database
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.database import (
    DirectoryBasedExampleDatabase,
    InMemoryExampleDatabase,
    ReadOnlyDatabase,
)

pytestmark = pytest.mark.fuzz

CI = settings(deadline=None, derandomize=True)
"""As ``tests/conftest.py``'s ``ci`` profile."""


def probe(chosen: settings, seen: list[int], failing: bool) -> Callable[[], None]:
    """One test function (one key in the database) under ``chosen`` settings."""

    @chosen
    @given(st.integers(0, 10**6))
    def numbers(number: int) -> None:
        seen.append(number)
        assert not failing or number < 1000

    return numbers


def save_a_counterexample(database: object) -> None:
    """A failing run that leaves its counterexample (1000, shrunk) in ``database``."""
    with pytest.raises(AssertionError):
        probe(settings(database=database, max_examples=500, deadline=None), [], True)()


def test_ci_replays_the_saved_examples_first_in_the_same_order_and_writes_nothing() -> None:
    saved = InMemoryExampleDatabase()
    save_a_counterexample(saved)
    assert saved.data, "the counterexample was not saved"
    contents = {key: set(values) for key, values in saved.data.items()}
    # What fuzzing.fuzz() builds in CI: the database given to a child of the loaded profile.
    ci = settings(CI, database=ReadOnlyDatabase(saved), max_examples=20)
    assert ci.derandomize and ci.database is not None
    runs: list[list[int]] = []
    for _ in range(2):
        seen: list[int] = []
        probe(ci, seen, failing=False)()
        runs.append(seen)
    assert runs[0][0] == 1000, "the saved counterexample was not replayed first"
    assert runs[0] == runs[1], "two CI runs tried different examples"
    assert {key: set(values) for key, values in saved.data.items()} == contents


def test_locally_the_smallest_counterexample_is_added_and_none_is_deleted(
    tmp_path: Path,
) -> None:
    kept = KeptExamples(tmp_path)
    save_a_counterexample(kept)
    seen: list[int] = []
    probe(settings(database=kept, max_examples=1, deadline=None), seen, failing=False)()
    assert seen[0] == 1000  # replayed, and it passes now: a plain database would delete it
    examples = files(tmp_path)
    assert examples, "the counterexample was not saved"
    save_a_counterexample(kept)  # found again: nothing more to keep
    probe(settings(database=kept, max_examples=1, deadline=None), [], failing=False)()
    assert files(tmp_path) == examples
    # only the smallest: no step of the shrinking, no secondary corpus (hypothesis's
    # database of keys holds one file per key)
    assert len(examples) <= 2, examples


def files(folder: Path) -> list[Path]:
    return sorted(path.relative_to(folder) for path in folder.rglob("*") if path.is_file())


def test_the_saved_examples_are_read_only_in_ci_and_kept_elsewhere() -> None:
    in_ci = examples_database(ci=True)
    assert isinstance(in_ci, ReadOnlyDatabase)
    assert isinstance(in_ci._wrapped, DirectoryBasedExampleDatabase)
    assert Path(in_ci._wrapped.path) == EXAMPLES
    local = examples_database(ci=False)
    assert isinstance(local, KeptExamples) and Path(local.directory.path) == EXAMPLES
