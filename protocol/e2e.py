"""The receiving side of the E2E header: alive counters checked per frame ID.

The CRC is checked by the codec (a corrupt frame raises :class:`DecodeError`); this module
classifies the counters of the frames that decoded, in the spirit of AUTOSAR E2E profile
1's state machine, and counts what it saw. Only a frame classified ``OK`` or ``LOST`` (newer,
with some frames missed before it) may be acted on.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import can

from protocol.codec import COUNTER_MODULO, WIRE, MessageCodec
from protocol.errors import DecodeError

MAX_FORWARD_JUMP = COUNTER_MODULO // 2
"""A counter more than this far ahead is taken as an old frame arriving late (stale)."""
RESYNC_AFTER = 0.5
"""s of silence on a frame ID after which its counter starts over: no frame is that late
on a bus, so a jump back after such a gap is a sender that restarted (a new bridge's first
command, say), not an old frame; AUTOSAR's E2E state machine re-initialises the same way."""


class Check(Enum):
    FIRST = "first"
    OK = "ok"
    LOST = "lost"
    REPEATED = "repeated"
    STALE = "stale"

    @property
    def usable(self) -> bool:
        return self in (Check.FIRST, Check.OK, Check.LOST)


@dataclass(slots=True)
class E2ECounts:
    """What a receiver has seen, for status frames and the end-of-run report."""

    ok: int = 0
    lost: int = 0
    repeated: int = 0
    stale: int = 0
    corrupt: int = 0
    unknown: int = 0
    """Frames with an ID the DBC does not define (another system's traffic, or a fault)."""

    @property
    def bad(self) -> int:
        """Frames of this node's IDs received but not acted on."""
        return self.repeated + self.stale + self.corrupt


@dataclass(slots=True)
class E2EMonitor:
    """Alive-counter checks for every frame ID a node receives."""

    counts: E2ECounts = field(default_factory=E2ECounts)
    _last: dict[int, int] = field(default_factory=dict)
    _stale: dict[int, int] = field(default_factory=dict)
    _seen: dict[int, float] = field(default_factory=dict)

    def check(self, frame_id: int, counter: int, received: float | None = None) -> Check:
        """Classify ``counter``; with ``received`` (s), a frame ID silent for
        :data:`RESYNC_AFTER` starts over."""
        last = self._last.get(frame_id)
        if received is not None:
            silent = received - self._seen.get(frame_id, received) > RESYNC_AFTER
            self._seen[frame_id] = received
            if silent:
                last = None
                self._stale.pop(frame_id, None)
        if last is None:
            self._last[frame_id] = counter
            self.counts.ok += 1
            return Check.FIRST
        step = (counter - last) % COUNTER_MODULO
        if step <= MAX_FORWARD_JUMP:
            # Only a stale frame's own successor, next in line, may continue it: one left
            # from long ago would let a reordered old frame through (5, 4 after a stale 3).
            self._stale.pop(frame_id, None)
        if step == 0:
            self.counts.repeated += 1
            return Check.REPEATED
        if step > MAX_FORWARD_JUMP:
            # Either an old frame arriving late, or more than MAX_FORWARD_JUMP frames lost.
            # Two frames in a row that continue each other decide it: the sender has moved on.
            if self._stale.get(frame_id) == (counter - 1) % COUNTER_MODULO:
                del self._stale[frame_id]
                self._last[frame_id] = counter
                self.counts.ok += 1
                return Check.OK
            self._stale[frame_id] = counter
            self.counts.stale += 1
            return Check.STALE
        self._last[frame_id] = counter
        self.counts.ok += 1
        if step > 1:
            self.counts.lost += step - 1
            return Check.LOST
        return Check.OK

    def accept(
        self, message: can.Message, wanted: set[int]
    ) -> tuple[MessageCodec, int, Any] | None:
        """A received frame, decoded (codec, counter, record), if it may be acted on; None
        otherwise.

        Frames this node does not listen to (other IDs, extended, remote, error frames) are
        passed over, those with an ID the DBC does not define counted as unknown; ones that
        fail to decode are counted as corrupt; ones whose counter is not usable are counted
        by :meth:`check`.
        """
        if message.is_error_frame or message.is_remote_frame:
            return None
        if message.arbitration_id not in wanted or message.is_extended_id:
            if message.is_extended_id or message.arbitration_id not in WIRE.defined_ids:
                self.counts.unknown += 1
            return None
        try:
            codec, counter, record = WIRE.decode(message.arbitration_id, message.data)
        except DecodeError:
            self.corrupt()
            return None
        if not self.check(codec.frame_id, counter, message.timestamp).usable:
            return None
        return codec, counter, record

    def corrupt(self) -> None:
        """Count a frame that failed to decode (bad CRC, length, ID or range)."""
        self.counts.corrupt += 1

    def forget(self) -> None:
        """Start over, e.g. when a restarted peer begins again."""
        self._last.clear()
        self._stale.clear()
        self._seen.clear()
