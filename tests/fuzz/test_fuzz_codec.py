"""Fuzzing the CAN decoder and the E2E check (``protocol/codec.py``, ``protocol/e2e.py``).

Every frame starts as a valid encoding of a DBC message and is then broken: bits and bytes
flipped, set, inserted or cut, the length or the ID changed (to another of ours, any 11-bit
one, an extended one), marked remote, error or FD. Properties: decoding raises only
:class:`DecodeError`, and what it accepts is exactly a frame the encoder would write (so
never one whose CRC fails); :meth:`E2EMonitor.accept`, fed a stream of such frames, never
raises, never acts on a frame that is not a valid data frame of an ID the node listens to,
and never acts twice on one alive counter (a repeated frame) unless the sender went silent
long enough to have restarted.

The deterministic single and double bit flips of every message are in
``tests/protocol/test_codec.py``; this adds random combinations of everything at once.
"""

from __future__ import annotations

import math

import can
import pytest
from fuzzing import fuzz, mutated
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    initialize,
    invariant,
    precondition,
    rule,
    run_state_machine_as_test,
)

from protocol.codec import COUNTER_MODULO, WIRE, MessageCodec, crc8
from protocol.e2e import RESYNC_AFTER, E2EMonitor
from protocol.errors import DecodeError

pytestmark = pytest.mark.fuzz

CODECS = sorted(WIRE.messages.values(), key=lambda codec: codec.frame_id)
OUR_IDS = sorted(WIRE.defined_ids)


@st.composite
def records(draw: st.DrawFn, codec: MessageCodec) -> list[float]:
    """Valid values for every signal of ``codec``: raw integers over the DBC range."""
    values: list[float] = []
    for spec in codec.signals:
        low, high = spec.raw_range
        raw = draw(
            st.one_of(st.sampled_from([low, high, min(max(0, low), high)]), st.integers(low, high))
        )
        values.append(raw if spec.integer else raw * spec.scale + spec.offset)
    return values


@st.composite
def valid_frames(draw: st.DrawFn) -> tuple[MessageCodec, bytes]:
    """A valid frame of any E2E-protected message of the DBC."""
    codec = draw(st.sampled_from(CODECS), label="message")
    counter = draw(st.integers(0, COUNTER_MODULO - 1), label="counter")
    return codec, codec.encode(draw(records(codec)), counter)


frame_ids = st.one_of(
    st.sampled_from(OUR_IDS),
    st.integers(0, 0x7FF),
    st.integers(0x800, 0x1FFFFFFF),  # only an extended frame carries these
)


@st.composite
def broken_frames(draw: st.DrawFn) -> tuple[int, bytes]:
    """``(frame ID, data)``: a valid frame of any message, then broken (or left alone)."""
    codec, data = draw(valid_frames())
    frame_id = codec.frame_id
    if draw(st.booleans(), label="other ID"):
        frame_id = draw(frame_ids)
    if draw(st.integers(0, 3), label="edit data") > 0:
        data = draw(mutated(data))
    if draw(st.integers(0, 4), label="fix CRC") == 0 and data:
        data = bytes([crc8(frame_id, data[1:])]) + data[1:]  # a valid CRC over broken contents
    return frame_id, data


@fuzz(600)
@given(broken_frames())
def test_decoding_a_broken_frame_raises_only_decode_error(frame: tuple[int, bytes]) -> None:
    """Only DecodeError, naming the frame; what is accepted is what the encoder writes."""
    frame_id, data = frame
    try:
        codec, counter, record = WIRE.decode(frame_id, data)
    except DecodeError as error:
        assert error.frame_id == frame_id
        assert error.reason and f"0x{frame_id:03X}" in str(error)
        return
    assert codec.frame_id == frame_id
    assert data[0] == crc8(frame_id, data[1:])
    assert codec.encode(record, counter) == data, "a frame accepted that is not canonical"


@fuzz(150)
@given(st.sampled_from(CODECS), st.binary(max_size=72))
def test_each_message_decoder_takes_any_bytes(codec: MessageCodec, data: bytes) -> None:
    try:
        counter, record = codec.decode(data)
    except DecodeError as error:
        assert error.frame_id == codec.frame_id and codec.name in error.reason
        return
    assert codec.encode(record, counter) == data


@fuzz(150)
@given(valid_frames(), st.data())
def test_a_corrupted_crc_byte_is_always_refused(
    frame: tuple[MessageCodec, bytes], data: st.DataObject
) -> None:
    """Whatever else is in the frame, a wrong CRC is never decoded."""
    codec, good = frame
    body = data.draw(mutated(good[1:]), label="body") if len(good) > 1 else b""
    body = (body + bytes(codec.length))[: codec.length - 1]  # keep the length: CRC is the test
    crc = crc8(codec.frame_id, body)
    wrong = data.draw(st.integers(0, 255).filter(lambda byte: byte != crc), label="crc")
    with pytest.raises(DecodeError):
        WIRE.decode(codec.frame_id, bytes([wrong]) + body)


# --- the E2E monitor, fed a stream -----------------------------------------------------------


