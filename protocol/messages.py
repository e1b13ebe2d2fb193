"""The frames the nodes exchange, as typed helpers over the codec (layouts live in the DBC).

Also the wire quantisation as a function: the in-process simulation passes the joint state
and the command through :func:`on_the_wire_state` and :func:`on_the_wire_command`, so it sees
exactly the values a controller and a plant see over CAN, and a lockstep co-simulation gives
bit-identical results.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass
from enum import IntEnum, IntFlag

import can

from protocol.codec import COUNTER_MODULO, WIRE, MessageCodec

Joints = tuple[float, float, float]

COMMAND = WIRE["JointVelocityCommand"]
STATE = (WIRE["JointState1"], WIRE["JointState2"], WIRE["JointState3"])
STATE_IDS = tuple(codec.frame_id for codec in STATE)
STEP = WIRE["StepSync"]
STOP = WIRE["EmergencyStop"]
NODE_COMMAND = WIRE["NodeCommand"]
CONTROLLER_STATUS = WIRE["ControllerStatus"]
PLANT_STATUS = WIRE["PlantStatus"]
STATUS_PERIOD = 0.1
"""s between status frames (about 10 Hz)."""


class NodeState(IntEnum):
    INIT = 0
    READY = 1
    RUNNING = 2
    FAULT = 3
    ESTOP = 4


class NodeId(IntEnum):
    CONTROLLER = 1
    PLANT = 2
    OPERATOR = 3
    ALL = 255


class Request(IntEnum):
    RESET = 1
    RUN = 2
    STOP = 3


class ControllerFault(IntFlag):
    STALE_STATE = 1
    PLANT_FAULT = 2
    ESTOP = 4
    ENCODE = 8


class PlantFault(IntFlag):
    JOINT_LIMIT = 1
    COMMAND_TIMEOUT = 2
    COLLISION = 4
    ESTOP = 8


class Counter:
    """The alive counter of one frame ID: +1 mod 16 per frame sent."""

    __slots__ = ("value",)

    def __init__(self) -> None:
        self.value = COUNTER_MODULO - 1

    def next(self) -> int:
        self.value = (self.value + 1) % COUNTER_MODULO
        return self.value


@dataclass(frozen=True, slots=True)
class Status:
    """A decoded ControllerStatus or PlantStatus frame."""

    state: NodeState
    fault: int
    flags: int
    bad_frames: int
    extra: int


def encode_status(
    codec: MessageCodec,
    counter: int,
    state: NodeState,
    fault: int,
    flags: int,
    bad: int,
    extra: int,
) -> bytes:
    """``bad`` saturates at the field's maximum; ``extra`` must already fit 16 bits."""
    return codec.encode((int(state), fault, flags, min(bad, 0xFFFF), extra), counter)


def decode_status(values: Sequence[float]) -> Status:
    state, fault, flags, bad, extra = (int(v) for v in values)
    return Status(NodeState(min(state, NodeState.ESTOP)), fault, flags, bad, extra)


def send_frame(bus: can.BusABC, frame_id: int, data: bytes, prog: str) -> None:
    """Send one frame; a failure is said on stderr and the node goes on (the next tick retries)."""
    try:
        bus.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))
    except can.CanError as error:
        print(f"{prog}: send failed: {error}", file=sys.stderr)


def on_the_wire_command(rates: Joints) -> Joints:
    """The command the plant decodes for ``rates``."""
    _, values = COMMAND.decode(COMMAND.encode((1, *rates), 0))
    return (values[1], values[2], values[3])


def on_the_wire_state(position: Joints, velocity: Joints) -> tuple[Joints, Joints]:
    """The joint state the controller decodes for the plant's exact state."""
    decoded = [
        codec.decode(codec.encode((0, p, v), 0))[1]
        for codec, p, v in zip(STATE, position, velocity, strict=True)
    ]
    return (
        (decoded[0][1], decoded[1][1], decoded[2][1]),
        (decoded[0][2], decoded[1][2], decoded[2][2]),
    )
