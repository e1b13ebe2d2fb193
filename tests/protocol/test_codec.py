"""The struct codec against cantools' reading of the same DBC, the E2E header, and the wire's
resolution and ranges against the issue's requirements and RobotConfig().

Tolerances. Integer signals (scale 1, offset 0) must agree exactly. A scaled signal's value
is ``raw * scale + offset`` in binary floating point, and scales such as 0.001 or 1e-6 are not
exact binary fractions, so two correct implementations may give values an ulp apart for
the same raw integer; what the wire carries is the raw integer. Values closer than half a
scale step to each other round to the same raw integer, so "within half a step" is the
widest tolerance that still means "the same bits on the wire"; the tests also check the raw
integers (and the bytes) exactly. For a value off the grid, encoding rounds to the nearest
step, so a round trip moves it by at most half a step.
"""

from __future__ import annotations

import math
import struct
from itertools import combinations
from typing import Any

import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import ROOT

from protocol.codec import WIRE, MessageCodec, SignalSpec, Wire, crc8
from protocol.config import RobotConfig
from protocol.errors import DecodeError, EncodeError

DBC_PATH = ROOT / "protocol" / "scara.dbc"
DB: Any = cantools.database.load_file(str(DBC_PATH))
CODECS = list(WIRE.messages.values())
IDS = [codec.name for codec in CODECS]
PROPERTY = settings(max_examples=150, deadline=None)

# The issue's resolution requirements, by DBC unit.
REQUIRED_RESOLUTION = {"rad": 1e-6, "m": 1e-6, "rad/s": 1e-3, "m/s": 1e-4}


# --- helpers ---------------------------------------------------------------------------------


def physical(spec: SignalSpec, raw: int) -> float:
    """The physical value of a raw integer, as the DBC defines it."""
    return raw if spec.integer else raw * spec.scale + spec.offset


def quantised(spec: SignalSpec, value: float) -> float:
    """The value the wire can carry nearest to ``value``."""
    return physical(spec, round((value - spec.offset) / spec.scale))


def raw_of(spec: SignalSpec, value: float) -> int:
    return round((value - spec.offset) / spec.scale)


def assert_same(spec: SignalSpec, got: float, want: float) -> None:
    """Exact for integer signals; for scaled ones within half a step and the same raw."""
    if spec.integer:
        assert got == want, spec.name
    else:
        assert abs(got - want) < spec.scale / 2, (spec.name, got, want)
        assert raw_of(spec, got) == raw_of(spec, want), spec.name


def raws(spec: SignalSpec) -> st.SearchStrategy[int]:
    """Raw integers over the whole DBC range, its ends and zero drawn often."""
    low, high = spec.raw_range
    edges = sorted({low, high, min(max(0, low), high)})
    return st.one_of(st.sampled_from(edges), st.integers(low, high))


