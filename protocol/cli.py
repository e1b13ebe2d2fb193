"""What the commands share: ``-v`` for diagnostics through :mod:`logging` (python-can's
way), argparse types that check a number's range and name the flag when it is wrong,
stopping on SIGINT however the command was started, a quiet exit when the reader of its
output goes away, and the flags more than one command takes (``--comms-timeout``)."""

from __future__ import annotations

import argparse
import functools
import logging
import math
import os
import signal
import sys
from collections.abc import Callable
from typing import ParamSpec

Arguments = ParamSpec("Arguments")


def add_verbosity(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=0,
        help="more diagnostics on stderr (-v: info, -vv: debug, python-can's too)",
    )


def configure_logging(verbosity: int) -> None:
    """Warnings by default; ``-v`` adds the project's info, ``-vv`` debug from every library."""
    logging.basicConfig(format="%(name)s: %(message)s", level=logging.WARNING)
    if verbosity >= 2:
        logging.getLogger().setLevel(logging.DEBUG)
    elif verbosity == 1:
        logging.getLogger("scara").setLevel(logging.INFO)


def interruptible() -> None:
    """SIGINT (Ctrl-C, ``kill -INT``) raises KeyboardInterrupt in this process even when it
    was started with SIGINT ignored: a shell without job control (a script's ``cmd &``)
    starts its background commands so, Python then keeps ignoring it, and the command, or a
    test or launcher stopping it the documented way, would wait for ever."""
    signal.signal(signal.SIGINT, signal.default_int_handler)


def quiet_on_closed_pipe(main: Callable[Arguments, int]) -> Callable[Arguments, int]:
    """A command's ``main`` that exits with 1, without a traceback, when the reader of its
    output goes away (``scara-compare | head``), as Python's documentation advises (the
    note on SIGPIPE in :mod:`signal`): stdout is pointed at /dev/null, so that the
    interpreter's last flush does not fail again."""

    @functools.wraps(main)
    def run(*args: Arguments.args, **kwargs: Arguments.kwargs) -> int:
        try:
            code = main(*args, **kwargs)
            sys.stdout.flush()
        except BrokenPipeError:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return 1
        return code

    return run


def number(
    low: float, high: float = math.inf, *, integer: bool = False, low_open: bool = False
) -> Callable[[str], float]:
    """An argparse ``type`` for a finite number in ``[low, high]`` (``(low, high]`` if
    ``low_open``); argparse's error then names the flag and the bad value."""

    def parse(text: str) -> float:
        try:
            value: float = int(text) if integer else float(text)
        except ValueError:
            kind = "an integer" if integer else "a number"
            raise argparse.ArgumentTypeError(f"must be {kind}, got {text!r}") from None
        too_low = value <= low if low_open else value < low
        if not math.isfinite(value) or too_low or value > high:
            bound = f"({low:g}" if low_open else f"[{low:g}"
            raise argparse.ArgumentTypeError(f"must be in {bound}, {high:g}], got {text}")
        return value

    return parse


def add_comms_timeout_argument(
    parser: argparse.ArgumentParser, default: float | None, default_help: str
) -> None:
    """``--comms-timeout S``, the controller's comms-loss timeout: on the controller's command
    line and on the launcher's, which passes it on; ``default_help`` says what it defaults to
    there (the value and its lower bound are the controller's to state)."""
    parser.add_argument(
        "--comms-timeout",
        type=number(0.0, 10.0, low_open=True),
        default=default,
        metavar="S",
        help="s without a fresh joint state before a hold becomes a latched fault "
        f"({default_help})",
    )
