"""The frame codec: the DBC compiled into ``struct`` layouts, with the E2E header checked.

``scara.dbc`` is the one definition of the wire. At import the codec reads it with cantools
and compiles each message into a precomputed ``struct.Struct``: byte 0 is the CRC, the low
nibble of byte 1 the alive counter, the high nibble of byte 1 may hold one small signal, and
every other signal is byte-aligned little-endian of 8, 16, 24 or 32 bits. A DBC that strays
from that shape is refused here rather than encoded wrongly. Tests check every message
against cantools' own decoding of the same file.

Frames are read and written by name: each message has a record type (a named tuple whose
fields are the message's signals, named as in the DBC, Crc and Counter left out) that
:meth:`MessageCodec.decode` returns and :meth:`MessageCodec.encode` takes. Enumerations and
the bits of flag fields are the DBC's value tables, turned into Python enums by
:meth:`Wire.enum`, and send schedules its ``GenMsgCycleTime`` and ``ScaraSchedule``
attributes.

Encoding is strict, as in cantools: a value outside its signal's DBC range raises
:class:`EncodeError`. Decoding raises :class:`DecodeError` for an unknown ID, a wrong length,
a bad CRC or a value outside its range.
"""

from __future__ import annotations

import enum
import math
import struct
from collections import namedtuple
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from typing import Any

import cantools

from protocol.errors import DecodeError, EncodeError
from protocol.ops import SCALAR, Ops, Real

DBC_TEXT = resources.files("protocol").joinpath("scara.dbc").read_text()

CRC_POLY = 0x1D  # CRC-8 SAE J1850, as AUTOSAR E2E profile 1
CRC_INIT = 0xFF
CRC_XOR_OUT = 0xFF
COUNTER_MODULO = 16


def alive_counter(data: bytes | bytearray) -> int:
    """The alive counter of a frame's E2E header (low nibble of byte 1), without decoding."""
    return data[1] & 0x0F


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ CRC_POLY) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc8(frame_id: int, body: bytes | bytearray | memoryview) -> int:
    """CRC over the frame ID (2 bytes, little-endian) and bytes 1.. of the frame."""
    table = _CRC_TABLE
    crc = table[CRC_INIT ^ (frame_id & 0xFF)]
    crc = table[crc ^ ((frame_id >> 8) & 0xFF)]
    for byte in body:
        crc = table[crc ^ byte]
    return crc ^ CRC_XOR_OUT


@dataclass(frozen=True, slots=True)
class SignalSpec:
    """One signal of a message, with its raw integer range taken from the DBC."""

    name: str
    start: int
    length: int
    signed: bool
    scale: float
    offset: float
    minimum: float
    maximum: float
    unit: str

    @property
    def integer(self) -> bool:
        return self.scale == 1 and self.offset == 0

    @property
    def raw_range(self) -> tuple[int, int]:
        low = math.ceil(round((self.minimum - self.offset) / self.scale, 6))
        high = math.floor(round((self.maximum - self.offset) / self.scale, 6))
        return low, high


def quantised(ops: Ops, value: Real, scale: float, offset: float, low: int, high: int) -> Real:
    """The value a receiver decodes for ``value`` sent in a signal of ``scale`` and
    ``offset`` whose raw integers lie in [``low``, ``high``] (round half to even, as Python's
    ``round`` and numpy's ``rint``): for one value, or one per run of a batch."""
    raw = ops.min(ops.max(ops.rint((value - offset) / scale), low), high)
    return raw * scale + offset


_FORMATS = {(8, False): "B", (8, True): "b", (16, False): "H", (16, True): "h"}
_FORMATS |= {(32, False): "I", (32, True): "i", (24, False): "HB", (24, True): "Hb"}