def mid_values(codec: MessageCodec) -> list[float]:
    """A valid, non-trivial value for every signal."""
    return [physical(s, (s.raw_range[0] + 2 * s.raw_range[1]) // 3) for s in codec.signals]


def with_crc(frame_id: int, frame: bytes | bytearray) -> bytes:
    """The frame with byte 0 set to the right CRC for ``frame_id``."""
    data = bytearray(frame)
    data[0] = crc8(frame_id, bytes(data[1:]))
    return bytes(data)


def cantools_encode(codec: MessageCodec, values: list[float], counter: int) -> bytes:
    """cantools' frame for the same values, with our CRC put into byte 0."""
    signals: dict[str, float] = {"Crc": 0, "Counter": counter}
    signals |= dict(zip(codec.signal_names, values, strict=True))
    data = DB.encode_message(codec.frame_id, signals, scaling=True, strict=True)
    assert data[0] == 0
    return with_crc(codec.frame_id, data)


def crc8_bitwise(data: bytes) -> int:
    """CRC-8 SAE J1850 the slow way: poly 0x1D, init 0xFF, xor-out 0xFF, MSB first."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def bit_range(spec: SignalSpec) -> tuple[int, int]:
    """Raw integers the signal's bits can hold."""
    if spec.signed:
        return -(1 << (spec.length - 1)), (1 << (spec.length - 1)) - 1
    return 0, (1 << spec.length) - 1


# --- the codec against cantools ------------------------------------------------------------


def test_every_dbc_message_is_compiled() -> None:
    assert sorted(m.name for m in DB.messages) == sorted([*WIRE.messages, *WIRE.isotp])
    for message in DB.messages:
        if message.name in WIRE.isotp:  # ISO-TP carriers: raw frames, the transfer is checked
            carrier = WIRE.isotp[message.name]
            assert (carrier.frame_id, carrier.length) == (message.frame_id, 8)
            assert [s.name for s in message.signals] == ["IsoTp"]
            continue
        codec = WIRE[message.name]
        assert (codec.frame_id, codec.length) == (message.frame_id, message.length)
        names = [s.name for s in message.signals if s.name not in ("Crc", "Counter")]
        assert sorted(codec.signal_names) == sorted(names)


@pytest.mark.parametrize("codec", CODECS, ids=IDS)
@PROPERTY
@given(data=st.data())
def test_codec_agrees_with_cantools_over_the_whole_range(
    codec: MessageCodec, data: st.DataObject
) -> None:
    raw = [data.draw(raws(spec), label=spec.name) for spec in codec.signals]
    counter = data.draw(st.integers(0, 15), label="counter")
    values = [physical(spec, r) for spec, r in zip(codec.signals, raw, strict=True)]

    # ours -> cantools
    ours = codec.encode(values, counter)
    assert len(ours) == codec.length
    theirs = DB.decode_message(codec.frame_id, ours, decode_choices=False, scaling=True)
    assert theirs["Counter"] == counter
    assert theirs["Crc"] == ours[0] == crc8(codec.frame_id, ours[1:])
    for spec, value in zip(codec.signals, values, strict=True):
        assert_same(spec, theirs[spec.name], value)

    # cantools -> ours: the very same bytes, and the same values back
    cantools_frame = cantools_encode(codec, values, counter)
    assert cantools_frame == ours
    got_counter, got = codec.decode(cantools_frame)
    assert got_counter == counter
    for spec, value, back in zip(codec.signals, values, got, strict=True):
        assert_same(spec, back, value)

    # our round trip gives exactly the quantised value
    assert codec.decode(ours) == (
        counter,
        tuple(quantised(s, v) for s, v in zip(codec.signals, values, strict=True)),
    )

    # our encoding of what cantools decoded is the same frame
    again = [theirs[name] for name in codec.signal_names]
    assert codec.encode(again, counter) == ours


@pytest.mark.parametrize("codec", CODECS, ids=IDS)
@PROPERTY
@given(data=st.data())
def test_values_off_the_grid_round_to_the_nearest_step(
    codec: MessageCodec, data: st.DataObject
) -> None:
    values: list[float] = []
    for spec in codec.signals:
        low, high = spec.raw_range
        if spec.integer:
            values.append(data.draw(st.integers(low, high), label=spec.name))
        else:
            bounds = physical(spec, low), physical(spec, high)
            values.append(data.draw(st.floats(*bounds), label=spec.name))
    ours = codec.encode(values, 9)
    assert cantools_encode(codec, values, 9) == ours
    _, got = codec.decode(ours)
    for spec, value, back in zip(codec.signals, values, got, strict=True):
        assert back == quantised(spec, value)
        assert abs(back - value) <= spec.scale * (0.5 + 1e-6), spec.name
    # The in-process simulation's wire: the same values without building the frame, bit for
    # bit (the lockstep co-simulation's logs equal the simulation's only if this holds).
    assert codec.quantise(values) == got
    assert all(type(a) is type(b) for a, b in zip(codec.quantise(values), got, strict=True))


# --- E2E header: CRC-8 SAE J1850 over the frame ID and bytes 1.. ----------------------------


def test_crc_is_sae_j1850() -> None:
    assert crc8_bitwise(b"123456789") == 0x4B  # the standard check value
    # crc8 prefixes the ID as two little-endian bytes: "12" is ID 0x3231.
    assert crc8(0x3231, b"3456789") == 0x4B


@given(frame_id=st.integers(0, 0x7FF), body=st.binary(max_size=7))
def test_crc_table_matches_the_bitwise_reference(frame_id: int, body: bytes) -> None:
    assert crc8(frame_id, body) == crc8_bitwise(frame_id.to_bytes(2, "little") + body)


@pytest.mark.parametrize("codec", CODECS, ids=IDS)
def test_crc_covers_the_frame_id(codec: MessageCodec) -> None:
    frame = codec.encode(mid_values(codec), 3)
    body = frame[1:]
    others = {c.frame_id for c in CODECS} - {codec.frame_id}
    for first, second in combinations(range(11), 2):  # every 1- and 2-bit change of the ID
        others |= {codec.frame_id ^ (1 << first), codec.frame_id ^ (1 << first) ^ (1 << second)}
    for other_id in others - {codec.frame_id}:
        assert crc8(other_id, body) != frame[0], hex(other_id)
    # The same payload under another ID of the same length is refused.
    for other in CODECS:
        if other is not codec and other.length == codec.length:
            with pytest.raises(DecodeError, match="CRC"):
                WIRE.decode(other.frame_id, frame)


@pytest.mark.parametrize("codec", CODECS, ids=IDS)
def test_every_single_and_double_bit_flip_is_refused(codec: MessageCodec) -> None:
    frame = codec.encode(mid_values(codec), 11)
    assert WIRE.decode(codec.frame_id, frame)[1] == 11
    bits = range(8 * codec.length)
    for flips in [(bit,) for bit in bits] + list(combinations(bits, 2)):
        corrupt = bytearray(frame)
        for bit in flips:
            corrupt[bit // 8] ^= 1 << (bit % 8)
        with pytest.raises(DecodeError):
            WIRE.decode(codec.frame_id, bytes(corrupt))


@pytest.mark.parametrize("codec", CODECS, ids=IDS)
def test_wrong_length_is_refused(codec: MessageCodec) -> None:
    frame = codec.encode(mid_values(codec), 0)
    for wrong in (frame[:-1], frame + b"\x00", b"", frame + frame):
        with pytest.raises(DecodeError, match="DLC"):
            WIRE.decode(codec.frame_id, wrong)
        with pytest.raises(DecodeError):
            codec.decode(wrong)


def test_unknown_id_is_refused() -> None:
    frame = WIRE["JointState1"].encode(mid_values(WIRE["JointState1"]), 0)
    for frame_id in sorted({0x000, 0x7FF, 0x113, 0x101} - set(WIRE.by_id)):
        with pytest.raises(DecodeError, match="unknown") as info:
            WIRE.decode(frame_id, with_crc(frame_id, frame))
        assert info.value.frame_id == frame_id


@pytest.mark.parametrize("codec", CODECS, ids=IDS)
def test_values_outside_the_dbc_range_are_refused_naming_the_signal(codec: MessageCodec) -> None:
    good = mid_values(codec)
    codec.encode(good, 0)
    for index, spec in enumerate(codec.signals):
        low, high = spec.raw_range
        step = 1.0 if spec.integer else spec.scale
        for bad in (
            physical(spec, high) + step,
            physical(spec, low) - step,
            math.nan,
            math.inf,
            -math.inf,
        ):
            values = list(good)
            values[index] = bad
            with pytest.raises(EncodeError, match=rf"{codec.name}\.{spec.name}\b"):
                codec.encode(values, 0)
    with pytest.raises(EncodeError):
        codec.encode(good[:-1], 0)


@pytest.mark.parametrize("codec", CODECS, ids=IDS)
def test_raw_values_outside_the_dbc_range_are_refused_with_a_valid_crc(
    codec: MessageCodec,
) -> None:
    crafted = 0
    for spec in codec.signals:
        low, high = spec.raw_range
        bits_low, bits_high = bit_range(spec)
        for bad in (high + 1, bits_high, low - 1, bits_low):
            if not (bits_low <= bad <= bits_high) or low <= bad <= high:
                continue
            raw = {s.name: s.raw_range[0] for s in codec.signals} | {"Crc": 0, "Counter": 1}
            raw[spec.name] = bad
            data = DB.encode_message(codec.frame_id, raw, scaling=False, strict=False)
            with pytest.raises(DecodeError, match=f"{spec.name}: raw {bad} out of range"):
                WIRE.decode(codec.frame_id, with_crc(codec.frame_id, data))
            crafted += 1
    if codec.name.startswith(("JointState", "JointVelocityCommand")):
        assert crafted > 0


@pytest.mark.parametrize("codec", CODECS, ids=IDS)
def test_bits_outside_every_signal_must_be_zero(codec: MessageCodec) -> None:
    message = DB.get_message_by_name(codec.name)
    used = {bit for s in message.signals for bit in range(s.start, s.start + s.length)}
    frame = codec.encode(mid_values(codec), 2)
    for bit in sorted(set(range(8 * codec.length)) - used):
        crafted = bytearray(frame)
        crafted[bit // 8] |= 1 << (bit % 8)
        with pytest.raises(DecodeError):
            WIRE.decode(codec.frame_id, with_crc(codec.frame_id, crafted))


@pytest.mark.parametrize("codec", CODECS, ids=IDS)
def test_dbc_ranges_fit_their_bits(codec: MessageCodec) -> None:
    for spec in codec.signals:
        low, high = spec.raw_range
        bits_low, bits_high = bit_range(spec)
        assert bits_low <= low <= high <= bits_high, spec.name


def test_every_value_a_table_names_is_in_its_signals_range() -> None:
    # Reason 15 (no_way_round) was named but outside [0, 14]: the controller could not say it
    for message in DB.messages:
        for signal in message.signals:
            if signal.choices:
                low, high = signal.minimum, signal.maximum
                assert all(low <= int(value) <= high for value in signal.choices), (
                    f"{message.name}.{signal.name}: {sorted(signal.choices)} not in [{low}, {high}]"
                )


def test_counter_is_the_low_nibble_of_byte_1() -> None:
    codec = WIRE["JointVelocityCommand"]
    for counter in range(16):
        frame = codec.encode([1, 0.5, -0.25, 0.125], counter)
        assert frame[1] & 0x0F == counter
        assert codec.decode(frame)[0] == counter


# --- the codec refuses a DBC it cannot compile ---------------------------------------------

PROBE_DBC = """VERSION ""

NS_ :

BS_:

BU_: A B

BO_ 100 Probe: {length} A
 SG_ Crc : 0|8@1+ (1,0) [0|255] "" B
 SG_ Counter : 8|4@1+ (1,0) [0|15] "" B
{signals}
"""


def probe(length: int, *signals: str) -> str:
    return PROBE_DBC.format(length=length, signals="\n".join(f" SG_ {s} B" for s in signals))


def test_a_well_formed_probe_compiles() -> None:
    wire = Wire(
        probe(4, 'Mode : 12|2@1+ (1,0) [0|3] ""', 'Speed : 16|16@1- (0.01,0) [-100|100] ""')
    )
    codec = wire["Probe"]
    assert codec.decode(codec.encode([2, -12.34], 7)) == (7, (2, -12.34))


@pytest.mark.parametrize(
    ("length", "signals", "named"),
    [
        (4, ['Speed : 20|12@1+ (1,0) [0|4095] ""'], "Probe.Speed"),  # misaligned start
        (5, ['Speed : 18|16@1- (1,0) [-100|100] ""'], "Probe.Speed"),  # straddles bytes
        (4, ['Speed : 16|12@1+ (1,0) [0|4095] ""'], "Probe.Speed"),  # 12 bits wide
        (4, ['Lo : 16|8@1+ (1,0) [0|255] ""', 'Speed : 26|6@1+ (1,0) [0|63] ""'], "Probe.Speed"),
        (4, ['Mode : 12|2@1- (1,0) [-1|1] ""', 'Speed : 16|16@1+ (1,0) [0|9] ""'], "Probe.Mode"),
        (4, ['Mode : 12|1@1+ (0.5,0) [0|0.5] ""', 'Speed : 16|16@1+ (1,0) [0|9] ""'], "Probe.Mode"),
        (4, ['Speed : 16|8@1+ (1,0) [0|255] ""'], "Probe: signals cover 24 bits of 32"),
        (4, ['Speed : 23|16@0- (1,0) [-100|100] ""'], "Probe: must start"),  # Motorola order
    ],
)
def test_a_dbc_the_codec_cannot_compile_is_refused(
    length: int, signals: list[str], named: str
) -> None:
    with pytest.raises(ValueError, match=named):
        Wire(probe(length, *signals))


# --- resolution and ranges of the wire against the issue and RobotConfig() ------------------


def test_resolution_meets_the_issue() -> None:
    """The joint state and the command carry the required resolution (the monitoring frames,
    ControllerCoordination's distances and angle, need not)."""
    seen: set[str] = set()
    control = ("JointVelocityCommand", "JointState1", "JointState2", "JointState3")
    for codec in (WIRE[name] for name in control):
        for spec in codec.signals:
            if spec.unit in REQUIRED_RESOLUTION:
                seen.add(spec.unit)
                need = REQUIRED_RESOLUTION[spec.unit]
                assert spec.scale <= need * (1 + 1e-9), (codec.name, spec.name, spec.scale)
    assert seen == set(REQUIRED_RESOLUTION)


def _encodable(spec: SignalSpec) -> tuple[float, float]:
    low, high = spec.raw_range
    return physical(spec, low), physical(spec, high)


def _rates(codec: MessageCodec) -> list[SignalSpec]:
    return [s for s in codec.signals if s.unit in ("rad/s", "m/s")]


def test_dbc_ranges_cover_the_default_robot() -> None:
    robot = RobotConfig()
    units = ("rad", "rad", "m")
    command = _rates(WIRE["JointVelocityCommand"])
    assert [s.unit for s in command] == [unit + "/s" for unit in units]
    for joint in range(3):
        state = WIRE[f"JointState{joint + 1}"]
        (position,) = [s for s in state.signals if s.unit == units[joint]]
        (velocity,) = _rates(state)
        low, high = _encodable(position)
        assert low <= robot.joint_min[joint] and robot.joint_max[joint] <= high, position.name
        limit = robot.speed_limits[joint]
        for rate in (velocity, command[joint]):
            low, high = _encodable(rate)
            assert low <= -limit and limit <= high, (joint, rate.name)


def test_the_default_robots_extremes_cross_the_wire() -> None:
    robot = RobotConfig()
    command = WIRE["JointVelocityCommand"]
    for sign in (-1.0, 1.0):
        rates = [sign * limit for limit in robot.speed_limits]
        _, got = command.decode(command.encode([1, *rates], 0))
        for spec, rate, back in zip(command.signals[1:], rates, got[1:], strict=True):
            assert abs(back - rate) <= spec.scale / 2
    for joint in range(3):
        state = WIRE[f"JointState{joint + 1}"]
        limit = robot.speed_limits[joint]
        for position in (robot.joint_min[joint], robot.joint_max[joint]):
            for velocity in (-limit, limit):
                _, (_, p, v) = state.decode(state.encode([0, position, velocity], 0))
                assert abs(p - position) <= state.signals[1].scale / 2
                assert abs(v - velocity) <= state.signals[2].scale / 2


def test_struct_layout_is_little_endian() -> None:
    # A hand-packed frame, independent of both codecs: Theta1Rate -1.000, Theta2Rate 2.000,
    # D3Rate 0.0300, Enable 1, counter 4.
    codec = WIRE["JointVelocityCommand"]
    frame = with_crc(codec.frame_id, struct.pack("<BBhhh", 0, 0x14, -1000, 2000, 300))
    assert codec.encode([1, -1.0, 2.0, 0.03], 4) == frame


# --- frames by name ------------------------------------------------------------------------


@pytest.mark.parametrize("codec", CODECS, ids=IDS)
def test_records_are_named_as_in_the_dbc(codec: MessageCodec) -> None:
    message = DB.get_message_by_name(codec.name)
    in_frame_order = sorted(message.signals, key=lambda signal: signal.start)
    names = [s.name for s in in_frame_order if s.name not in ("Crc", "Counter")]
    assert list(codec.Record._fields) == names
    values = mid_values(codec)
    by_name = codec.record(**dict(zip(names, values, strict=True)))
    assert codec.encode(by_name, 3) == codec.encode(values, 3)
    counter, decoded = codec.decode(codec.encode(by_name, 3))
    assert counter == 3 and type(decoded) is codec.Record
    for name in names:
        assert_same(codec.spec[name], getattr(decoded, name), getattr(by_name, name))
    with pytest.raises(TypeError):
        codec.record(**dict(zip(names[1:], values[1:], strict=True)))  # every field is needed


def test_enumerations_are_the_dbcs_value_tables() -> None:
    from protocol.messages import ControllerFault, NodeState, PlantFlag, Request

    state = DB.get_message_by_name("ControllerStatus").get_signal_by_name("State").choices
    assert {member.value: member.name for member in NodeState} == {
        int(value): str(label).upper() for value, label in state.items()
    }
    faults = DB.get_message_by_name("ControllerStatus").get_signal_by_name("FaultCode").choices
    assert {member.value: member.name for member in ControllerFault} == {
        int(value): str(label).upper() for value, label in faults.items()
    }
    assert all(bin(member.value).count("1") == 1 for member in ControllerFault)
    assert PlantFlag.COLLISION | PlantFlag.D3_AT_STOP == 9
    assert Request.RESET == 1 and NodeState.HOLD.name == "HOLD"


def test_a_shared_enumeration_whose_tables_differ_is_refused() -> None:
    text = DBC_PATH.read_text().replace('VAL_ 1793 State 0 "init"', 'VAL_ 1793 State 0 "booting"')
    wire = Wire(text)
    with pytest.raises(ValueError, match="differ"):
        wire.enum("NodeState", ("ControllerStatus", "State"), ("PlantStatus", "State"))


def test_send_schedules_come_from_the_dbc_attributes() -> None:
    assert WIRE["JointVelocityCommand"].schedule == "tick"
    assert WIRE["StepSync"].schedule == "lockstep_tick"
    assert WIRE["ControllerStatus"].schedule == "cyclic"
    assert WIRE["ControllerStatus"].cycle_time == pytest.approx(0.1)
    assert WIRE["EmergencyStop"].schedule == "event" and WIRE["EmergencyStop"].cycle_time is None
