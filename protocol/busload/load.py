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

The schedule is the DBC's: each message's ``ScaraSchedule`` attribute says whether it goes
out every control tick (``tick``), every tick in lockstep only (``lockstep_tick``), on its
own ``GenMsgCycleTime`` (``cyclic``), or on events only (``event``, and the ISO-TP transfers
``isotp``: no cyclic load).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from protocol.codec import WIRE, IsoTpMessage, MessageCodec

MAX_DLC = 8
"""Classic CAN: at most 8 data bytes."""
STUFFED_OVERHEAD_BITS = 34
"""SOF, 11-bit ID, RTR, IDE, r0, DLC (4) and CRC (15): the non-data bits that are stuffed."""
UNSTUFFED_OVERHEAD_BITS = 13
"""CRC delimiter, ACK slot and delimiter, EOF (7) and inter-frame space (3): never stuffed."""
DEFAULT_BITRATE = 1_000_000


def frame_bits(dlc: int, *, stuffing: bool = True) -> int:
    """Bits a base frame with ``dlc`` data bytes takes on the bus, inter-frame space
    included; with ``stuffing`` the worst case of bit stuffing (Davis et al. 2007)."""
    if not 0 <= dlc <= MAX_DLC:
        raise ValueError(f"a classic CAN frame has 0..{MAX_DLC} data bytes, not {dlc}")
    stuffed = STUFFED_OVERHEAD_BITS + 8 * dlc
    stuff_bits = (stuffed - 1) // 4 if stuffing else 0
    return stuffed + UNSTUFFED_OVERHEAD_BITS + stuff_bits


def schedule(codec: MessageCodec | IsoTpMessage, *, lockstep: bool) -> tuple[str, float, float]:
    """``(label, frames per control tick, frames per second regardless of the tick)``."""
    if codec.schedule == "tick" or (codec.schedule == "lockstep_tick" and lockstep):
        return "every tick", 1.0, 0.0
    if codec.schedule == "lockstep_tick":
        return "lockstep only", 0.0, 0.0
    if codec.schedule == "cyclic" and codec.cycle_time:
        return f"{1.0 / codec.cycle_time:g} Hz", 0.0, 1.0 / codec.cycle_time
    return "event", 0.0, 0.0


FRAMES: tuple[MessageCodec | IsoTpMessage, ...] = tuple(
    sorted([*WIRE.messages.values(), *WIRE.isotp.values()], key=lambda codec: codec.frame_id)
)
"""The messages of ``scara.dbc``, lowest ID (highest priority) first."""


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


def check_rate(rate_hz: float, bitrate: int) -> None:
    if not (math.isfinite(rate_hz) and rate_hz > 0.0):
        raise ValueError(f"rate_hz must be a positive number, got {rate_hz!r}")
    if bitrate <= 0:
        raise ValueError(f"bitrate must be positive, got {bitrate!r}")


def bus_load(rate_hz: float, bitrate: int = DEFAULT_BITRATE, lockstep: bool = False) -> BusLoad:
    """Worst-case bus load of the wire at control rate ``rate_hz``."""
    check_rate(rate_hz, bitrate)
    loads = []
    for codec in FRAMES:
        label, per_tick, fixed_hz = schedule(codec, lockstep=lockstep)
        loads.append(
            FrameLoad(
                codec.name,
                codec.frame_id,
                codec.length,
                frame_bits(codec.length),
                label,
                per_tick * rate_hz + fixed_hz,
            )
        )
    return BusLoad(rate_hz, bitrate, lockstep, tuple(loads))


def max_rate_hz(target: float, bitrate: int = DEFAULT_BITRATE, lockstep: bool = False) -> float:
    """The highest control rate whose worst-case load stays at ``target``."""
    per_tick = fixed = 0.0
    for codec in FRAMES:
        _, frames_per_tick, fixed_hz = schedule(codec, lockstep=lockstep)
        per_tick += frames_per_tick * frame_bits(codec.length)
        fixed += fixed_hz * frame_bits(codec.length)
    return (target * bitrate - fixed) / per_tick
