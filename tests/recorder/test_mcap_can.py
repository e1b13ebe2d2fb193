"""MCAP as a python-can log format (``recorder/mcap_can.py``), and the recovery of a file
cut short (``recorder/recover.py``), on files read back with the ``mcap`` library."""

from __future__ import annotations

import io
import random
from pathlib import Path

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.opcode import Opcode
from mcap.reader import make_reader

from recorder.mcap_can import (
    CHUNK_SIZE,
    FrameChannels,
    RecorderCounts,
    RecordingError,
    check_mcap,
    counts_channel,
    end_chunk,
    finish,
    frames,
    open_writer,
)
from recorder.recover import recover
from recorder.replay import frame_filter, read_frames, selected


def frame(
    t: float, arbitration_id: int, data: bytes, *, extended: bool = False, remote: bool = False
) -> can.Message:
    return can.Message(
        timestamp=t,
        arbitration_id=arbitration_id,
        data=b"" if remote else data,
        dlc=len(data),
        is_extended_id=extended,
        is_remote_frame=remote,
        channel="vcan0",
    )


def key(message: can.Message) -> tuple[object, ...]:
    """All of a frame but its time (see :func:`same_times`)."""
    return (
        message.arbitration_id,
        bytes(message.data),
        message.is_extended_id,
        message.is_remote_frame,
        message.is_error_frame,
        message.channel,
    )


def same_times(a: list[can.Message], b: list[can.Message]) -> bool:
    """Equal within 1 us: a float of epoch seconds holds a quarter of a microsecond."""
    return len(a) == len(b) and all(
        abs(x.timestamp - y.timestamp) < 1e-6 for x, y in zip(a, b, strict=True)
    )


def write(path: Path, messages: list[can.Message]) -> None:
    with can.Logger(path) as writer:  # through python-can's entry point for .mcap
        for message in messages:
            writer.on_message_received(message)


FRAMES = [
    frame(100.0, 0x110, bytes(range(7))),
    frame(100.0005, 0x100, bytes(8)),
    frame(100.001, 0x123, b"\x01\x02"),
    frame(100.0015, 0x1ABCDEF, b"\xff" * 8, extended=True),
    frame(100.002, 0x7FF, bytes(2), remote=True),
]


def test_frames_keep_time_id_data_and_flags_and_channels_are_named_after_the_dbc(
    tmp_path: Path,
) -> None:
    path = tmp_path / "x.mcap"
    write(path, FRAMES)
    with can.LogReader(path) as reader:
        back = list(reader)
    assert [key(m) for m in back] == [key(m) for m in FRAMES] and same_times(back, FRAMES)
    with path.open("rb") as stream:
        mcap = make_reader(stream)
        summary = mcap.get_summary()
        assert summary is not None
        topics = {channel.topic for channel in summary.channels.values()}
        encodings = {channel.message_encoding for channel in summary.channels.values()}
        times = [message.log_time for _, _, message in mcap.iter_messages()]
        assert summary.chunk_indexes, "no chunk index"
    assert topics == {"can/JointState1", "can/JointVelocityCommand", "can/other"}
    assert encodings == {"can-frame"}
    assert times == [round(m.timestamp * 1e9) for m in FRAMES]


def test_a_flood_of_random_ids_goes_to_one_channel_and_reads_back_whole(tmp_path: Path) -> None:
    """A channel per foreign ID let a flood of random extended IDs (scara-soak's) grow the
    recorder's channels, and its memory, by thousands: they share ``can/other`` now."""
    draw = random.Random(7)
    flood = [
        frame(200.0 + i * 1e-4, draw.randrange(2**29), draw.randbytes(i % 9), extended=True)
        for i in range(3000)
    ]
    flood.append(
        can.Message(timestamp=201.0, arbitration_id=0x4, is_error_frame=True, channel="vcan0")
    )
    path = tmp_path / "flood.mcap"
    write(path, [*FRAMES, *flood])
    with can.LogReader(path) as reader:
        back = list(reader)
    assert [key(m) for m in back] == [key(m) for m in [*FRAMES, *flood]]
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and len(summary.channels) == 3


@settings(max_examples=50, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 0x7FF), st.binary(min_size=0, max_size=8), st.floats(0, 1e-3)),
        min_size=1,
        max_size=40,
    )
)
def test_any_standard_frames_round_trip_in_order(raw: list[tuple[int, bytes, float]]) -> None:
    stream = io.BytesIO()
    writer = open_writer(stream)
    channels = FrameChannels(writer)
    messages, t = [], 1_700_000_000.0
    for arbitration_id, data, step in raw:
        t += step
        messages.append(frame(t, arbitration_id, data))
        channels.write(messages[-1])
    finish(writer)
    stream.seek(0)
    back = list(frames(stream))
    assert [key(m) for m in back] == [key(m) for m in messages] and same_times(back, messages)


