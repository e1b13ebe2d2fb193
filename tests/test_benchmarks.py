"""The benchmark scripts still run on today's law: a small study benchmark finishes, writes its
numbers, and its scalar sample agrees with the batch (a new measure once broke it only at
10,000 scenarios, found when the README's numbers were due)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from support import ROOT


@pytest.mark.slow
def test_a_small_study_benchmark_runs_and_its_scalar_sample_agrees_with_the_batch(
    tmp_path: Path,
) -> None:
    numbers = tmp_path / "study.json"
    finished = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "bench_study.py"),
            "--count",
            "8",
            "--workers",
            "1",
            "--json",
            str(numbers),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    assert numbers.exists(), finished.stderr[-3000:]
    rows = {row["key"]: row for row in json.loads(numbers.read_text())["results"]}
    assert rows["agreement"]["passed"], rows["agreement"]
    assert rows["batch_wall_s"]["value"] > 0.0
