"""MCAP as a python-can log format: :class:`MCAPWriter` and :class:`MCAPReader`.

Registered through python-can's ``can.io.message_writer`` / ``can.io.message_reader`` entry
points for ``.mcap``, so ``python -m can.logger -f run.mcap`` and ``python -m can.player
run.mcap`` work, and so does conversion to and from ``.blf``, ``.asc``, ``.csv`` or ``.log``
with python-can's own readers and writers.

The layout, one idea: a frame is an MCAP message whose log time is the bus timestamp in
nanoseconds. Its channel says everything else about it: one channel per kind of frame of the
DBC's (``can/JointState1``, ``can/ScenarioUpload/remote``), the ID and the flags in the
channel's metadata, the message's data the frame's raw data bytes. Every other frame (an ID
the DBC does not define, any extended ID, an error frame) goes to one channel, ``can/other``
(its metadata says ``id_in_data``), its data preceded by 4 bytes big-endian of SocketCAN's
``can_id``: the ID with ``CAN_EFF_FLAG`` (bit 31), ``CAN_RTR_FLAG`` (30) and ``CAN_ERR_FLAG``
(29). A channel per foreign ID would let a flood of random extended IDs grow the writer's
channels, and memory, without bound. The message encoding is ``can-frame`` and there is no
schema (the data is bytes). Chunks are zstd-compressed and indexed (a chunk index, no
message indexes: they took half a file, and the writer kept each chunk's offsets in memory
until the end, 1.35 MB per 1,000 chunks, 10 chunks a second), so a file cut short is readable
up to its last complete chunk.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import can
import zstandard
from can.io.generic import BinaryIOMessageReader, BinaryIOMessageWriter
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType, Writer

from protocol.codec import WIRE
from protocol.errors import ScaraError

DAMAGE_ERRORS = (
    McapError,
    EOFError,
    ValueError,
    KeyError,
    struct.error,
    OverflowError,
    MemoryError,
    zstandard.ZstdError,
)
"""What the mcap library raises on a damaged file (cut, corrupt chunk, wild lengths)."""
READ_ERRORS = (*DAMAGE_ERRORS, OSError)
"""And a file that cannot be read at all."""

FRAME_ENCODING = "can-frame"
TOPIC_PREFIX = "can/"
CHUNK_SIZE = 256 * 1024
"""bytes per chunk at most, before compression (``scara-record`` ends its chunks sooner, by
time: :data:`FLUSH_PERIOD`)."""
FLUSH_PERIOD = 0.1
"""s: the most of its last frames a ``scara-record`` killed (kill -9) loses. Its writer ends
the chunk and hands it to the OS once the chunk's first message is this old: mcap's Writer
ends chunks only by size, and a chunk still in memory dies with the process."""
PROFILE = "scara"
DBC_NAMES = {message.frame_id: name for name, message in WIRE.messages.items()} | {
    message.frame_id: name for name, message in WIRE.isotp.items()
}
"""The DBC's message names by frame ID: the names of the channels of our frames."""


class RecordingError(ScaraError):
    """A file that is not a readable MCAP recording (empty, truncated, another format)."""


EXTENDED_FLAG = 0x8000_0000
REMOTE_FLAG = 0x4000_0000
ERROR_FLAG = 0x2000_0000
"""SocketCAN's CAN_EFF_FLAG, CAN_RTR_FLAG and CAN_ERR_FLAG, in ``can/other``'s 4-byte ID."""
ID_MASK = 0x1FFF_FFFF
"""The ID's 29 bits under the flags (SocketCAN's CAN_EFF_MASK)."""
CAN_ID = struct.Struct(">I")
OTHER_TOPIC = TOPIC_PREFIX + "other"


