"""Rewrite an MCAP file whose writer died (``kill -9``, power loss) as a valid, indexed one.

A recording is written in chunks; a writer killed mid-run leaves the header, the complete
chunks and part of the last one, with no summary or index. :func:`recover` reads the records
in order until the data stops making sense, copies schemas, channels, messages, attachments
and metadata into a new file (chunked, compressed, indexed), and reports what was lost: the
bytes after the last complete record.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

from mcap.exceptions import McapError
from mcap.records import Attachment, Channel, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from recorder.mcap_can import RecordingError, check_mcap, finish, open_writer


@dataclass(frozen=True, slots=True)
class RecoveryReport:
    messages: int
    channels: int
    attachments: int
    metadata: int
    kept_bytes: int
    """Bytes of the damaged file up to the end of its last complete record."""
    size: int
    was_complete: bool
    """The file had its footer: nothing was missing."""
    last_log_time: int

    @property
    def lost_bytes(self) -> int:
        return self.size - self.kept_bytes

    def summary(self, out: Path) -> str:
        state = "was complete" if self.was_complete else "was cut short"
        return (
            f"the recording {state}: {self.messages} messages on {self.channels} channels, "
            f"{self.attachments} attachments and {self.metadata} metadata records recovered "
            f"into {out}; {self.lost_bytes} of {self.size} bytes lost (the last, incomplete "
            f"chunk), data up to log time {self.last_log_time / 1e9:.6f} s"
        )


def recover(source: Path, out: Path) -> RecoveryReport:
    """Copy every complete record of ``source`` into a new MCAP file at ``out``."""
    check_mcap(source)
    if source.resolve() == out.resolve():
        raise RecordingError(f"{out}: write the recovered file elsewhere than the damaged one")
    size = source.stat().st_size
    schemas: dict[int, int] = {0: 0}
    channels: dict[int, int] = {}
    counts = {"messages": 0, "attachments": 0, "metadata": 0}
    kept = 0
    complete = False
    started = False
    last_log_time = 0
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
                    channels[record.id] = writer.register_channel(
                        record.topic,
                        record.message_encoding,
                        schemas[record.schema_id],
                        dict(record.metadata),
                    )
                elif isinstance(record, Message) and record.channel_id in channels:
                    writer.add_message(
                        channels[record.channel_id],
                        record.log_time,
                        record.data,
                        record.publish_time,
                        record.sequence,
                    )
                    counts["messages"] += 1
                    last_log_time = max(last_log_time, record.log_time)
                elif isinstance(record, Attachment):
                    writer.add_attachment(
                        record.create_time,
                        record.log_time,
                        record.name,
                        record.media_type,
                        record.data,
                    )
                    counts["attachments"] += 1
                elif isinstance(record, Metadata):
                    writer.add_metadata(record.name, dict(record.metadata))
                    counts["metadata"] += 1
                elif isinstance(record, Footer):
                    complete = True
                elif isinstance(record, Header):
                    started = True
                kept = stream.tell()
        except (McapError, EOFError, struct.error, ValueError, MemoryError):
            pass  # the cut: everything before it is in
        if complete:
            kept = size
        finish(writer)
    if not started:
        out.unlink()
        raise RecordingError(f"{source}: no MCAP header after the magic: nothing to recover")
    return RecoveryReport(
        counts["messages"],
        len(channels),
        counts["attachments"],
        counts["metadata"],
        kept,
        size,
        complete,
        last_log_time,
    )
