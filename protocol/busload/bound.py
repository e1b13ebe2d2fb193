"""The least bus load any frame layout could reach at the required resolutions.

Why the wire cannot go below a certain load whatever the layout: every quantity that must
cross the bus each tick needs a number of bits set by its range and resolution, each frame
carries at most 52 of them beside its 12-bit E2E header, and frames of different senders
cannot be shared on CAN. :func:`minimum_load` gives that bound for a robot's ranges.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from protocol.busload.load import DEFAULT_BITRATE, MAX_DLC, check_rate, frame_bits
from protocol.config import RobotConfig

E2E_HEADER_BITS = 12
"""Alive counter (4 bits) and CRC-8 (8 bits) in every frame of this wire."""
POSITION_RESOLUTION = (1e-6, 1e-6, 1e-6)
"""Required resolution of the joint positions: rad, rad, m."""
RATE_RESOLUTION = (1e-3, 1e-3, 1e-4)
"""Required resolution of joint velocities and commanded rates: rad/s, rad/s, m/s."""


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
        check_rate(rate_hz, bitrate)
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
