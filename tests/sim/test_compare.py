"""scara-compare: the command line, the sweeps, and the same results in-process and on Dask."""

from __future__ import annotations

import contextlib
import csv
import io
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from support import SLOWDOWN

from controller.fuzzy import RuleBase
from protocol.errors import ConfigError
from protocol.scenario import Mode
from sim.compare import main
from sim.generator import generate_scenario_at
from sim.study.jobs import TICK_OVERHEAD_STEPS, Job, plan_jobs, run_ticks
from sim.study.results import NEAR_STOP
from sim.study.variants import BASELINE, parse_sweep

COUNT = ["-n", "2", "--seed", "9", "-q"]  # two short scenarios (6 and 8 s)


@pytest.fixture(scope="module")
def in_process(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("in_process")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main([*COUNT, "--workers", "2", "--out", str(out)]) == 0
    return out, printed.getvalue()


@pytest.fixture(scope="module")
def dask_scheduler() -> Iterator[str]:
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(
        host="127.0.0.1",
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        dashboard_address="127.0.0.1:0",
    ) as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        yield cluster.scheduler_address


def rows(path: Path) -> list[dict[str, str]]:
    with path.open() as file:
        return list(csv.DictReader(file))


def test_writes_a_row_per_scenario_and_mode_the_table_and_the_figures(
    in_process: tuple[Path, str],
) -> None:
    out, printed = in_process
    table = rows(out / "compare.csv")
    assert sorted((row["mode"], row["index"]) for row in table) == [
        (mode, index) for mode in ("conventional", "fuzzy") for index in ("0", "1")
    ]
    assert all(float(row["peak_jerk"]) > 0.0 for row in table)
    assert "| measure | fuzzy | conventional |" in printed
    assert "scenarios where avoidance engaged" in printed
    near = {
        mode: sum(float(r["stop_margin"]) < NEAR_STOP for r in table if r["mode"] == mode)
        for mode in ("fuzzy", "conventional")
    }
    row = f"| scenarios near a stop (margin < {NEAR_STOP:g}) |"
    assert f"{row} {near['fuzzy']} | {near['conventional']} |" in printed
    for name in ("compare.png", "worst-fuzzy.png", "worst-conventional.png"):
        assert (out / name).stat().st_size > 10_000


def test_dask_gives_the_in_process_results(
    in_process: tuple[Path, str], dask_scheduler: str, tmp_path: Path
) -> None:
    assert main([*COUNT, "--scheduler", dask_scheduler, "--out", str(tmp_path), "--no-figure"]) == 0
    assert rows(tmp_path / "compare.csv") == rows(in_process[0] / "compare.csv")


def test_help_and_usage_errors(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as done:
        main(["--help"])
    assert done.value.code == 0
    assert "--scheduler" in capsys.readouterr().out
    for arguments, named in (
        (["-n", "0"], "--count"),
        (["--workers", "zero"], "--workers"),
        (["--sweep", "bogus=1"], "bogus"),
        (["--sweep", "switch_distance=-0.1"], "switch_distance"),
        (["--sweep", "min_distance.near=0:0.01:0.04"], "terms.near: must hold 4 entries"),
        (["--sweep", "min_distance.near=0:0:nan:0.05"], "terms.near[2]: must be a finite number"),
        (["--sweep", "k_C.peaks=0.9:0.5:0.1"], "small < medium < big"),
        (["--sweep", "sensing_range"], "NAME=V1"),
    ):
        with pytest.raises(SystemExit) as done:
            main(arguments)
        assert done.value.code == 2
        assert named in capsys.readouterr().err


def test_verbosity_tells_what_the_study_does_on_stderr(tmp_path: Path) -> None:
    def run(*verbosity: str) -> subprocess.CompletedProcess[str]:
        command = [sys.executable, "-m", "sim.compare", "-n", "1", "--seed", "9", "-q"]
        command += ["--workers", "1", "--no-figure", "--out", str(tmp_path), *verbosity]
        return subprocess.run(command, capture_output=True, text=True, timeout=120, check=True)

    quiet, debug = run(), run("-vv")
    assert "scara.compare" not in quiet.stderr
    assert "scara.compare: generated 1 scenarios of seed 9 in" in debug.stderr
    assert "scara.compare: 2 runs of 1 variants in 1 batches on 1 worker processes" in debug.stderr
    assert "scara.compare: batch of baseline: 2 runs" in debug.stderr
    assert quiet.stdout == debug.stdout  # the report is the same


def test_sweeps_make_one_variant_per_value_in_the_modes_they_concern() -> None:
    switch = parse_sweep("switch_distance=0.02,0.06")
    assert [v.name for v in switch] == ["switch_distance=0.02", "switch_distance=0.06"]
    assert all(v.modes == (Mode.CONVENTIONAL,) for v in switch)
    assert switch[1].controller == {"switch_distance": 0.06}
    (margin,) = parse_sweep("ao_pass_margin=0.02")
    assert margin.modes == tuple(Mode)
    near, peaks = (
        parse_sweep("min_distance.near=0:0:0.02:0.05")[0],
        parse_sweep("k_C.peaks=0.1:0.5:0.9")[0],
    )
    assert near.modes == peaks.modes == (Mode.FUZZY,)
    assert isinstance(near.rule_base, RuleBase) and isinstance(peaks.rule_base, RuleBase)
    assert near.rule_base.inputs["min_distance"].terms["near"].d == 0.05
    assert peaks.rule_base.outputs["k_C"].peaks == (0.1, 0.5, 0.9)
    assert peaks.rule_base.outputs["k_T"].peaks == RuleBase.load().outputs["k_T"].peaks
    with pytest.raises(ConfigError, match="not a number"):
        parse_sweep("switch_distance=far")


def test_batches_hold_every_run_once_with_long_runs_in_smaller_batches() -> None:
    scenarios = [generate_scenario_at(5, index) for index in range(40)]
    variants = [BASELINE, *parse_sweep("switch_distance=0.02")]
    jobs = plan_jobs(scenarios, variants, batch_size=1000, workers=4)
    runs = [
        (job.variant, mode, index)
        for job in jobs
        for mode, index in zip(job.modes, job.indices, strict=True)
    ]
    expected = [("baseline", mode, index) for mode in Mode for index in range(40)]
    expected += [("switch_distance=0.02", Mode.CONVENTIONAL, index) for index in range(40)]
    assert sorted(runs, key=str) == sorted(expected, key=str)
    baseline = [job for job in jobs if job.variant == "baseline"]
    assert len(baseline) == 2 and all(len(set(job.modes)) == 2 for job in baseline)
    short, long = sorted(baseline, key=lambda job: max(s.duration for s in job.scenarios))
    assert max(s.duration for s in short.scenarios) <= min(s.duration for s in long.scenarios)
    assert len(long.scenarios) < len(short.scenarios)

    def cost(ticks: list[int]) -> int:
        return max(ticks) * TICK_OVERHEAD_STEPS + sum(ticks)

    def ticks_of(job: Job) -> list[int]:
        return [run_ticks(scenario) for scenario in job.scenarios]

    everything = sorted(ticks_of(short) + ticks_of(long))
    best = min(
        max(cost(everything[:cut]), cost(everything[cut:])) for cut in range(1, len(everything))
    )
    assert max(cost(ticks_of(short)), cost(ticks_of(long))) <= best * 1.0001
    assert all(len(job.scenarios) <= 30 for job in plan_jobs(scenarios, variants[:1], 30, 1))


def test_ctrl_c_stops_workers_and_exits_130_without_a_traceback(tmp_path: Path) -> None:
    command = [sys.executable, "-m", "sim.compare", "-n", "40", "--out", str(tmp_path)]
    process = subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,  # a group of its own, as a terminal's Ctrl-C reaches
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    assert process.stderr is not None
    seen = b""
    while b"generating" not in seen:  # past the imports: it has started its workers
        chunk = os.read(process.stderr.fileno(), 4096)
        assert chunk, "scara-compare ended before it started"
        seen += chunk
    time.sleep(1.0)
    os.killpg(process.pid, signal.SIGINT)
    _, error = process.communicate(timeout=30 * SLOWDOWN)
    error = seen + error
    assert process.returncode == 130
    assert "interrupted" in error.decode()
    assert "Traceback" not in error.decode()
    deadline = time.monotonic() + 10.0 * SLOWDOWN  # workers and the resource tracker leave soon
    while subprocess.run(["pgrep", "-g", str(process.pid)], capture_output=True).stdout:
        assert time.monotonic() < deadline, "processes of scara-compare outlived it"
        time.sleep(0.2)
