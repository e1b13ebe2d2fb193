"""The frames the nodes exchange, by name, and the enumerations of the wire.

Layouts, enumerations, flag bits and send periods all come from ``scara.dbc`` (through
:data:`protocol.codec.WIRE`); this module only gives them Python names. Enumeration members
are the DBC's value-table labels in upper case, e.g. ``NodeState.RUNNING``; they are built at
import, so static type checkers see them as ``Any``. :func:`reason_of` is the Reason a task's
error gets on the wire (the controller's answer, and the bridge's refusal before sending).

Also the wire's quantisation as functions: :func:`on_the_wire_state` and
:func:`on_the_wire_command` through the codec's records, and :func:`joints_on_the_wire` and
:func:`rates_on_the_wire` computing the same values directly, for one arm or a batch's runs,
which the in-process simulations use: they see exactly the values a controller and a plant see
over CAN, and a lockstep co-simulation gives bit-identical results.
"""

from __future__ import annotations

from typing import Any

from protocol.codec import COUNTER_MODULO, WIRE, quantised
from protocol.errors import (
    ConfigError,
    NoWayRoundError,
    PathOutsideWorkspaceError,
    PlanTooFastError,
    UnreachableWaypointError,
    WaypointInObstacleError,
    WaypointNearLimitError,
    WaypointNearObstacleError,
)
from protocol.ops import Ops, Real

Joints = tuple[float, float, float]

COMMAND = WIRE["JointVelocityCommand"]
STATE = (WIRE["JointState1"], WIRE["JointState2"], WIRE["JointState3"])
STATE_IDS = tuple(codec.frame_id for codec in STATE)
STEP = WIRE["StepSync"]
STOP = WIRE["EmergencyStop"]
NODE_COMMAND = WIRE["NodeCommand"]
CONTROLLER_STATUS = WIRE["ControllerStatus"]
PLANT_STATUS = WIRE["PlantStatus"]
CONTROLLER_ANSWER = WIRE["ControllerAnswer"]
COORDINATION = WIRE["ControllerCoordination"]
RUN_STATUS = WIRE["ControllerRun"]
SCENARIO_UPLOAD = WIRE.isotp["ScenarioUpload"]
SCENARIO_DOWNLOAD = WIRE.isotp["ScenarioDownload"]
WORLD_UPLOAD = WIRE.isotp["WorldUpload"]
WORLD_FLOW = WIRE.isotp["WorldFlow"]

NodeState: Any = WIRE.enum("NodeState", ("ControllerStatus", "State"), ("PlantStatus", "State"))
NodeId: Any = WIRE.enum("NodeId", ("NodeCommand", "Target"), ("NodeCommand", "Source"))
Request: Any = WIRE.enum("Request", ("NodeCommand", "Command"))
Answered: Any = WIRE.enum("Answered", ("ControllerAnswer", "Request"))
Reason: Any = WIRE.enum("Reason", ("ControllerAnswer", "Reason"))
Behaviour: Any = WIRE.enum("Behaviour", ("ControllerRun", "Behaviour"))
Side: Any = WIRE.enum("Side", ("ControllerCoordination", "Side"))
ControllerFault: Any = WIRE.enum("ControllerFault", ("ControllerStatus", "FaultCode"), flag=True)
ControllerFlag: Any = WIRE.enum("ControllerFlag", ("ControllerStatus", "Flags"), flag=True)
PlantFault: Any = WIRE.enum("PlantFault", ("PlantStatus", "FaultCode"), flag=True)
PlantFlag: Any = WIRE.enum("PlantFlag", ("PlantStatus", "Flags"), flag=True)


_REASONS: tuple[tuple[type[ConfigError], Any], ...] = (
    (UnreachableWaypointError, Reason.UNREACHABLE),
    (WaypointInObstacleError, Reason.INSIDE_OBSTACLE),
    (PathOutsideWorkspaceError, Reason.PATH_LEAVES_WORKSPACE),
    (NoWayRoundError, Reason.NO_WAY_ROUND),
    (WaypointNearObstacleError, Reason.NEAR_OBSTACLE),
    (WaypointNearLimitError, Reason.NEAR_JOINT_LIMIT),
    (PlanTooFastError, Reason.TOO_FAST),
)
"""A task's error and the ControllerAnswer reason it is refused with."""


