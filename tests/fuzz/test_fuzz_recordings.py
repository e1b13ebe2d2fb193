"""Fuzzing what reads a recording (``recorder/recover.py``, ``recorder/replay.py``,
``recorder/mcap_can.py``): MCAP files cut short and corrupted.

Three small recordings as ``scara-record`` writes them (frames of the DBC's messages and
foreign, extended, remote and error frames, a decoded-state channel, an attachment and
metadata; zstd chunks, many small zstd chunks, and uncompressed chunks) are cut at any byte,
or have bits flipped, bytes set, inserted or deleted, or a range zeroed. A corruption is a
*recipe* (which recording, which edits), so that an input the fuzzing found can be pinned
with ``@example`` in a few characters.

Properties: :func:`recover` takes any file cut short and writes a recording that reads back
as a prefix of the original frames; on any file, recover and the readers (``read_frames``,
``read_state``, ``read_attachments``) raise only :class:`RecordingError`; and the real
commands exit with status 0 or 2, with a message and no traceback.
"""

from __future__ import annotations

import io
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import pytest
from fuzzing import fuzz
from hypothesis import example, given
from hypothesis import strategies as st
from mcap.writer import CompressionType, Writer
from support import ROOT, SLOWDOWN

from protocol.messages import COMMAND, STATE, command_record
from recorder.mcap_can import FrameChannels, RecordingError, finish, open_writer, read_attachments
from recorder.recover import recover
from recorder.replay import read_frames, read_state

pytestmark = pytest.mark.fuzz


def frames() -> list[can.Message]:
    """What a short run puts on a bus: joint states and commands, and others' frames."""
    messages = []
    t = 1_700_000_000.0
    for tick in range(120):
        t += 0.002
        for codec in STATE:
            record = codec.Record(CommandEcho=tick % 16, Position=0.001 * tick, Velocity=0.1)
            messages.append(_frame(t, codec.frame_id, codec.encode(record, tick % 16)))
        command = command_record((0.1, -0.1, 0.01))
        messages.append(_frame(t + 1e-4, COMMAND.frame_id, COMMAND.encode(command, tick % 16)))
        if tick % 30 == 0:
            messages.append(_frame(t, 0x7FF, b"\x01\x02"))
            messages.append(_frame(t, 0x1ABCDEF0, bytes(8), extended=True))
            messages.append(
                can.Message(timestamp=t, arbitration_id=0x123, is_remote_frame=True, dlc=4)
            )
            messages.append(
                can.Message(timestamp=t, is_error_frame=True, arbitration_id=0x4, data=bytes(8))
            )
    return messages


def _frame(t: float, arbitration_id: int, data: bytes, extended: bool = False) -> can.Message:
    return can.Message(
        timestamp=t, arbitration_id=arbitration_id, data=data, is_extended_id=extended
    )


FRAMES = frames()


def recording(make_writer: Callable[[io.BytesIO], Writer]) -> bytes:
    stream = io.BytesIO()
    writer = make_writer(stream)
    channels = FrameChannels(writer)
    state = writer.register_channel("scara/joints", "json", 0, {})
    writer.add_attachment(1, 1, "scenario.json", "application/json", b'{"name": "fuzz"}')
    for index, message in enumerate(FRAMES):
        channels.write(message)
        if index % 20 == 0:
            stamp = round(message.timestamp * 1e9)
            writer.add_message(state, stamp, b'{"position": [0, 0, 0]}', stamp, index)
    writer.add_metadata("recording", {"software": "fuzz"})
    finish(writer)
    return stream.getvalue()


def _small_chunks(compression: CompressionType, size: int) -> Callable[[io.BytesIO], Writer]:
    def make(stream: io.BytesIO) -> Writer:
        writer = Writer(stream, chunk_size=size, compression=compression)
        writer.start(profile="scara", library="fuzz")
        return writer

    return make


RECORDINGS = [
    recording(open_writer),  # as scara-record writes it: one zstd chunk here
    recording(_small_chunks(CompressionType.ZSTD, 1024)),
    recording(_small_chunks(CompressionType.NONE, 2048)),
]

