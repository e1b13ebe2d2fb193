"""Fault injection on the sending side of a bus: drop or corrupt a share of the frames.

Used by tests and by hand (``--inject-faults drop=0.05,corrupt=0.01,seed=1``) to show that
the receivers detect what a bad wire does: a corrupted frame has one random data bit flipped,
which the CRC always catches, and a dropped frame shows as a gap in the alive counter.
"""

from __future__ import annotations

import argparse
import random
from collections.abc import Sequence
from dataclasses import dataclass

import can

from protocol.bus import send_frames
from protocol.errors import ConfigError


@dataclass(slots=True)
class InjectedCounts:
    sent: int = 0
    dropped: int = 0
    corrupted: int = 0


@dataclass(frozen=True, slots=True)
class FaultSpec:
    drop: float = 0.0
    corrupt: float = 0.0
    seed: int = 0

    @classmethod
    def parse(cls, text: str) -> FaultSpec:
        """``drop=P,corrupt=P,seed=N`` (any subset)."""
        values: dict[str, float] = {}
        for part in filter(None, text.split(",")):
            key, _, number = part.partition("=")
            if key not in ("drop", "corrupt", "seed"):
                raise ConfigError(f"inject-faults.{key}", "unknown; use drop, corrupt, seed")
            try:
                values[key] = int(number) if key == "seed" else float(number)
            except ValueError as error:
                kind = "an integer" if key == "seed" else "a number"
                raise ConfigError(f"inject-faults.{key}", f"not {kind}: {number!r}") from error
        spec = cls(values.get("drop", 0.0), values.get("corrupt", 0.0), int(values.get("seed", 0)))
        for name in ("drop", "corrupt"):
            if not 0.0 <= getattr(spec, name) <= 1.0:
                raise ConfigError(f"inject-faults.{name}", "must be a probability in [0, 1]")
        return spec


class FaultInjector(can.BusABC):
    """A bus that passes everything to ``inner`` except the frames it drops or corrupts."""

    def __init__(self, inner: can.BusABC, spec: FaultSpec) -> None:
        self.inner = inner
        self.spec = spec
        self.counts = InjectedCounts()
        self._random = random.Random(spec.seed)
        super().__init__(channel=getattr(inner, "channel_info", "faulty"))
        self.channel_info = f"faulty({getattr(inner, 'channel_info', '?')})"

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        survivor = self._through(msg)
        if survivor is not None:
            self.inner.send(survivor, timeout)

    def send_many(self, messages: Sequence[can.Message]) -> None:
        """Frames sent together: each one dropped or corrupted on its own."""
        survivors = [m for m in map(self._through, messages) if m is not None]
        if survivors:
            send_frames(self.inner, survivors)

    def _through(self, msg: can.Message) -> can.Message | None:
        """``msg`` as the wire passes it: None if dropped, with one bit flipped if corrupted."""
        draw = self._random.random()
        if draw < self.spec.drop:
            self.counts.dropped += 1
            return None
        if draw < self.spec.drop + self.spec.corrupt and msg.dlc:
            data = bytearray(msg.data)
            bit = self._random.randrange(8 * len(data))
            data[bit // 8] ^= 1 << (bit % 8)
            msg = can.Message(
                arbitration_id=msg.arbitration_id,
                data=bytes(data),
                is_extended_id=msg.is_extended_id,
                timestamp=msg.timestamp,
            )
            self.counts.corrupted += 1
        self.counts.sent += 1
        return msg

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.inner.recv(timeout), True

    def shutdown(self) -> None:
        self.inner.shutdown()
        super().shutdown()


def add_fault_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--inject-faults",
        metavar="SPEC",
        help="drop/corrupt frames this node sends, e.g. drop=0.05,corrupt=0.01,seed=1 (tests)",
    )
