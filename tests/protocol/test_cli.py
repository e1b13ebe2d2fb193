"""What every command shares (``protocol.cli``): a bad number names the flag; SIGINT stops
a command however it was started."""

from __future__ import annotations

import argparse
import math
import signal
import subprocess
import sys

import pytest
from support import ROOT, SIGINT_IGNORED

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
    code += "print('ready', flush=True)\ntime.sleep(30)\n"
    process = subprocess.Popen(
        [*SIGINT_IGNORED, sys.executable, "-c", code],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert process.stdout is not None and process.stdout.readline() == "ready\n"
        process.send_signal(signal.SIGINT)
        try:
            _, err = process.communicate(timeout=10)
            stopped = True
        except subprocess.TimeoutExpired:
            stopped = False
    finally:
        process.kill()
        process.wait()
    assert stopped == restored
    if restored:
        assert "KeyboardInterrupt" in err
