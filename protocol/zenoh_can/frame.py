"""The CAN-over-Zenoh frame format: one Zenoh sample carries the frames sent together.

Each frame is a 15-byte little-endian header ``<dIBBB`` (timestamp float64 in seconds since
the epoch, arbitration id uint32, flags uint8, dlc uint8, data length uint8) followed by its
data bytes; a sample is one or more frames back to back, in the order they were sent (a
plant's three joint-state frames travel as one sample: one message for the router and for
every receiver instead of three). Flags: 0x01 extended id, 0x02 remote, 0x04 error frame,
0x08 CAN FD, 0x10 bit rate switch, 0x20 error state indicator; 0x40 and 0x80 are reserved
and must be 0. The timestamp is the sender's clock when it sent the frame; a receiving bus
stamps its own receive time on the message, as python-can's other interfaces do.
"""

from __future__ import annotations

import math
import struct
from typing import Final

from can import Message

#: timestamp float64, arbitration id uint32, flags uint8, dlc uint8, data length uint8;
#: the data bytes follow.
HEADER: Final = struct.Struct("<dIBBB")

FLAG_EXTENDED: Final = 0x01
FLAG_REMOTE: Final = 0x02
FLAG_ERROR: Final = 0x04
FLAG_FD: Final = 0x08
FLAG_BRS: Final = 0x10
FLAG_ESI: Final = 0x20
_FLAGS_KNOWN: Final = 0x3F

_MAX_STANDARD_ID: Final = 0x7FF
_MAX_EXTENDED_ID: Final = 0x1FFFFFFF
_MAX_CLASSIC_DATA: Final = 8
_MAX_FD_DATA: Final = 64


class MalformedFrameError(ValueError):
    """A payload on the bus key is not a frame in this format."""


def encode_frame(msg: Message, timestamp: float | None = None) -> bytes:
    """Pack ``msg`` as header + data; refuse what a receiver would reject as malformed.

    ``timestamp`` overrides ``msg.timestamp`` (the bus passes the send time when the
    message carries none).
    """
    data = bytes(msg.data or b"")
    flags = (
        (FLAG_EXTENDED if msg.is_extended_id else 0)
        | (FLAG_REMOTE if msg.is_remote_frame else 0)
        | (FLAG_ERROR if msg.is_error_frame else 0)
        | (FLAG_FD if msg.is_fd else 0)
        | (FLAG_BRS if msg.bitrate_switch else 0)
        | (FLAG_ESI if msg.error_state_indicator else 0)
    )
    stamp = msg.timestamp if timestamp is None else timestamp
    _check_fields(stamp, msg.arbitration_id, flags, msg.dlc, len(data))
    return HEADER.pack(stamp, msg.arbitration_id, flags, msg.dlc, len(data)) + data


def decode_frames(payload: bytes, channel: str | None = None) -> list[Message]:
    """Unpack a sample into its received :class:`can.Message` s; MalformedFrameError if any
    part of it is not a frame (then none is taken: a sample is sent whole or not at all)."""
    if not payload:
        raise MalformedFrameError("empty payload")
    frames = []
    offset = 0
    while offset < len(payload):
        frame, offset = _decode_one(payload, offset, channel)
        frames.append(frame)
    return frames


def _decode_one(payload: bytes, offset: int, channel: str | None) -> tuple[Message, int]:
    if len(payload) - offset < HEADER.size:
        raise MalformedFrameError(
            f"{len(payload) - offset} bytes at offset {offset} are shorter than a header"
        )
    stamp, arbitration_id, flags, dlc, length = HEADER.unpack_from(payload, offset)
    start = offset + HEADER.size
    data = payload[start : start + length]
    if len(data) != length:
        raise MalformedFrameError(f"frame at offset {offset} is cut short")
    _check_fields(stamp, arbitration_id, flags, dlc, length)
    message = Message(
        timestamp=stamp,
        arbitration_id=arbitration_id,
        is_extended_id=bool(flags & FLAG_EXTENDED),
        is_remote_frame=bool(flags & FLAG_REMOTE),
        is_error_frame=bool(flags & FLAG_ERROR),
        is_fd=bool(flags & FLAG_FD),
        bitrate_switch=bool(flags & FLAG_BRS),
        error_state_indicator=bool(flags & FLAG_ESI),
        dlc=dlc,
        data=data,
        channel=channel,
        is_rx=True,
        check=False,
    )
    return message, start + length


def _check_fields(stamp: float, arbitration_id: int, flags: int, dlc: int, size: int) -> None:
    """The one set of rules both ends apply, so a frame we send is never dropped as malformed."""
    if not math.isfinite(stamp):
        raise MalformedFrameError(f"timestamp {stamp!r} is not finite")
    if flags & ~_FLAGS_KNOWN:
        raise MalformedFrameError(f"reserved flag bits set in {flags:#04x}")
    limit = _MAX_EXTENDED_ID if flags & FLAG_EXTENDED else _MAX_STANDARD_ID
    if not 0 <= arbitration_id <= limit:
        raise MalformedFrameError(f"arbitration id {arbitration_id:#x} exceeds {limit:#x}")
    most = _MAX_FD_DATA if flags & FLAG_FD else _MAX_CLASSIC_DATA
    if size > most:
        raise MalformedFrameError(f"{size} data bytes exceed {most}")
    if not 0 <= dlc <= most:
        raise MalformedFrameError(f"dlc {dlc} exceeds {most}")
