"""Rewrite an MCAP file whose writer died (``kill -9``, power loss) as a valid, indexed one.

A recording is written in chunks; a writer killed mid-run leaves the header, the complete
chunks and perhaps part of the next one, with no summary or index. :func:`recover` reads the
records in order until the data stops making sense, copies schemas, channels, messages,
attachments and metadata into a new file (chunked, compressed, indexed), and reports what it
kept and what it could not: the bytes after the last complete record (and the log times of
a chunk cut there, from its header), and, from the recorder's own counts in the file
(``recorder/counts``), how many of the frames it had received are not in the file. What the
recorder received after its last flush never reached the file: that, the file cannot count.
"""

from __future__ import annotations

import contextlib
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from recorder.mcap_can import (
    COUNTS_TOPIC,
    DAMAGE_ERRORS,
    FLUSH_PERIOD,
    FRAME_ENCODING,
    FrameKind,
    RecorderCounts,
    RecordingError,
    check_mcap,
    finish,
    open_writer,
)

RECORDING_METADATA = "recording"
"""The metadata ``scara-record`` writes when it finishes a file (its final counts)."""
_CHUNK_HEAD = struct.Struct("<BQQQ")
"""A chunk record's start: opcode, length, then its messages' first and last log time."""


INDEXES = frozenset(
    {
        Opcode.MESSAGE_INDEX,
        Opcode.CHUNK_INDEX,
        Opcode.ATTACHMENT_INDEX,
        Opcode.METADATA_INDEX,
        Opcode.STATISTICS,
        Opcode.SUMMARY_OFFSET,
        Opcode.DATA_END,
        Opcode.FOOTER,
    }
)
"""Records that only index or sum up the others: cutting one loses no data."""


@dataclass(frozen=True, slots=True)
class Cut:
    """The unreadable end of a file cut short: its last ``size`` bytes."""

    size: int
    opcode: Opcode | None
    """The record it is the start of; None if it is not the start of a record."""
    record_size: int | None
    """That record's whole size, if its length field survived."""
    chunk_log_times: tuple[int, int] | None
    """Of a cut chunk whose header survived: its messages' first and last log time (ns)."""

    def summary(self) -> str:
        if self.opcode is None:
            return f"the last {self.size} bytes, not the start of a record"
        text = f"the last {self.size} bytes, the start of a {self.opcode.name.lower()} record"
        if self.record_size is not None:
            text += f" of {self.record_size} bytes"
        if self.chunk_log_times is not None:
            first, last = self.chunk_log_times
            text += f", its messages logged from {first / 1e9:.6f} to {last / 1e9:.6f} s"
        return text + (" (an index: no data in it)" if self.opcode in INDEXES else "")


@dataclass(frozen=True, slots=True)
class RecoveryReport:
    frames: int
    """CAN frames kept."""
    other_messages: int
    """Messages kept that are not frames: decoded state, the recorder's counts."""
    channels: int
    attachments: int
    metadata: int
    cut: Cut | None
    """None: the file ended on a complete record."""
    was_complete: bool
    """The file had its footer: nothing was missing."""
    log_times: tuple[int, int] | None
    """The first and last log time kept (ns); None if no message was."""
    counts: RecorderCounts | None
    """The recorder's last counts in the file: its final ones if complete, else those at its
    last flush; None if the file has none (another writer, an older recorder)."""
    counts_log_time: int | None
    """When the recorder wrote :attr:`counts` at a flush (ns); None: its final counts, from
    the metadata it writes when it finishes."""

    @property
    def frames_not_kept(self) -> int | None:
        """Of the frames the recorder had received by its last counts, those not in the file:
        the dropped ones, and the queued ones not written. The recorder writes in the order
        it received, and the file keeps a prefix of what it wrote, so every frame written
        after the counts was received before any received after them."""
        if self.counts is None:
            return None
        return max(self.counts.dropped, self.counts.received - self.frames)

    def summary(self, out: Path) -> str:
        kept = (
            f"kept {self.frames} CAN frames and {self.other_messages} other messages on "
            f"{self.channels} channels, {self.attachments} attachments and {self.metadata} "
            f"metadata records, into {out}"
        )
        if self.log_times is not None:
            kept += f"; log time {self.log_times[0] / 1e9:.6f} to {self.log_times[1] / 1e9:.6f} s"
        counts = self._counts_line()
        if self.was_complete:
            return "\n".join(["the recording was complete: nothing was cut from it", kept, counts])
        last = (
            "its start" if self.log_times is None else f"log time {self.log_times[1] / 1e9:.6f} s"
        )
        lines = [
            "the recording was cut short (its recorder did not finish it)",
            kept,
            counts,
            "cut off: "
            + (
                "nothing, the file ends on a complete record"
                if self.cut is None
                else self.cut.summary()
            ),
            f"lost: whatever the recorder received after {last} (until it died) never reached "
            "the file and cannot be counted from it; scara-record flushes "
            f"{FLUSH_PERIOD:g} s after a chunk's first frame, so that is its last "
            f"{FLUSH_PERIOD:g} s if it kept pace",
        ]
        return "\n".join(lines)

    def _counts_line(self) -> str:
        not_kept = self.frames_not_kept
        if self.counts is None or not_kept is None:
            return "the recorder's counts: none in the file (another writer, or an older recorder)"
        if self.counts_log_time is None:
            when = "final counts"
        else:
            when = f"counts at its last flush (log time {self.counts_log_time / 1e9:.6f} s)"
        line = (
            f"the recorder's {when}: {self.counts.received} frames received, "
            f"{self.counts.dropped} dropped; "
        )
        if not_kept == 0:
            return line + "every one of them is in the file"
        return line + f"{not_kept} of them not in the file"