@pytest.mark.parametrize("suffix", [".blf", ".asc", ".csv", ".log"])
def test_conversion_to_and_from_python_cans_formats(tmp_path: Path, suffix: str) -> None:
    standard = [m for m in FRAMES if not m.is_remote_frame]
    source = tmp_path / "a.mcap"
    write(source, standard)
    other, back = tmp_path / f"b{suffix}", tmp_path / "c.mcap"
    with can.LogReader(source) as reader, can.Logger(other) as writer:
        for message in reader:
            writer.on_message_received(message)
    with can.LogReader(other) as reader, can.Logger(back) as writer:
        for message in reader:
            writer.on_message_received(message)
    with can.LogReader(back) as reader:
        again = list(reader)
    assert [(m.arbitration_id, bytes(m.data), m.is_extended_id) for m in again] == [
        (m.arbitration_id, bytes(m.data), m.is_extended_id) for m in standard
    ]
    # the spacing survives (.asc and .blf count time from the start of the log)
    spacing = [round(m.timestamp - again[0].timestamp, 6) for m in again]
    assert spacing == [round(m.timestamp - standard[0].timestamp, 6) for m in standard]


def test_a_file_cut_short_is_recovered_up_to_its_last_complete_chunk(tmp_path: Path) -> None:
    count = 60_000  # several chunks of CHUNK_SIZE
    messages = [
        frame(100 + i * 1e-4, 0x110, i.to_bytes(4, "little") + bytes(3)) for i in range(count)
    ]
    whole = tmp_path / "whole.mcap"
    write(whole, messages)
    data = whole.read_bytes()
    assert len(data) > 3 * CHUNK_SIZE / 10  # compressed, yet more than one chunk
    with whole.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 2
    chunk = summary.chunk_indexes[-2]
    cut = tmp_path / "cut.mcap"  # the writer killed in the middle of a chunk: no summary
    cut.write_bytes(data[: chunk.chunk_start_offset + chunk.chunk_length // 2])
    with pytest.raises(RecordingError, match="scara-record recover"):
        list(read_frames(cut))

    report = recover(cut, tmp_path / "fixed.mcap")
    back = list(read_frames(tmp_path / "fixed.mcap"))
    assert not report.was_complete and report.cut is not None
    assert 0 < len(back) == report.frames < count and report.other_messages == 0
    assert [key(m) for m in back] == [key(m) for m in messages[: len(back)]]  # a prefix
    assert same_times(back, messages[: len(back)])
    # the cut chunk's head says which messages it held: those right after the kept ones
    assert report.cut.opcode == Opcode.CHUNK and report.cut.chunk_log_times is not None
    assert report.cut.chunk_log_times == (chunk.message_start_time, chunk.message_end_time)
    assert chunk.message_start_time == round(messages[len(back)].timestamp * 1e9)
    summary = report.summary(tmp_path / "fixed.mcap")
    assert f"kept {report.frames} CAN frames" in summary and "cannot be counted" in summary
    assert f"cut off: the last {report.cut.size} bytes, the start of a chunk record" in summary
    assert "counts: none in the file" in summary  # python-can's logger writes none

    complete = recover(whole, tmp_path / "again.mcap")
    assert complete.was_complete and complete.cut is None and complete.frames == count
    assert "nothing was cut" in complete.summary(tmp_path / "again.mcap")


def test_recovery_counts_what_the_recorder_received_and_the_file_lacks(tmp_path: Path) -> None:
    """The recorder's counts at its last flush say 10 frames received, 3 dropped; the file
    holds 5 frames: 5 of those received are not in it (3 dropped, 2 queued and lost)."""
    path = tmp_path / "counted.mcap"
    with path.open("wb") as stream:
        writer = open_writer(stream)
        channels, counts = FrameChannels(writer), counts_channel(writer)
        for message in FRAMES:
            channels.write(message)
        end_chunk(writer, counts, RecorderCounts(received=10, dropped=3), 7)  # then killed
    report = recover(path, tmp_path / "fixed.mcap")
    assert report.cut is None and report.frames_not_kept == 5
    assert report.counts == RecorderCounts(10, 3) and report.counts_log_time == 7
    summary = report.summary(tmp_path / "fixed.mcap")
    assert "10 frames received, 3 dropped; 5 of them not in the file" in summary, summary
    assert "cut off: nothing" in summary and "cannot be counted" in summary


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "empty"),
        (b"timestamp,arbitration_id\n", "not an MCAP file"),
        (b"\x89MCAP0\r\n\x01\x02", "not a readable MCAP recording"),
    ],
)
def test_bad_files_are_named_errors(tmp_path: Path, content: bytes, message: str) -> None:
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=message):
        check_mcap(path)
        list(read_frames(path))


def test_selection_by_time_and_frame() -> None:
    picked = list(selected(FRAMES, frame_filter(["JointState1", "0x123"]), 0.0005, 0.0012))
    assert [m.arbitration_id for m in picked] == [0x123]
    assert frame_filter([]) is None
    with pytest.raises(RecordingError, match="--only 'Nope'"):
        frame_filter(["Nope"])
