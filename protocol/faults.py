"""Fault injection on the sending side of a bus: drop, corrupt, duplicate or reorder a share
of the frames.

Used by tests, by ``scara-soak`` and by hand
(``--inject-faults drop=0.05,corrupt=0.01,duplicate=0.01,reorder=0.01,seed=1``) to show that
the receivers detect what a bad wire does: a corrupted frame has one random data bit flipped,
which the CRC always catches; a dropped frame shows as a gap in the alive counter; a
duplicated one repeats its counter and a reordered one (held back and sent after the next)
comes with a stale counter, neither of which a receiver acts on.
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
    duplicated: int = 0
    reordered: int = 0


@dataclass(frozen=True, slots=True)
class FaultSpec:
    drop: float = 0.0
    corrupt: float = 0.0
    seed: int = 0
    duplicate: float = 0.0
    reorder: float = 0.0

    @classmethod
    def parse(cls, text: str) -> FaultSpec:
        """``drop=P,corrupt=P,duplicate=P,reorder=P,seed=N`` (any subset)."""
        values: dict[str, float] = {}
        for part in filter(None, text.split(",")):
            key, _, number = part.partition("=")
            if key not in (*_SHARES, "seed"):
                known = ", ".join((*_SHARES, "seed"))
                raise ConfigError(f"inject-faults.{key}", f"unknown; use {known}")
            try:
                values[key] = int(number) if key == "seed" else float(number)
            except ValueError as error:
                kind = "an integer" if key == "seed" else "a number"
                raise ConfigError(f"inject-faults.{key}", f"not {kind}: {number!r}") from error
        spec = cls(
            drop=values.get("drop", 0.0),
            corrupt=values.get("corrupt", 0.0),
            seed=int(values.get("seed", 0)),
            duplicate=values.get("duplicate", 0.0),
            reorder=values.get("reorder", 0.0),
        )
        for name in _SHARES:
            if not 0.0 <= getattr(spec, name) <= 1.0:
                raise ConfigError(f"inject-faults.{name}", "must be a probability in [0, 1]")
        if spec.drop + spec.corrupt > 1.0:
            raise ConfigError("inject-faults.corrupt", "drop and corrupt must sum to at most 1")
        return spec

    def text(self) -> str:
        """The spec as :meth:`parse` reads it (a command line's ``--inject-faults``)."""
        shares = ",".join(f"{name}={getattr(self, name):g}" for name in _SHARES)
        return f"{shares},seed={self.seed}"


_SHARES = ("drop", "corrupt", "duplicate", "reorder")


class FaultInjector(can.BusABC):
    """A bus that passes everything to ``inner`` except the frames it drops or corrupts."""

    def __init__(self, inner: can.BusABC, spec: FaultSpec) -> None:
        self.inner = inner
        self.spec = spec
        self.counts = InjectedCounts()
        self._random = random.Random(spec.seed)
        super().__init__(channel=getattr(inner, "channel_info", "faulty"))
        self.channel_info = f"faulty({getattr(inner, 'channel_info', '?')})"
        self._held: can.Message | None = None
        """A frame held back to go out after the next one (reordered)."""

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        for survivor in self._through(msg):
            self.inner.send(survivor, timeout)

    def send_many(self, messages: Sequence[can.Message]) -> None:
        """Frames sent together: each one dropped, corrupted, duplicated or reordered on its
        own."""
        survivors = [frame for message in messages for frame in self._through(message)]
        if survivors:
            send_frames(self.inner, survivors)

    def _through(self, msg: can.Message) -> list[can.Message]:
        """What the wire passes for ``msg``: nothing if dropped, one bit flipped if corrupted,
        twice if duplicated, nothing yet if held back (it follows the next frame)."""
        passed = self._altered(msg)
        if passed is None:
            return []
        held, self._held = self._held, None
        if held is None and self._draw(self.spec.reorder):
            self._held = passed
            self.counts.reordered += 1
            return []
        frames = [passed]
        if self._draw(self.spec.duplicate):
            frames.append(passed)
            self.counts.duplicated += 1
        return frames if held is None else [*frames, held]

    def _draw(self, share: float) -> bool:
        """True with probability ``share``; no draw for a share of 0, so that a seed drops
        and corrupts the same frames as before duplication and reordering existed."""
        return share > 0.0 and self._random.random() < share

    def _altered(self, msg: can.Message) -> can.Message | None:
        """``msg`` dropped (None) or with one bit flipped, by the spec's shares."""
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