def reason_of(error: ConfigError) -> Any:
    """The ControllerAnswer reason for a task's error (``bad_field`` for any other)."""
    return next((reason for kind, reason in _REASONS if isinstance(error, kind)), Reason.BAD_FIELD)


class Counter:
    """The alive counter of one frame ID: +1 mod 16 per frame sent."""

    __slots__ = ("value",)

    def __init__(self) -> None:
        self.value = COUNTER_MODULO - 1

    def next(self) -> int:
        self.value = (self.value + 1) % COUNTER_MODULO
        return self.value


class JointStateParts:
    """Puts JointState1-3 back together: the three frames of one plant step share one alive
    counter and one CommandEcho; a set that is not complete, or not consistent, is dropped."""

    def __init__(self) -> None:
        self._parts: dict[int, list[Any]] = {}

    def add(self, joint: int, counter: int, record: Any) -> tuple[Joints, Joints, int] | None:
        """``(position, velocity, echo)`` once all three frames of ``counter`` are in."""
        parts = self._parts.setdefault(counter, [None, None, None])
        parts[joint] = record
        if any(part is None for part in parts):
            if len(self._parts) > 4:  # incomplete sets of lost frames: keep only recent ones
                for old in list(self._parts)[:-2]:
                    del self._parts[old]
            return None
        self._parts.clear()
        first, second, third = parts
        if not first.CommandEcho == second.CommandEcho == third.CommandEcho:
            return None
        return (
            (first.Position, second.Position, third.Position),
            (first.Velocity, second.Velocity, third.Velocity),
            first.CommandEcho,
        )

    def clear(self) -> None:
        self._parts.clear()


def command_record(rates: Joints, enable: bool = True) -> Any:
    """The JointVelocityCommand record of joint ``rates`` (rad/s, rad/s, m/s)."""
    return COMMAND.Record(
        Enable=int(enable), Theta1Rate=rates[0], Theta2Rate=rates[1], D3Rate=rates[2]
    )


def _wire_of(specs: tuple[Any, ...]) -> tuple[tuple[float, float, int, int], ...]:
    return tuple((spec.scale, spec.offset, *spec.raw_range) for spec in specs)


_POSITION = _wire_of(tuple(codec.spec["Position"] for codec in STATE))
_VELOCITY = _wire_of(tuple(codec.spec["Velocity"] for codec in STATE))
_RATES = _wire_of(tuple(COMMAND.spec[name] for name in ("Theta1Rate", "Theta2Rate", "D3Rate")))


def joints_on_the_wire(
    ops: Ops, position: tuple[Real, Real, Real], velocity: tuple[Real, Real, Real]
) -> tuple[tuple[Real, Real, Real], tuple[Real, Real, Real]]:
    """:func:`on_the_wire_state` for values the codec's range checks would pass (the plant
    keeps positions within the joint limits and speeds within the speed limits, which
    ``check_robot_fits_wire`` keeps within the wire's ranges): one arm, or a batch's runs."""
    return _on_the_wire(ops, position, _POSITION), _on_the_wire(ops, velocity, _VELOCITY)


def rates_on_the_wire(ops: Ops, rates: tuple[Real, Real, Real]) -> tuple[Real, Real, Real]:
    """:func:`on_the_wire_command` for commands within the speed limits (the law keeps them
    there): one arm, or a batch's runs."""
    return _on_the_wire(ops, rates, _RATES)


def _on_the_wire(
    ops: Ops, values: tuple[Real, Real, Real], wires: tuple[tuple[float, float, int, int], ...]
) -> tuple[Real, Real, Real]:
    first, second, third = wires
    return (
        quantised(ops, values[0], *first),
        quantised(ops, values[1], *second),
        quantised(ops, values[2], *third),
    )


def on_the_wire_command(rates: Joints) -> Joints:
    """The command the plant decodes for ``rates``."""
    command = COMMAND.quantise(command_record(rates))
    return (command.Theta1Rate, command.Theta2Rate, command.D3Rate)


def on_the_wire_state(position: Joints, velocity: Joints) -> tuple[Joints, Joints]:
    """The joint state the controller decodes for the plant's exact state."""
    decoded = [
        codec.quantise(codec.Record(CommandEcho=0, Position=p, Velocity=v))
        for codec, p, v in zip(STATE, position, velocity, strict=True)
    ]
    return (
        (decoded[0].Position, decoded[1].Position, decoded[2].Position),
        (decoded[0].Velocity, decoded[1].Velocity, decoded[2].Velocity),
    )