@dataclass(frozen=True, slots=True)
class FrameKind:
    """What a channel's frames share: everything about a frame but its time and data (and,
    with ``id_in_data``, its ID and flags, which ``can/other`` carries in each message)."""

    arbitration_id: int
    is_extended_id: bool = False
    is_remote_frame: bool = False
    is_error_frame: bool = False
    is_fd: bool = False
    bitrate_switch: bool = False
    channel: str = ""
    id_in_data: bool = False

    @classmethod
    def of(cls, message: can.Message) -> FrameKind:
        channel = "" if message.channel is None else str(message.channel)
        ours = not (message.is_extended_id or message.is_error_frame or message.is_fd)
        if ours and message.arbitration_id in DBC_NAMES:
            return cls(
                message.arbitration_id,
                is_remote_frame=message.is_remote_frame,
                channel=channel,
            )
        return cls(
            0,
            is_fd=message.is_fd,
            bitrate_switch=message.bitrate_switch,
            channel=channel,
            id_in_data=True,
        )

    @property
    def topic(self) -> str:
        """``can/<DBC name>`` for our frames, ``can/other`` for any other."""
        if self.id_in_data:
            return OTHER_TOPIC
        return (
            TOPIC_PREFIX
            + DBC_NAMES[self.arbitration_id]
            + ("/remote" if self.is_remote_frame else "")
        )

    def data(self, message: can.Message) -> bytes:
        """What a message of this channel carries of ``message``."""
        if not self.id_in_data:
            return bytes(message.data)
        can_id = message.arbitration_id
        can_id |= EXTENDED_FLAG if message.is_extended_id else 0
        can_id |= REMOTE_FLAG if message.is_remote_frame else 0
        can_id |= ERROR_FLAG if message.is_error_frame else 0
        return CAN_ID.pack(can_id) + bytes(message.data)

    def message(self, log_time: int, data: bytes) -> can.Message:
        """The frame a message of this channel holds; :class:`RecordingError` if it is
        shorter than ``can/other``'s ID."""
        arbitration_id = self.arbitration_id
        extended, remote, error = self.is_extended_id, self.is_remote_frame, self.is_error_frame
        if self.id_in_data:
            if len(data) < CAN_ID.size:
                raise RecordingError(f"a frame on {OTHER_TOPIC} has {len(data)} bytes, no ID")
            (can_id,) = CAN_ID.unpack_from(data)
            data = data[CAN_ID.size :]
            arbitration_id = can_id & ID_MASK
            extended, remote, error = (
                bool(can_id & flag) for flag in (EXTENDED_FLAG, REMOTE_FLAG, ERROR_FLAG)
            )
        return can.Message(
            timestamp=log_time / 1e9,
            arbitration_id=arbitration_id,
            is_extended_id=extended,
            is_remote_frame=remote,
            is_error_frame=error,
            is_fd=self.is_fd,
            bitrate_switch=self.bitrate_switch,
            channel=self.channel or None,
            dlc=len(data),
            data=data,
        )

    def metadata(self) -> dict[str, str]:
        return {
            "arbitration_id": str(self.arbitration_id),
            "is_extended_id": str(self.is_extended_id).lower(),
            "is_remote_frame": str(self.is_remote_frame).lower(),
            "is_error_frame": str(self.is_error_frame).lower(),
            "is_fd": str(self.is_fd).lower(),
            "bitrate_switch": str(self.bitrate_switch).lower(),
            "channel": self.channel,
            "id_in_data": str(self.id_in_data).lower(),
        }

    @classmethod
    def from_metadata(cls, metadata: dict[str, str]) -> FrameKind:
        try:
            return cls(
                int(metadata["arbitration_id"]),
                metadata.get("is_extended_id") == "true",
                metadata.get("is_remote_frame") == "true",
                metadata.get("is_error_frame") == "true",
                metadata.get("is_fd") == "true",
                metadata.get("bitrate_switch") == "true",
                metadata.get("channel", ""),
                metadata.get("id_in_data") == "true",
            )
        except (KeyError, ValueError) as error:
            raise RecordingError(f"a CAN channel's metadata is incomplete: {error}") from None


def open_writer(stream: IO[bytes]) -> Writer:
    """An MCAP writer with zstd chunks of :data:`CHUNK_SIZE`, started."""
    writer = Writer(
        stream,
        chunk_size=CHUNK_SIZE,
        compression=CompressionType.ZSTD,
        index_types=IndexType.ALL & ~IndexType.MESSAGE,
    )
    writer.start(profile=PROFILE, library="scara-fuzzy recorder")
    return writer


def finish(writer: Writer) -> None:
    """Write the summary and the index: ``Writer.finish`` (unannotated in mcap)."""
    writer.finish()  # type: ignore[no-untyped-call]


def flush(writer: Writer) -> None:
    """End the chunk in progress and hand every byte written so far to the OS (which keeps
    them if the process is killed): ``Writer.flush`` (unannotated in mcap)."""
    writer.flush()  # type: ignore[no-untyped-call]


COUNTS_TOPIC = "recorder/counts"
"""The channel of the recorder's own counts, one message at the end of each chunk: what a
file cut short still says of the frames its recorder received."""
COUNTS_SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "the frames scara-record had received and dropped (full queue) so far",
    "type": "object",
    "properties": {
        "received": {"type": "integer", "minimum": 0},
        "dropped": {"type": "integer", "minimum": 0},
    },
    "required": ["received", "dropped"],
}