Recipe = tuple[int, tuple[tuple[str, int, int], ...]]
"""Which recording, and the edits: ``(kind, offset, value)``, the offset taken modulo the
length at the time of the edit."""


def corrupt(recipe: Recipe) -> bytes:
    which, edits = recipe
    data = bytearray(RECORDINGS[which])
    for kind, offset, value in edits:
        at = offset % (len(data) + 1)
        if kind == "cut":
            del data[at:]
        elif not data:
            continue
        elif kind == "flip":
            data[at % len(data)] ^= 1 << (value % 8)
        elif kind == "set":
            data[at % len(data)] = value % 256
        elif kind == "insert":
            data[at:at] = bytes([value % 256]) * (value % 7 + 1)
        elif kind == "delete":
            del data[at : at + value % 16 + 1]
        elif kind == "zero":
            data[at : at + value % 64 + 1] = bytes(len(data[at : at + value % 64 + 1]))
    return bytes(data)


offsets = st.integers(0, max(len(r) for r in RECORDINGS))
cuts: st.SearchStrategy[Recipe] = st.tuples(
    st.integers(0, len(RECORDINGS) - 1),
    st.tuples(st.tuples(st.just("cut"), offsets, st.just(0))),
)
recipes: st.SearchStrategy[Recipe] = st.tuples(
    st.integers(0, len(RECORDINGS) - 1),
    st.lists(
        st.tuples(
            st.sampled_from(["cut", "flip", "set", "insert", "delete", "zero"]),
            offsets,
            st.integers(0, 255),
        ),
        min_size=1,
        max_size=3,
    ).map(tuple),
)


def key(message: can.Message) -> tuple[Any, ...]:
    return (
        message.arbitration_id,
        bytes(message.data),
        message.is_extended_id,
        message.is_remote_frame,
        message.is_error_frame,
    )


ORIGINAL = [key(message) for message in FRAMES]


def same_times(back: list[can.Message]) -> bool:
    """The first frames' times within 1 us (nanoseconds in the file, a float read back)."""
    return all(abs(a.timestamp - b.timestamp) < 1e-6 for a, b in zip(back, FRAMES, strict=False))


def in_a_file(data: bytes, check: Callable[[Path], None]) -> None:
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "fuzzed.mcap"
        path.write_bytes(data)
        check(path)


@fuzz(100)
@given(cuts)
@example((0, (("cut", len(RECORDINGS[0]), 0),)))  # not cut at all
def test_a_recording_cut_anywhere_is_recovered_as_a_prefix_of_its_frames(recipe: Recipe) -> None:
    data = corrupt(recipe)

    def check(path: Path) -> None:
        out = path.with_name("recovered.mcap")
        try:
            report = recover(path, out)
        except RecordingError as error:
            assert "header" in str(error) or "magic" in str(error) or "empty" in str(error)
            assert not out.exists()
            return
        messages = list(read_frames(out))
        back = [key(message) for message in messages]
        assert back == ORIGINAL[: len(back)], "recovered frames that were not recorded"
        assert same_times(messages)
        cut = 0 if report.cut is None else report.cut.size
        assert 0 <= cut <= len(data)
        assert report.frames == len(back)
        if data == RECORDINGS[recipe[0]]:
            assert report.was_complete and report.cut is None and back == ORIGINAL

    in_a_file(data, check)


def only_recording_errors(read: Callable[[Path], Any]) -> Callable[[Path], None]:
    def check(path: Path) -> None:
        try:
            read(path)
        except RecordingError as error:
            assert str(error)

    return check


# Pinned: each raised something else than RecordingError (recording 2 is uncompressed, so
# its offsets depend only on the mcap writer; recording 0's on zstd too).
STRUCT_ERROR = (2, (("cut", 35642, 0),))  # cut in the summary section
ZSTD_ERROR = (0, (("flip", 231, 0),))  # a corrupt zstd chunk
OVERFLOW_ERROR = (2, (("flip", 172, 7),))  # a record length past what an index holds
MEMORY_ERROR = (2, (("flip", 161, 0),))  # a record length past the memory
KEY_ERROR = (2, (("flip", 439, 7),))  # read_state: a message of a channel not in the summary
HALF_WRITTEN = (2, (("flip", 103, 7),))  # recover stops midway, its output left unfinished
BAD_CHANNEL = (2, (("flip", 267, 0),))  # a CAN channel's metadata corrupt: copied as it is


