"""Worst-case load of the classic CAN bus, computed from the DBC frame layout.

Every frame is a classic CAN base frame (11-bit ID). Its length on the wire in the worst
case of bit stuffing is, for ``s`` data bytes::

    bits(s) = 8 s + 47 + floor((34 + 8 s - 1) / 4)        (= 55 + 10 s)

47 bits of fixed overhead (SOF 1, ID 11, RTR 1, IDE 1, r0 1, DLC 4, CRC 15, CRC delimiter
1, ACK slot and delimiter 2, EOF 7, inter-frame space 3); of these, the 34 bits from SOF to
the end of the CRC sequence and the 8 s data bits are subject to stuffing, and in the worst
case one stuff bit follows every 4 bits after the first. Source: R. I. Davis, A. Burns,
R. J. Bril and J. J. Lukkien, "Controller Area Network (CAN) schedulability analysis:
refuted, revisited and revised", Real-Time Systems 35(3):239-272, 2007, section 3
(``C_m = (g + 8 s_m + 13 + floor((g + 8 s_m - 1) / 4)) tau_bit``, g = 34 for 11-bit IDs,
i.e. ``(55 + 10 s_m) tau_bit``). Cross-checked against the Linux kernel's
``include/linux/can/length.h``, which gives 135 bits for a stuffed 8-byte base frame
including the intermission.

Schedule (DESIGN.md section 5 and the DBC comments): JointVelocityCommand and JointState1-3
once per control tick, StepSync once per tick in lockstep mode only, ControllerStatus and
PlantStatus at 10 Hz, EmergencyStop (and any other message of the DBC not listed here) on
events only, which carry no cyclic load.

Run ``scara-busload --help``.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources

import cantools

from protocol.robot import RobotConfig

DBC_TEXT = resources.files("protocol").joinpath("scara.dbc").read_text()

MAX_DLC = 8
"""Classic CAN: at most 8 data bytes."""
STUFFED_OVERHEAD_BITS = 34
"""SOF, 11-bit ID, RTR, IDE, r0, DLC (4) and CRC (15): the non-data bits that are stuffed."""
UNSTUFFED_OVERHEAD_BITS = 13
"""CRC delimiter, ACK slot and delimiter, EOF (7) and inter-frame space (3): never stuffed."""
E2E_HEADER_BITS = 12
"""Alive counter (4 bits) and CRC-8 (8 bits) in every frame of this wire."""

DEFAULT_BITRATE = 1_000_000
DEFAULT_RATES_HZ = (500.0, 1000.0)
TARGET_LOAD = 0.30
STATUS_RATE_HZ = 10.0

PER_TICK = ("JointVelocityCommand", "JointState1", "JointState2", "JointState3")
"""Sent once per control tick in both modes."""
LOCKSTEP_PER_TICK = ("StepSync",)
"""Sent once per control tick in lockstep mode only."""
STATUS = ("ControllerStatus", "PlantStatus")
"""Sent at :data:`STATUS_RATE_HZ` whatever the control rate."""

POSITION_RESOLUTION = (1e-6, 1e-6, 1e-6)
"""Required resolution of the joint positions: rad, rad, m."""
RATE_RESOLUTION = (1e-3, 1e-3, 1e-4)
"""Required resolution of joint velocities and commanded rates: rad/s, rad/s, m/s."""


def frame_bits(dlc: int, *, stuffing: bool = True) -> int:
    """Bits a base frame with ``dlc`` data bytes takes on the bus, inter-frame space
    included; with ``stuffing`` the worst case of bit stuffing (Davis et al. 2007)."""
    if not 0 <= dlc <= MAX_DLC:
        raise ValueError(f"a classic CAN frame has 0..{MAX_DLC} data bytes, not {dlc}")
    stuffed = STUFFED_OVERHEAD_BITS + 8 * dlc
    stuff_bits = (stuffed - 1) // 4 if stuffing else 0
    return stuffed + UNSTUFFED_OVERHEAD_BITS + stuff_bits


@dataclass(frozen=True, slots=True)
class Frame:
    """A message of the DBC as far as the bus is concerned."""

    name: str
    frame_id: int
    dlc: int


def dbc_frames(dbc_text: str = DBC_TEXT) -> tuple[Frame, ...]:
    """The messages of a DBC, by frame ID (lowest ID, highest priority, first)."""
    database = cantools.database.load_string(dbc_text, database_format="dbc")
    if not isinstance(database, cantools.database.can.Database):
        raise ValueError("not a CAN database")
    frames = (Frame(m.name, m.frame_id, m.length) for m in database.messages)
    return tuple(sorted(frames, key=lambda frame: frame.frame_id))


FRAMES = dbc_frames()
"""The frames of ``scara.dbc``."""
DLC_BY_NAME: dict[str, int] = {frame.name: frame.dlc for frame in FRAMES}
"""Data bytes of every message, by name."""


def schedule(name: str, *, lockstep: bool) -> tuple[str, float, float]:
    """``(label, frames per control tick, frames per second regardless of the tick)``."""
    if name in PER_TICK:
        return "every tick", 1.0, 0.0
    if name in LOCKSTEP_PER_TICK:
        return ("every tick", 1.0, 0.0) if lockstep else ("lockstep only", 0.0, 0.0)
    if name in STATUS:
        return f"{STATUS_RATE_HZ:g} Hz", 0.0, STATUS_RATE_HZ
    return "event", 0.0, 0.0


@dataclass(frozen=True, slots=True)
class FrameLoad:
    """One message's share of the bus."""

    name: str
    frame_id: int
    dlc: int
    bits: int
    schedule: str
    frames_per_s: float

    @property
    def bits_per_s(self) -> float:
        return self.bits * self.frames_per_s