def recover(source: Path, out: Path) -> RecoveryReport:
    """Copy every complete record of ``source`` into a new MCAP file at ``out``."""
    check_mcap(source)
    if source.resolve() == out.resolve():
        raise RecordingError(f"{out}: write the recovered file elsewhere than the damaged one")
    size = source.stat().st_size
    schemas: dict[int, int] = {0: 0}
    channels: dict[int, int] = {}
    frame_channels: set[int] = set()
    counts_channels: set[int] = set()
    attachments = metadata = frames = other_messages = 0
    first_log_time: int | None = None
    last_log_time = 0
    counts: RecorderCounts | None = None
    counts_log_time: int | None = None
    kept = 0
    complete = False
    started = False
    with source.open("rb") as stream, out.open("wb") as target:
        writer = open_writer(target)
        reader = StreamReader(stream, record_size_limit=size)
        try:
            for record in reader.records:
                if isinstance(record, Schema):
                    schemas[record.id] = writer.register_schema(
                        record.name, record.encoding, record.data
                    )
                elif isinstance(record, Channel) and record.id not in channels:
                    if record.schema_id not in schemas:
                        continue  # its schema was in the part that is lost
                    if record.message_encoding == FRAME_ENCODING:
                        try:
                            FrameKind.from_metadata(dict(record.metadata))
                        except RecordingError:
                            continue  # a CAN channel whose metadata is corrupt: no frames
                    channels[record.id] = writer.register_channel(
                        record.topic,
                        record.message_encoding,
                        schemas[record.schema_id],
                        dict(record.metadata),
                    )
                    if record.message_encoding == FRAME_ENCODING:
                        frame_channels.add(record.id)
                    elif record.topic == COUNTS_TOPIC:
                        counts_channels.add(record.id)
                elif isinstance(record, Message) and record.channel_id in channels:
                    writer.add_message(
                        channels[record.channel_id],
                        record.log_time,
                        record.data,
                        record.publish_time,
                        record.sequence,
                    )
                    if record.channel_id in frame_channels:
                        frames += 1
                    else:
                        other_messages += 1
                    if record.channel_id in counts_channels:
                        with contextlib.suppress(RecordingError):  # copied all the same
                            counts = RecorderCounts.decode(record.data)
                            counts_log_time = record.log_time
                    if first_log_time is None:
                        first_log_time = record.log_time
                    first_log_time = min(first_log_time, record.log_time)
                    last_log_time = max(last_log_time, record.log_time)
                elif isinstance(record, Attachment):
                    writer.add_attachment(
                        record.create_time,
                        record.log_time,
                        record.name,
                        record.media_type,
                        record.data,
                    )
                    attachments += 1
                elif isinstance(record, Metadata):
                    writer.add_metadata(record.name, dict(record.metadata))
                    metadata += 1
                    final = _final_counts(record) if record.name == RECORDING_METADATA else None
                    if final is not None:
                        counts, counts_log_time = final, None
                elif isinstance(record, Footer):
                    complete = True
                elif isinstance(record, Header):
                    started = True
                kept = stream.tell()
        except DAMAGE_ERRORS:  # not OSError: a failing write is no damage of the source
            pass  # the cut: everything before it is in
        cut = None if complete or kept >= size else _describe_cut(stream, kept, size)
        finish(writer)
    if not started:
        out.unlink()
        raise RecordingError(f"{source}: no MCAP header after the magic: nothing to recover")
    return RecoveryReport(
        frames,
        other_messages,
        len(channels),
        attachments,
        metadata,
        cut,
        complete,
        None if first_log_time is None else (first_log_time, last_log_time),
        counts,
        counts_log_time,
    )


def _final_counts(record: Metadata) -> RecorderCounts | None:
    """The counts in the ``recording`` metadata of a finished recording, if it has them."""
    try:
        return RecorderCounts(
            int(record.metadata["frames_received"]), int(record.metadata["frames_dropped"])
        )
    except (KeyError, ValueError):
        return None


def _describe_cut(stream: IO[bytes], offset: int, size: int) -> Cut:
    """What the bytes from ``offset`` to the end are the start of, from the record's head."""
    stream.seek(offset)
    head = stream.read(_CHUNK_HEAD.size)
    try:
        opcode = Opcode(head[0])
    except ValueError:
        return Cut(size - offset, None, None, None)
    record_size = 9 + int(struct.unpack_from("<Q", head, 1)[0]) if len(head) >= 9 else None
    times = None
    if opcode == Opcode.CHUNK and len(head) == _CHUNK_HEAD.size:
        _, _, first, last = _CHUNK_HEAD.unpack(head)
        times = (int(first), int(last))
    return Cut(size - offset, opcode, record_size, times)