class E2EStream(RuleBasedStateMachine):
    """One receiver's E2EMonitor fed good, repeated, reordered and broken frames."""

    def __init__(self) -> None:
        super().__init__()
        self.monitor = E2EMonitor()
        self.now = 1000.0
        self.wanted: set[int] = set()
        self.counters: dict[int, int] = {}
        self.sent: list[can.Message] = []
        self.last_acted: dict[int, tuple[int, float]] = {}
        """Per frame ID: the alive counter and time of the last frame acted on."""
        self.heard: dict[int, float] = {}
        """Per frame ID: when the monitor last saw one of its frames decode."""
        self.offered = 0
        self.acted = 0

    @initialize(wanted=st.sets(st.sampled_from([c.frame_id for c in CODECS]), min_size=1))
    def listen(self, wanted: set[int]) -> None:
        self.wanted = wanted

    def offer(self, message: can.Message) -> None:
        before = self.counted()
        accepted = self.monitor.accept(message, self.wanted)  # never raises
        self.offered += 1
        frame_id = message.arbitration_id
        if accepted is None:
            return
        self.acted += 1
        codec, counter, record = accepted
        assert not (message.is_error_frame or message.is_remote_frame or message.is_extended_id)
        assert frame_id in self.wanted and codec.frame_id == frame_id
        data = bytes(message.data)
        assert data[0] == crc8(frame_id, data[1:]), "acted on a frame whose CRC fails"
        assert codec.encode(record, counter) == data
        assert self.counted() == before + 1  # counted once, as ok (and maybe lost before it)
        last = self.last_acted.get(frame_id)
        silent = (
            frame_id not in self.heard or message.timestamp - self.heard[frame_id] > RESYNC_AFTER
        )
        if last is not None and not silent:
            assert counter != last[0], f"acted twice on counter {counter} of 0x{frame_id:03X}"
        self.last_acted[frame_id] = (counter, message.timestamp)

    def counted(self) -> int:
        counts = self.monitor.counts
        return counts.ok + counts.repeated + counts.stale + counts.corrupt + counts.unknown

    def track_heard(self, message: can.Message) -> None:
        """What the monitor's silence rule sees: frames of a wanted ID that decode."""
        try:
            WIRE.decode(message.arbitration_id, message.data)
        except DecodeError:
            return
        if (
            message.arbitration_id in self.wanted
            and not message.is_extended_id
            and not (message.is_error_frame or message.is_remote_frame)
        ):
            self.heard[message.arbitration_id] = message.timestamp

    def send(self, message: can.Message) -> None:
        self.offer(message)
        self.track_heard(message)
        self.sent.append(message)

    @rule(frame=valid_frames(), step=st.sampled_from([1, 1, 1, 0, 2, 5, 9, 15]))
    def good_frame(self, frame: tuple[MessageCodec, bytes], step: int) -> None:
        """A sender's next frame (or a repeat, or some lost before it)."""
        codec, data = frame
        counter = (self.counters.get(codec.frame_id, -1) + step) % COUNTER_MODULO
        self.counters[codec.frame_id] = counter
        _, record = codec.decode(data)
        self.send(self.message(codec.frame_id, codec.encode(record, counter)))

    @rule(
        frame=broken_frames(), flags=st.sets(st.sampled_from(["extended", "remote", "error", "fd"]))
    )
    def broken_frame(self, frame: tuple[int, bytes], flags: set[str]) -> None:
        frame_id, data = frame
        self.send(self.message(frame_id, data, frozenset(flags)))

    @rule(data=st.data())
    def wrong_crc(self, data: st.DataObject) -> None:
        """A frame of an ID the node listens to, its next counter, valid but for its CRC."""
        frame_id = data.draw(st.sampled_from(sorted(self.wanted)), label="wanted ID")
        codec = WIRE.by_id[frame_id]
        counter = (self.counters.get(frame_id, -1) + 1) % COUNTER_MODULO
        good = codec.encode(data.draw(records(codec), label="record"), counter)
        crc = data.draw(st.integers(0, 255).filter(lambda byte: byte != good[0]), label="crc")
        self.send(self.message(frame_id, bytes([crc]) + good[1:]))

    @precondition(lambda self: bool(self.sent))
    @rule(data=st.data())
    def replayed_frame(self, data: st.DataObject) -> None:
        """An old frame again: a duplicate, or one arriving late."""
        old = data.draw(st.sampled_from(self.sent), label="old frame")
        self.send(self.message(old.arbitration_id, bytes(old.data)))

    @rule(seconds=st.sampled_from([0.0, 0.002, 0.1, RESYNC_AFTER, RESYNC_AFTER * 1.01, 5.0]))
    def time_passes(self, seconds: float) -> None:
        self.now += seconds

    @rule(
        timestamp=st.sampled_from([math.nan, math.inf, -math.inf, -1.0, 0.0]),
        frame=valid_frames(),
    )
    def odd_timestamp(self, timestamp: float, frame: tuple[MessageCodec, bytes]) -> None:
        """A bus that stamps nonsense: no exception either."""
        codec, data = frame
        message = self.message(codec.frame_id, data)
        message.timestamp = timestamp
        self.send(message)

    @rule()
    def forget(self) -> None:
        """A peer restarted: the node starts over."""
        self.monitor.forget()
        self.last_acted.clear()
        self.heard.clear()

    def message(
        self, frame_id: int, data: bytes, flags: frozenset[str] = frozenset()
    ) -> can.Message:
        self.now += 0.001
        return can.Message(
            timestamp=self.now,
            arbitration_id=frame_id,
            data=data,
            dlc=len(data),
            is_extended_id="extended" in flags,
            is_remote_frame="remote" in flags,
            is_error_frame="error" in flags,
            is_fd="fd" in flags,
            check=False,
        )

    @invariant()
    def counts_never_go_backwards(self) -> None:
        counts = self.monitor.counts
        assert min(counts.ok, counts.lost, counts.repeated, counts.stale, counts.corrupt) >= 0
        assert self.counted() <= self.offered  # at most one count a frame


def test_the_e2e_monitor_never_acts_on_a_bad_or_repeated_frame() -> None:
    run_state_machine_as_test(E2EStream, settings=fuzz(80, stateful_step_count=30))