@dataclass(frozen=True, slots=True)
class BusLoad:
    """The bus load at one control rate and bit rate."""

    rate_hz: float
    bitrate: int
    lockstep: bool
    frames: tuple[FrameLoad, ...]

    @property
    def frames_per_s(self) -> float:
        return sum(frame.frames_per_s for frame in self.frames)

    @property
    def bits_per_s(self) -> float:
        return sum(frame.bits_per_s for frame in self.frames)

    @property
    def fraction(self) -> float:
        """Share of the bus's bit time in use, 0..1 (above 1: the bus cannot carry it)."""
        return self.bits_per_s / self.bitrate


def _check(rate_hz: float, bitrate: int) -> None:
    if not (math.isfinite(rate_hz) and rate_hz > 0.0):
        raise ValueError(f"rate_hz must be a positive number, got {rate_hz!r}")
    if bitrate <= 0:
        raise ValueError(f"bitrate must be positive, got {bitrate!r}")


def bus_load(rate_hz: float, bitrate: int = DEFAULT_BITRATE, lockstep: bool = False) -> BusLoad:
    """Worst-case bus load of the wire at control rate ``rate_hz``."""
    _check(rate_hz, bitrate)
    loads = []
    for frame in FRAMES:
        label, per_tick, fixed_hz = schedule(frame.name, lockstep=lockstep)
        loads.append(
            FrameLoad(
                frame.name,
                frame.frame_id,
                frame.dlc,
                frame_bits(frame.dlc),
                label,
                per_tick * rate_hz + fixed_hz,
            )
        )
    return BusLoad(rate_hz, bitrate, lockstep, tuple(loads))


def max_rate_hz(
    target: float = TARGET_LOAD, bitrate: int = DEFAULT_BITRATE, lockstep: bool = False
) -> float:
    """The highest control rate whose worst-case load stays at ``target``."""
    per_tick = fixed = 0.0
    for frame in FRAMES:
        _, frames_per_tick, fixed_hz = schedule(frame.name, lockstep=lockstep)
        per_tick += frames_per_tick * frame_bits(frame.dlc)
        fixed += fixed_hz * frame_bits(frame.dlc)
    return (target * bitrate - fixed) / per_tick


def quantity_bits(low: float, high: float, resolution: float) -> int:
    """Fewest bits that give every step of ``resolution`` over ``[low, high]`` a code."""
    levels = math.floor(round((high - low) / resolution, 6)) + 1
    return (levels - 1).bit_length()


@dataclass(frozen=True, slots=True)
class Quantity:
    """A value that must cross the bus every control tick, at a given resolution."""

    sender: str
    name: str
    low: float
    high: float
    resolution: float

    @property
    def bits(self) -> int:
        return quantity_bits(self.low, self.high, self.resolution)


