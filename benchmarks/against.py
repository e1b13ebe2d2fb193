"""Before and after, side by side in one run: a benchmark script run on another revision's
code and on this one, in turns, on the same machine at the same time.

These machines are shared and noisy; numbers taken an hour apart compare the machine as much
as the code. Here each side runs ``rounds`` times, alternating (before, after, before, ...),
each in a fresh process on its own tree (the other revision from ``git archive``), and the
table gives each measurement's median over the rounds, and their ratio. A benchmark script
takes part by writing ``--json PATH`` with a ``results`` list of rows that have a ``key``, a
``label``, a ``unit`` and a ``median`` (or ``value``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


def add_against_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--before",
        metavar="REV",
        help="run on git revision REV's code and on this tree's, in turns, side by side",
    )
    parser.add_argument(
        "--rounds", type=int, default=3, metavar="N", help="with --before: runs of each (3)"
    )


def tree_at(revision: str, into: Path) -> Path:
    """The project's files at git ``revision``, unpacked below ``into``."""
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", "--format=tar", revision],
        check=True,
        capture_output=True,
    ).stdout
    tree = into / "tree"
    tree.mkdir()
    archive_file = into / "tree.tar"
    archive_file.write_bytes(archive)
    with tarfile.open(archive_file) as tar:
        tar.extractall(tree, filter="data")
    return tree


def run_in(tree: Path, script: str, arguments: Sequence[str], output: Path) -> dict[str, Any]:
    """``script`` of ``tree``'s benchmarks, run on ``tree``'s code; the numbers it wrote."""
    environment = dict(os.environ, PYTHONPATH=str(tree))
    finished = subprocess.run(
        [sys.executable, str(tree / "benchmarks" / script), *arguments, "--json", str(output)],
        cwd=tree,
        env=environment,
        check=False,
        stdout=subprocess.DEVNULL,
    )
    if not output.exists():
        raise SystemExit(f"{script} on {tree} wrote no numbers (exit {finished.returncode})")
    document: dict[str, Any] = json.loads(output.read_text())
    return document


def side_by_side(
    script: str,
    revision: str,
    arguments: Sequence[str],
    rounds: int,
    say: Callable[[str], None],
) -> str:
    """Run ``script`` with ``arguments`` on ``revision`` and on this tree, ``rounds`` times
    each in turns; a Markdown table of both sides' medians and their ratio."""
    sides: dict[str, list[dict[str, Any]]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        trees = {"before": tree_at(revision, folder), "after": ROOT}
        names = {"before": revision, "after": "this tree"}
        for turn in range(rounds):
            for side, tree in trees.items():
                say(f"round {turn + 1} of {rounds}: {side} ({names[side]})")
                document = run_in(tree, script, arguments, folder / f"{side}-{turn}.json")
                sides[side].append(document)
    return _table(sides, revision)


def _medians(documents: Sequence[dict[str, Any]]) -> dict[str, tuple[str, str, float]]:
    """Per row key: its label, unit and median over the rounds."""
    values: dict[str, list[float]] = {}
    labels: dict[str, tuple[str, str]] = {}
    for document in documents:
        for row in document["results"]:
            value = row.get("median", row.get("value"))
            if value is None:
                continue
            values.setdefault(row["key"], []).append(float(value))
            labels[row["key"]] = (row["label"], row["unit"])
    return {key: (*labels[key], statistics.median(found)) for key, found in values.items()}


def _table(sides: dict[str, list[dict[str, Any]]], revision: str) -> str:
    before, after = _medians(sides["before"]), _medians(sides["after"])
    rounds = len(sides["after"])
    lines = [
        f"| Measurement (median of {rounds} runs each, in turns) | Before ({revision}) | After "
        "| After / before |",
        "|---|---:|---:|---:|",
    ]
    for key, (label, unit, value) in after.items():
        if key not in before:
            lines.append(f"| {label} | - | {value:,.4g} {unit} | - |")
            continue
        old = before[key][2]
        ratio = f"{value / old:.2f}" if old else "-"
        lines.append(f"| {label} | {old:,.4g} {unit} | {value:,.4g} {unit} | {ratio} |")
    return "\n".join(lines)