@fuzz(100)
@given(recipes)
@example(STRUCT_ERROR)
@example(ZSTD_ERROR)
@example(OVERFLOW_ERROR)
@example(MEMORY_ERROR)
@example(KEY_ERROR)
def test_the_readers_refuse_a_broken_recording_only_with_a_recording_error(recipe: Recipe) -> None:
    data = corrupt(recipe)
    for read in (
        lambda path: list(read_frames(path)),
        lambda path: list(read_state(path)),
        read_attachments,
    ):
        in_a_file(data, only_recording_errors(read))


def _recover_and_read_back(path: Path) -> None:
    out = path.with_name("recovered.mcap")
    try:
        recover(path, out)
    except RecordingError as error:
        assert str(error)
        return
    list(read_frames(out))  # what recover writes is a readable recording


@fuzz(100)
@given(recipes)
@example(ZSTD_ERROR)
@example(HALF_WRITTEN)
@example(BAD_CHANNEL)
def test_a_corrupted_recording_is_recovered_or_refused(recipe: Recipe) -> None:
    in_a_file(corrupt(recipe), _recover_and_read_back)


# --- the real commands, a few runs -------------------------------------------------------------


def run(*command: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", *command],
        cwd=ROOT, capture_output=True, text=True, timeout=60 * SLOWDOWN,
    )  # fmt: skip


def exits_cleanly(done: subprocess.CompletedProcess[str], status: int, says: str) -> None:
    """Exit ``status``, saying ``says``, without a traceback."""
    assert "Traceback" not in done.stderr, done.stderr
    assert done.returncode == status, (done.stdout, done.stderr)
    assert says in done.stdout + done.stderr, (done.stdout, done.stderr)


def test_the_commands_recover_and_replay_a_recording_cut_short(tmp_path: Path) -> None:
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(RECORDINGS[2][: len(RECORDINGS[2]) * 2 // 3])
    done = run("recorder.replay", str(cut), "--interface", "virtual", "--as-fast-as-possible")
    exits_cleanly(done, 2, "'scara-record recover FILE' rewrites it")
    fixed = tmp_path / "fixed.mcap"
    done = run("recorder.node", "recover", str(cut), "--out", str(fixed))
    exits_cleanly(done, 0, "was cut short")
    done = run("recorder.replay", str(fixed), "--interface", "virtual", "--as-fast-as-possible")
    exits_cleanly(done, 0, "frames sent")


def test_scara_replay_refuses_a_recording_cut_in_its_summary_without_a_traceback(
    tmp_path: Path,
) -> None:
    path = tmp_path / "cut.mcap"
    path.write_bytes(corrupt(STRUCT_ERROR))
    done = run("recorder.replay", str(path), "--interface", "virtual", "--as-fast-as-possible")
    exits_cleanly(done, 2, "scara-replay: ")


def test_scara_record_recover_refuses_a_corrupt_chunk_without_a_traceback(tmp_path: Path) -> None:
    path = tmp_path / "corrupt.mcap"
    path.write_bytes(corrupt(ZSTD_ERROR))
    done = run("recorder.node", "recover", str(path), "--out", str(tmp_path / "out.mcap"))
    if done.returncode == 0:  # what came before the damage, recovered
        exits_cleanly(done, 0, "metadata records, into")
    else:
        exits_cleanly(done, 2, "scara-record recover: ")


def test_scara_record_recover_names_an_out_file_it_cannot_write(tmp_path: Path) -> None:
    path = tmp_path / "cut.mcap"
    path.write_bytes(RECORDINGS[2][:20_000])
    out = tmp_path / "no such folder" / "out.mcap"
    done = run("recorder.node", "recover", str(path), "--out", str(out))
    exits_cleanly(done, 2, "scara-record recover: ")
