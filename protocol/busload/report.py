"""``scara-busload``: the bus load table of the wire, and the least load any layout could reach."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence

from protocol.busload.bound import minimum_load
from protocol.busload.load import DEFAULT_BITRATE, FRAMES, bus_load, max_rate_hz
from protocol.cli import add_verbosity, configure_logging, number, quiet_on_closed_pipe

DEFAULT_RATES_HZ = (500.0, 1000.0)
TARGET_LOAD = 0.30


def _percent(fraction: float) -> str:
    return f"{100.0 * fraction:.1f} %"


def _highest(bitrate: int, lockstep: bool) -> str:
    rate = max_rate_hz(TARGET_LOAD, bitrate, lockstep)
    return f"{math.floor(rate)} Hz" if rate >= 1.0 else "none"


def _row(cells: Sequence[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def report(
    rates_hz: Sequence[float], bitrate: int = DEFAULT_BITRATE, lockstep: bool = False
) -> str:
    """The Markdown report ``main`` prints."""
    loads = [bus_load(rate, bitrate, lockstep) for rate in rates_hz]
    mode = "lockstep" if lockstep else "real-time"
    lines = [
        f"# CAN bus load: {mode} mode, {bitrate / 1000:g} kbit/s, worst-case bit stuffing",
        "",
        _row(
            ["Frame", "ID", "DLC", "Bits", "Schedule"]
            + [f"{load.rate_hz:g} Hz: {unit}" for load in loads for unit in ("frames/s", "bit/s")]
        ),
        _row(["---"] * (5 + 2 * len(loads))),
    ]
    for index, frame in enumerate(FRAMES):
        first = loads[0].frames[index]
        cells = [
            frame.name,
            f"0x{frame.frame_id:03X}",
            str(frame.length),
            str(first.bits),
            first.schedule,
        ]
        for load in loads:
            cells += [f"{load.frames[index].frames_per_s:g}", f"{load.frames[index].bits_per_s:g}"]
        lines.append(_row(cells))
    totals = ["**Total**", "", "", "", ""]
    for load in loads:
        totals += [f"{load.frames_per_s:g}", f"{load.bits_per_s:g}"]
    lines.append(_row(totals))
    lines.append(
        _row(
            ["**Load**", "", "", "", ""]
            + [x for load in loads for x in ("", _percent(load.fraction))]
        )
    )
    under = [f"{load.rate_hz:g} Hz" for load in loads if load.fraction < TARGET_LOAD]
    over = [f"{load.rate_hz:g} Hz" for load in loads if load.fraction >= TARGET_LOAD]
    lines += [
        "",
        f"Under {_percent(TARGET_LOAD)}: {', '.join(under) or 'none'}; "
        f"at or above: {', '.join(over) or 'none'}. "
        f"Highest control rate under {_percent(TARGET_LOAD)}: {_highest(bitrate, lockstep)}.",
    ]
    minimum = minimum_load()
    lines += [
        "",
        "## Least possible load for the required resolutions",
        "",
        "Positions 1 urad / 1 um over the joint limits, velocities and commanded rates "
        "1e-3 rad/s / 1e-4 m/s over the speed limits (RobotConfig()), a 4-bit counter and an "
        "8-bit CRC per frame, every joint state sent every tick; no flags, no status frames.",
        "",
        _row(["Sender", "Quantities (bits)", "Data bits/tick", "Frames/tick", "Bits/tick"]),
        _row(["---"] * 5),
    ]
    for sender in minimum.senders:
        quantities = ", ".join(f"{q.name} {q.bits}" for q in sender.quantities)
        lines.append(
            _row(
                [
                    sender.sender,
                    quantities,
                    str(sender.data_bits),
                    str(sender.frames),
                    str(sender.bits),
                ]
            )
        )
    lines += [
        _row(
            [
                "**Total**",
                "",
                str(sum(s.data_bits for s in minimum.senders)),
                str(sum(s.frames for s in minimum.senders)),
                str(minimum.bits_per_tick),
            ]
        ),
        "",
    ]
    for load in loads:
        least = minimum.fraction(load.rate_hz, bitrate)
        bare = minimum.fraction(load.rate_hz, bitrate, stuffing=False)
        verdict = "under" if least < TARGET_LOAD else "cannot be under"
        lines.append(
            f"- {load.rate_hz:g} Hz: at least {_percent(least)} "
            f"({_percent(bare)} with no stuff bits at all): {verdict} {_percent(TARGET_LOAD)}."
        )
    return "\n".join(lines)


@quiet_on_closed_pipe
def main(argv: Sequence[str] | None = None) -> int:
    """Print the bus load table (Markdown) of the wire defined by scara.dbc."""
    parser = argparse.ArgumentParser(
        prog="scara-busload",
        description=(
            "Worst-case classic CAN bus load of the SCARA wire, computed from the frame "
            "layout in scara.dbc (11-bit IDs, worst-case bit stuffing), with the least "
            "load any layout could reach at the required resolutions."
        ),
    )
    parser.add_argument(
        "--rate",
        type=number(0.0, low_open=True),
        nargs="+",
        default=list(DEFAULT_RATES_HZ),
        metavar="HZ",
        help="control rates in Hz (default: 500 1000)",
    )
    parser.add_argument(
        "--bitrate",
        type=number(1, integer=True),
        default=DEFAULT_BITRATE,
        metavar="BIT/S",
        help="bus bit rate in bit/s (default: 1000000)",
    )
    parser.add_argument(
        "--lockstep", action="store_true", help="lockstep mode: a StepSync frame every tick"
    )
    add_verbosity(parser)
    args = parser.parse_args(argv)
    configure_logging(args.verbose)
    print(report(args.rate, args.bitrate, args.lockstep))
    return 0


if __name__ == "__main__":
    sys.exit(main())
