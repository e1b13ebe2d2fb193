"""What every command shares (``protocol.cli``): a bad number names the flag; SIGINT stops
a command however it was started; a reader that goes away does not give a traceback."""

from __future__ import annotations

import argparse
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from support import ROOT, SIGINT_IGNORED, SLOWDOWN

from protocol.cli import number


def test_number_accepts_its_range_and_refuses_the_rest() -> None:
    rate = number(100, 1000)
    assert rate("100") == 100.0 and rate("1000") == 1000.0 and rate("512.5") == 512.5
    for bad in ("0", "99.9", "1000.1", "-5", "nan", "inf", "fast", ""):
        with pytest.raises(argparse.ArgumentTypeError):
            rate(bad)
    positive = number(0.0, low_open=True)
    assert positive("1e-9") == 1e-9 and positive("1e9") == 1e9
    with pytest.raises(argparse.ArgumentTypeError, match=r"\(0, inf\]"):
        positive("0")
    port = number(1, 65535, integer=True)
    assert port("17447") == 17447 and isinstance(port("1"), int)
    with pytest.raises(argparse.ArgumentTypeError, match="integer"):
        port("1.5")
    assert not math.isnan(number(-1, 1)("-1"))


def test_argparse_names_the_flag_and_the_value(capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser(prog="tool")
    parser.add_argument("--rate", type=number(100, 1000))
    with pytest.raises(SystemExit) as exited:
        parser.parse_args(["--rate", "0"])
    assert exited.value.code == 2
    error = capsys.readouterr().err
    assert "--rate" in error and "0" in error and "[100, 1000]" in error


@pytest.mark.parametrize("restored", [False, True])
def test_interruptible_stops_on_sigint_a_process_started_with_it_ignored(restored: bool) -> None:
    """Without it, a command a script started in the background ignores SIGINT for ever."""
    code = "import sys, time\n"
    if restored:
        code += "from protocol.cli import interruptible\ninterruptible()\n"
    code += "print('ready', flush=True)\ntime.sleep(3600)\n"  # outlasts the wait below
    process = subprocess.Popen(
        [*SIGINT_IGNORED, sys.executable, "-c", code],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert process.stdout is not None and process.stdout.readline() == "ready\n"
        process.send_signal(signal.SIGINT)
        try:
            _, err = process.communicate(timeout=10 * SLOWDOWN)
            stopped = True
        except subprocess.TimeoutExpired:
            stopped = False
    finally:
        process.kill()
        process.wait()
    assert stopped == restored
    if restored:
        assert "KeyboardInterrupt" in err


@pytest.mark.parametrize(
    ("module", "arguments"),
    [
        ("protocol.busload.report", []),
        ("sim.cli", ["reference", "--mode", "fuzzy"]),
        ("sim.compare", ["-n", "2", "--seed", "9", "--workers", "1", "--no-figure", "-q"]),
    ],
)
def test_a_command_whose_reader_has_gone_exits_1_without_a_traceback(
    module: str, arguments: list[str], tmp_path: Path
) -> None:
    """As ``scara-compare | head -0``: the pipe is closed before the command writes."""
    reader, writer = os.pipe()
    os.close(reader)
    outputs = ["--out", str(tmp_path)] if module.startswith("sim.") else []
    try:
        done = subprocess.run(
            [sys.executable, "-c", f"import sys; from {module} import main; sys.exit(main())",
             *arguments, *outputs],
            cwd=ROOT, stdout=writer, stderr=subprocess.PIPE, text=True, timeout=120 * SLOWDOWN,
        )  # fmt: skip
    finally:
        os.close(writer)
    assert done.returncode == 1
    assert "Traceback" not in done.stderr and "BrokenPipeError" not in done.stderr, done.stderr