class MessageCodec:
    """Encoder and decoder of one message.

    ``Record`` is the message's named tuple: its fields are the signals after Crc and
    Counter (see :attr:`signal_names`), in the order they sit in the frame.
    """

    def __init__(self, message: Any, schedule: str) -> None:
        self.name: str = message.name
        self.frame_id: int = message.frame_id
        self.length: int = message.length
        self.schedule = schedule
        """``event``, ``tick`` (every control tick), ``lockstep_tick`` or ``cyclic``."""
        self.cycle_time: float | None = message.cycle_time / 1000 if message.cycle_time else None
        """s between frames (for ``tick`` messages: at the default control rate)."""
        specs = sorted(
            (
                SignalSpec(
                    s.name,
                    s.start,
                    s.length,
                    s.is_signed,
                    float(s.scale),
                    float(s.offset),
                    float(s.minimum),
                    float(s.maximum),
                    s.unit or "",
                )
                for s in message.signals
            ),
            key=lambda spec: spec.start,
        )
        head = [(spec.name, spec.start, spec.length) for spec in specs[:2]]
        little = all(s.byte_order == "little_endian" for s in message.signals)
        if head != [("Crc", 0, 8), ("Counter", 8, 4)] or not little:
            raise ValueError(f"{self.name}: must start with Crc 0|8 and Counter 8|4, Intel order")
        rest = specs[2:]
        self.aux: SignalSpec | None = None
        if rest and rest[0].start == 12:
            self.aux = rest.pop(0)
            if self.aux.length > 4 or self.aux.signed or not self.aux.integer:
                raise ValueError(f"{self.name}.{self.aux.name}: byte 1 holds a small unsigned int")
        fmt = "<BB"
        position = 16
        for spec in rest:
            if spec.start != position or (spec.length, spec.signed) not in _FORMATS:
                raise ValueError(
                    f"{self.name}.{spec.name}: not a byte-aligned 8/16/24/32-bit field"
                )
            fmt += _FORMATS[(spec.length, spec.signed)]
            position += spec.length
        if position != self.length * 8:
            raise ValueError(f"{self.name}: signals cover {position} bits of {self.length * 8}")
        self.struct = struct.Struct(fmt)
        self.signals: tuple[SignalSpec, ...] = ((self.aux,) if self.aux else ()) + tuple(rest)
        self.signal_names = tuple(spec.name for spec in self.signals)
        self.spec = {spec.name: spec for spec in self.signals}
        self.choices: dict[str, dict[int, str]] = {
            s.name: {int(value): str(label) for value, label in s.choices.items()}
            for s in message.signals
            if s.choices
        }
        self.Record: Any = namedtuple(self.name, self.signal_names)  # type: ignore[misc]
        for spec in self.signals:
            low, high = spec.raw_range
            bits = spec.length
            lowest, highest = (
                (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if spec.signed else (0, (1 << bits) - 1)
            )
            if low < lowest or high > highest:
                raise ValueError(f"{self.name}.{spec.name}: DBC range does not fit {bits} bits")
        self._plan = tuple(
            (spec.scale, spec.offset, *spec.raw_range, spec.length == 24, spec.integer)
            for spec in self.signals
        )
        self._limits = tuple((spec.minimum, spec.maximum) for spec in self.signals)
        self._make = tuple.__new__

    def record(self, **fields: float) -> Any:
        """The message's record from its fields by name (every field must be given)."""
        return self.Record(**fields)

    def encode(self, record: Sequence[float], counter: int) -> bytes:
        """The frame's bytes for ``record`` (physical units) and alive ``counter``."""
        if len(record) != len(self._plan):
            raise EncodeError(f"{self.name}: expected {len(self._plan)} values {self.signal_names}")
        if not 0 <= counter < COUNTER_MODULO:
            raise EncodeError(f"{self.name}.Counter: {counter} outside [0, {COUNTER_MODULO - 1}]")
        raws: list[int] = []
        for index, (
            value,
            (scale, offset, low, high, wide, integer),
            (minimum, maximum),
        ) in enumerate(zip(record, self._plan, self._limits, strict=True)):
            if not minimum <= value <= maximum:  # also false for NaN
                name = f"{self.name}.{self.signal_names[index]}"
                raise EncodeError(f"{name}: {value!r} outside [{minimum:g}, {maximum:g}]")
            raw = round((value - offset) / scale)
            if integer and raw != value:
                raise EncodeError(
                    f"{self.name}.{self.signal_names[index]}: {value!r} is not an integer"
                )
            raw = low if raw < low else high if raw > high else raw
            if wide:
                raws.append(raw & 0xFFFF)
                raws.append(raw >> 16)
            else:
                raws.append(raw)
        second = counter & 0x0F
        if self.aux is not None:
            second |= raws.pop(0) << 4
        body = bytearray(self.struct.pack(0, second, *raws))
        body[0] = crc8(self.frame_id, memoryview(body)[1:])
        return bytes(body)

    def quantise(self, record: Sequence[float]) -> Any:
        """The record a receiver decodes when ``record`` is sent: ``decode(encode(record))``'s
        values, bit for bit, without building the frame (the in-process simulation's wire)."""
        if len(record) != len(self._plan):
            raise EncodeError(f"{self.name}: expected {len(self._plan)} values {self.signal_names}")
        values: list[float] = []
        for index, (value, (scale, offset, low, high, _, integer), (minimum, maximum)) in enumerate(
            zip(record, self._plan, self._limits, strict=True)
        ):
            if not minimum <= value <= maximum:  # also false for NaN
                name = f"{self.name}.{self.signal_names[index]}"
                raise EncodeError(f"{name}: {value!r} outside [{minimum:g}, {maximum:g}]")
            if integer:
                if round(value) != value:
                    raise EncodeError(
                        f"{self.name}.{self.signal_names[index]}: {value!r} is not an integer"
                    )
                values.append(round(value))
                continue
            values.append(quantised(SCALAR, value, scale, offset, low, high))
        return self._make(self.Record, values)

    def decode(self, data: bytes | bytearray) -> tuple[int, Any]:
        """``(counter, record)`` of a frame; :class:`DecodeError` if it is not valid."""
        if len(data) != self.length:
            raise DecodeError(self.frame_id, f"{self.name} has DLC {self.length}, got {len(data)}")
        if crc8(self.frame_id, memoryview(data)[1:]) != data[0]:
            raise DecodeError(self.frame_id, f"{self.name}: CRC mismatch")
        unpacked = self.struct.unpack(data)
        second = unpacked[1]
        raws = list(unpacked[2:])
        if self.aux is not None:
            raws.insert(0, second >> 4)
        elif second >> 4:
            raise DecodeError(self.frame_id, f"{self.name}: unused bits of byte 1 are set")
        values: list[float] = []
        cursor = 0
        for index, (scale, offset, low, high, wide, integer) in enumerate(self._plan):
            raw = raws[cursor]
            if wide:
                raw |= raws[cursor + 1] << 16
                cursor += 2
            else:
                cursor += 1
            if raw < low or raw > high:
                raise DecodeError(
                    self.frame_id, f"{self.name}.{self.signal_names[index]}: raw {raw} out of range"
                )
            values.append(raw if integer else raw * scale + offset)
        return alive_counter(data), self._make(self.Record, values)


@dataclass(frozen=True, slots=True)
class IsoTpMessage:
    """A DBC message that carries ISO-TP (ISO 15765-2) frames: no E2E header per frame; the
    transfer is checked whole by its receiver."""

    name: str
    frame_id: int
    length: int
    schedule: str = "isotp"
    cycle_time: float | None = None


class Wire:
    """Every message of the DBC, by name and by frame ID: the E2E-protected ones compiled into
    :class:`MessageCodec` s (``messages``), the ISO-TP carriers apart (``isotp``)."""

    def __init__(self, dbc_text: str = DBC_TEXT) -> None:
        database: Any = cantools.database.load_string(dbc_text, database_format="dbc")
        definition = database.dbc.attribute_definitions.get("ScaraSchedule")
        self.messages: dict[str, MessageCodec] = {}
        self.isotp: dict[str, IsoTpMessage] = {}
        for message in database.messages:
            schedule = _schedule(message, definition)
            if schedule == "isotp":
                self.isotp[message.name] = IsoTpMessage(
                    message.name, message.frame_id, message.length
                )
            else:
                self.messages[message.name] = MessageCodec(message, schedule)
        self.by_id = {codec.frame_id: codec for codec in self.messages.values()}
        self.defined_ids = frozenset(
            [*self.by_id, *(carrier.frame_id for carrier in self.isotp.values())]
        )
        """Every frame ID the DBC defines; any other ID on the bus is foreign."""

    def __getitem__(self, name: str) -> MessageCodec:
        return self.messages[name]

    def decode(self, frame_id: int, data: bytes | bytearray) -> tuple[MessageCodec, int, Any]:
        """Decode a frame of any message; :class:`DecodeError` for an unknown ID too."""
        codec = self.by_id.get(frame_id)
        if codec is None:
            raise DecodeError(frame_id, "unknown frame ID")
        counter, record = codec.decode(data)
        return codec, counter, record

    def enum(self, name: str, *signals: tuple[str, str], flag: bool = False) -> Any:
        """An ``IntEnum`` (or ``IntFlag``) from the value table of ``(message, signal)``.

        Members are the table's labels in upper case. Several signals may share one
        enumeration: their tables must then be the same.
        """
        tables = [self[message].choices[signal] for message, signal in signals]
        if any(table != tables[0] for table in tables):
            raise ValueError(f"{name}: the value tables of {signals} differ")
        members = {label.upper(): value for value, label in sorted(tables[0].items())}
        if flag:
            return enum.IntFlag(name, members)
        return enum.IntEnum(name, members)


def _schedule(message: Any, definition: Any) -> str:
    """The message's ``ScaraSchedule`` attribute; ``event`` where the DBC has none."""
    if definition is None:
        return "event"
    attribute = message.dbc.attributes.get("ScaraSchedule") if message.dbc else None
    if attribute is None:
        return str(definition.default_value)
    return str(definition.choices[attribute.value])


WIRE = Wire()
"""The project's wire, compiled once from ``scara.dbc``."""
