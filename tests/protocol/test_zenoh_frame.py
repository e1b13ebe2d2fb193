"""The CAN-over-Zenoh frame format (``protocol.zenoh_can.frame``): every valid frame, and any
run of them sent together, survives encode and decode; what a receiver would drop is refused
when sending, and a sample with any malformed part is refused whole."""

from __future__ import annotations

import math

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import same_frame

from protocol.zenoh_can.frame import (
    FLAG_FD,
    HEADER,
    MalformedFrameError,
    decode_frames,
    encode_frame,
)

_ids = st.one_of(
    st.tuples(st.just(False), st.integers(0, 0x7FF)),
    st.tuples(st.just(True), st.integers(0, 0x1FFFFFFF)),
)


@st.composite
def valid_frames(draw: st.DrawFn) -> can.Message:
    extended, arbitration_id = draw(_ids)
    fd = draw(st.booleans())
    remote = (not fd) and draw(st.booleans())
    data = b"" if remote else draw(st.binary(max_size=64 if fd else 8))
    return can.Message(
        timestamp=draw(st.floats(allow_nan=False, allow_infinity=False, width=64)),
        arbitration_id=arbitration_id,
        is_extended_id=extended,
        is_remote_frame=remote,
        is_error_frame=draw(st.booleans()),
        is_fd=fd,
        bitrate_switch=fd and draw(st.booleans()),
        error_state_indicator=fd and draw(st.booleans()),
        dlc=draw(st.integers(0, 8)) if remote else len(data),
        data=data,
        check=False,
    )


@given(valid_frames())
@settings(max_examples=300, deadline=None)
def test_every_valid_frame_survives_encode_and_decode(msg: can.Message) -> None:
    payload = encode_frame(msg)
    assert len(payload) == HEADER.size + len(msg.data)
    (back,) = decode_frames(payload, "x")
    assert same_frame(back, msg)
    assert back.channel == "x" and back.is_rx


@given(st.lists(valid_frames(), min_size=1, max_size=5))
@settings(max_examples=200, deadline=None)
def test_frames_sent_together_come_back_in_order(messages: list[can.Message]) -> None:
    back = decode_frames(b"".join(encode_frame(msg) for msg in messages))
    assert len(back) == len(messages)
    assert all(same_frame(x, y) for x, y in zip(back, messages, strict=True))


@pytest.mark.parametrize(
    ("msg", "problem"),
    [
        (can.Message(arbitration_id=0x800, is_extended_id=False), "exceeds"),
        (can.Message(arbitration_id=0x20000000, is_extended_id=True), "exceeds"),
        (can.Message(arbitration_id=1, data=bytes(9), check=False), "data bytes"),
        (can.Message(arbitration_id=1, data=bytes(65), is_fd=True, check=False), "data bytes"),
        (can.Message(timestamp=math.nan, arbitration_id=1), "not finite"),
        (can.Message(arbitration_id=1, dlc=9, is_remote_frame=True, check=False), "dlc"),
    ],
)
def test_encoding_refuses_what_a_receiver_would_drop(msg: can.Message, problem: str) -> None:
    with pytest.raises(MalformedFrameError, match=problem):
        encode_frame(msg)


@pytest.mark.parametrize(
    "payload",
    [
        b"",
        b"\x00" * (HEADER.size - 1),
        HEADER.pack(1.0, 0x10, 0x40, 0, 0),  # reserved flag bit
        HEADER.pack(1.0, 0x10, 0x00, 9, 9) + bytes(9),  # 9 bytes in a classic frame
        HEADER.pack(1.0, 0x10, 0x00, 9, 0),  # classic dlc 9
        HEADER.pack(1.0, 0x10, FLAG_FD, 65, 0),  # FD dlc 65
        HEADER.pack(1.0, 0x800, 0x00, 0, 0),  # 12-bit id without the extended flag
        HEADER.pack(math.inf, 0x10, 0x00, 0, 0),
        HEADER.pack(1.0, 0x10, 0x00, 4, 4) + bytes(3),  # cut short
        HEADER.pack(1.0, 0x10, 0x00, 0, 0) + b"\x00",  # a good frame, then a stray byte
        HEADER.pack(1.0, 0x10, 0x00, 0, 0) + HEADER.pack(1.0, 0x10, 0x40, 0, 0),  # good, bad
    ],
)
def test_decoding_rejects_malformed_payloads(payload: bytes) -> None:
    with pytest.raises(MalformedFrameError):
        decode_frames(payload)