def required_quantities(robot: RobotConfig | None = None) -> tuple[Quantity, ...]:
    """What every tick must carry: the commanded rates (controller) over the speed limits,
    the joint positions over the joint limits and the joint velocities over the speed
    limits (plant), at the resolutions the issue asks for."""
    robot = robot or RobotConfig()
    joints = ("theta1", "theta2", "d3")
    quantities = [
        Quantity("controller", f"{joint} rate", -limit, limit, resolution)
        for joint, limit, resolution in zip(
            joints, robot.speed_limits, RATE_RESOLUTION, strict=True
        )
    ]
    quantities += [
        Quantity("plant", f"{joint} position", low, high, resolution)
        for joint, low, high, resolution in zip(
            joints, robot.joint_min, robot.joint_max, POSITION_RESOLUTION, strict=True
        )
    ]
    quantities += [
        Quantity("plant", f"{joint} velocity", -limit, limit, resolution)
        for joint, limit, resolution in zip(
            joints, robot.speed_limits, RATE_RESOLUTION, strict=True
        )
    ]
    return tuple(quantities)


@dataclass(frozen=True, slots=True)
class SenderMinimum:
    """The least one node can put on the bus per tick for its quantities."""

    sender: str
    quantities: tuple[Quantity, ...]
    data_bits: int
    frames: int
    bits: int
    bits_unstuffed: int


def sender_minimum(sender: str, quantities: Sequence[Quantity]) -> SenderMinimum:
    """A lower bound on one sender's bits per tick.

    Each frame carries at most ``8 * MAX_DLC - E2E_HEADER_BITS`` bits of data, so ``D`` data
    bits need at least ``k = ceil(D / 52)`` frames; together these hold at least
    ``ceil((D + 12 k) / 8)`` bytes, spread as evenly as possible. Frame bits grow with the
    DLC and with the number of frames, so this is the least possible, even if signals could
    be split across frames. Frames of different senders cannot be shared on CAN.
    """
    data_bits = sum(quantity.bits for quantity in quantities)
    capacity = 8 * MAX_DLC - E2E_HEADER_BITS
    frames = max(1, -(-data_bits // capacity))
    payload_bytes = -(-(data_bits + E2E_HEADER_BITS * frames) // 8)
    base, longer = divmod(payload_bytes, frames)
    dlcs = [base + 1] * longer + [base] * (frames - longer)
    return SenderMinimum(
        sender,
        tuple(quantities),
        data_bits,
        frames,
        sum(frame_bits(dlc) for dlc in dlcs),
        sum(frame_bits(dlc, stuffing=False) for dlc in dlcs),
    )


@dataclass(frozen=True, slots=True)
class MinimumLoad:
    """The least per-tick traffic that meets the resolution requirements."""

    senders: tuple[SenderMinimum, ...]

    @property
    def bits_per_tick(self) -> int:
        return sum(sender.bits for sender in self.senders)

    @property
    def bits_per_tick_unstuffed(self) -> int:
        return sum(sender.bits_unstuffed for sender in self.senders)

    def fraction(
        self, rate_hz: float, bitrate: int = DEFAULT_BITRATE, *, stuffing: bool = True
    ) -> float:
        """Least load at ``rate_hz`` (status frames and events not even counted)."""
        _check(rate_hz, bitrate)
        bits = self.bits_per_tick if stuffing else self.bits_per_tick_unstuffed
        return bits * rate_hz / bitrate


def minimum_load(robot: RobotConfig | None = None) -> MinimumLoad:
    """The lower bound of per-tick traffic for ``robot`` (default RobotConfig())."""
    quantities = required_quantities(robot)
    senders = dict.fromkeys(quantity.sender for quantity in quantities)
    return MinimumLoad(
        tuple(
            sender_minimum(sender, [q for q in quantities if q.sender == sender])
            for sender in senders
        )
    )


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
            str(frame.dlc),
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


def _positive(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


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
        type=_positive,
        nargs="+",
        default=list(DEFAULT_RATES_HZ),
        metavar="HZ",
        help="control rates in Hz (default: 500 1000)",
    )
    parser.add_argument(
        "--bitrate",
        type=_positive_int,
        default=DEFAULT_BITRATE,
        metavar="BIT/S",
        help="bus bit rate in bit/s (default: 1000000)",
    )
    parser.add_argument(
        "--lockstep", action="store_true", help="lockstep mode: a StepSync frame every tick"
    )
    args = parser.parse_args(argv)
    print(report(args.rate, args.bitrate, args.lockstep))
    return 0


if __name__ == "__main__":
    sys.exit(main())