@dataclass(frozen=True, slots=True)
class RecorderCounts:
    """Frames a recorder had received so far, and how many of them it dropped."""

    received: int
    dropped: int

    def encode(self) -> bytes:
        return json.dumps({"received": self.received, "dropped": self.dropped}).encode()

    @classmethod
    def decode(cls, data: bytes) -> RecorderCounts:
        try:
            fields = json.loads(data)
            return cls(int(fields["received"]), int(fields["dropped"]))
        except (ValueError, KeyError, TypeError) as error:
            raise RecordingError(f"a {COUNTS_TOPIC} message is malformed: {error}") from None


def counts_channel(writer: Writer) -> int:
    """Register the :data:`COUNTS_TOPIC` channel (and its schema) on ``writer``."""
    schema_id = writer.register_schema(
        COUNTS_TOPIC, "jsonschema", json.dumps(COUNTS_SCHEMA).encode()
    )
    return writer.register_channel(COUNTS_TOPIC, "json", schema_id)


def end_chunk(writer: Writer, counts_id: int, counts: RecorderCounts, stamp: int) -> None:
    """``counts`` (on channel ``counts_id``) as the chunk's last message, logged at ``stamp``
    ns, then the chunk to the OS: what ``scara-record`` does every :data:`FLUSH_PERIOD`."""
    writer.add_message(counts_id, stamp, counts.encode(), stamp)
    flush(writer)


class FrameChannels:
    """The CAN channels of one MCAP writer, registered as their first frame comes."""

    def __init__(self, writer: Writer) -> None:
        self.writer = writer
        self._ids: dict[FrameKind, int] = {}
        self.written = 0

    def write(self, message: can.Message) -> None:
        kind = FrameKind.of(message)
        channel_id = self._ids.get(kind)
        if channel_id is None:
            channel_id = self.writer.register_channel(
                kind.topic, FRAME_ENCODING, schema_id=0, metadata=kind.metadata()
            )
            self._ids[kind] = channel_id
        stamp = round(message.timestamp * 1e9)
        self.writer.add_message(channel_id, stamp, kind.data(message), stamp, self.written)
        self.written += 1


class MCAPWriter(BinaryIOMessageWriter):
    """python-can's writer for ``.mcap`` (see the module docstring for the layout)."""

    def __init__(self, file: Any, **kwargs: Any) -> None:
        super().__init__(file, mode="wb")
        self._writer = open_writer(self.file)  # type: ignore[arg-type]
        self._frames = FrameChannels(self._writer)

    def on_message_received(self, msg: can.Message) -> None:
        self._frames.write(msg)

    def stop(self) -> None:
        finish(self._writer)
        super().stop()


def frames(stream: IO[bytes]) -> Iterator[can.Message]:
    """The CAN frames of an MCAP stream in the order they were written; :class:`RecordingError`
    if it is not a readable MCAP file."""
    try:
        reader = make_reader(stream)
        kinds: dict[int, FrameKind] = {}
        # in the file's order, which is the order the frames were received in (a log-time
        # merge across chunks would cost half the reading speed for nothing)
        for _, channel, message in reader.iter_messages(log_time_order=False):
            if channel.message_encoding != FRAME_ENCODING:
                continue  # decoded state, the run log: not frames
            kind = kinds.get(channel.id)
            if kind is None:
                kind = kinds[channel.id] = FrameKind.from_metadata(dict(channel.metadata))
            yield kind.message(message.log_time, message.data)
    except READ_ERRORS as error:
        raise RecordingError(
            f"not a readable MCAP recording ({error}); if its writer was killed, "
            "'scara-record recover FILE' rewrites it"
        ) from None


class MCAPReader(BinaryIOMessageReader):
    """python-can's reader for ``.mcap``: the frames in the order they were written."""

    def __init__(self, file: Any, **kwargs: Any) -> None:
        super().__init__(file, mode="rb")

    def __iter__(self) -> Iterator[can.Message]:
        yield from frames(self.file)  # type: ignore[arg-type]
        self.stop()


def read_attachments(path: Path) -> dict[str, bytes]:
    """The attachments of an MCAP file by name; :class:`RecordingError` if unreadable."""
    check_mcap(path)
    try:
        with path.open("rb") as stream:
            return {a.name: a.data for a in make_reader(stream).iter_attachments()}
    except READ_ERRORS as error:
        raise RecordingError(
            f"{path}: not a readable MCAP recording ({error}); if its writer was killed, "
            "'scara-record recover FILE' rewrites it"
        ) from None


def check_mcap(path: Path) -> None:
    """:class:`RecordingError` naming ``path`` unless it starts like an MCAP file."""
    try:
        with path.open("rb") as stream:
            head = stream.read(8)
    except OSError as error:
        raise RecordingError(f"{path}: {error.strerror}") from None
    if not head:
        raise RecordingError(f"{path}: the file is empty")
    if head != b"\x89MCAP0\r\n":
        raise RecordingError(f"{path}: not an MCAP file (it does not start with the MCAP magic)")
