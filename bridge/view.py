"""What the bridge knows of the robot, from the frames it hears: pure, no bus, no Zenoh.

:class:`RobotView` takes decoded frames (the joint state, the controller's status,
coordination and run frames, the plant's status) and keeps the latest of each as the JSON
payloads of the key space (``protocol/keys.py``), and turns changes into events: a run
started, finished or stopped, a waypoint reached, a hold and its end, the mode changed, a
fault, an e-stop, a collision, a reset. A node counts as alive while its status frames keep
coming (:data:`ALIVE_FOR`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from protocol.codec import MessageCodec
from protocol.config import RobotConfig
from protocol.kinematics import forward
from protocol.messages import (
    CONTROLLER_STATUS,
    COORDINATION,
    PLANT_STATUS,
    RUN_STATUS,
    STATE,
    Behaviour,
    ControllerFault,
    ControllerFlag,
    Joints,
    NodeState,
    PlantFault,
    PlantFlag,
    Side,
)

VIEWED = (*STATE, CONTROLLER_STATUS, PLANT_STATUS, COORDINATION, RUN_STATUS)
"""The frames a :class:`RobotView` is built from (the bridge and the recorder listen to them)."""

ALIVE_FOR = 0.5
"""s after its last status frame (sent at 10 Hz) a node still counts as alive."""

RUNNING = ("running", "hold")
"""Controller states in which a run is under way."""

Event = tuple[str, dict[str, Any]]
"""``(event, detail)`` as published on ``events``."""


@dataclass
class NodeView:
    """The latest status frame of one node."""

    state: str = "init"
    faults: list[str] = field(default_factory=list)
    bad_frames: int = 0
    last_seen: float = -float("inf")

    def alive(self, now: float) -> bool:
        return now - self.last_seen <= ALIVE_FOR


class RobotView:
    """The latest state of the robot as heard on the bus, and the events between."""

    def __init__(self, robot: RobotConfig) -> None:
        self.robot = robot
        self.joints: tuple[Joints, Joints] | None = None
        self.joints_time = 0.0
        self.controller = NodeView()
        self.plant = NodeView()
        self.mode = "fuzzy"
        self.clock = "realtime"
        self.deadline_misses = 0
        self.lateness_max_us = 0
        self.holds = 0
        self.waypoints_reached = 0
        self.progress = 0
        self.collision = False
        self.at_stop: list[str] = []
        self.steps = 0
        self.world = 0
        self.coordination: dict[str, Any] | None = None
        self.coordination_time = 0.0
        self._behaviour = "none"
        self._reached_on_bus = 0

    # --- frames in -----------------------------------------------------------------------

    def on_joint_state(self, position: Joints, velocity: Joints, received: float) -> None:
        self.joints = (position, velocity)
        self.joints_time = received

    def on_frame(self, codec: MessageCodec, record: Any, received: float) -> list[Event]:
        """Take one decoded status-rate frame; the events it brings."""
        if codec is CONTROLLER_STATUS:
            return self._on_controller(record, received)
        if codec is PLANT_STATUS:
            return self._on_plant(record, received)
        if codec is RUN_STATUS:
            return self._on_run(record)
        if codec is COORDINATION:
            self.coordination = {
                "k_t": record.KT,
                "k_c": record.KC,
                "d_left": record.DLeft,
                "d_right": record.DRight,
                "beta": record.Beta,
                "side": Side(record.Side).name.lower(),
                "behaviour": self._behaviour,
            }
            self.coordination_time = received
        return []

    def _on_controller(self, record: Any, received: float) -> list[Event]:
        events: list[Event] = []
        before = self.controller.state
        state = NodeState(record.State).name.lower()
        faults = [flag.name.lower() for flag in ControllerFault if flag & record.FaultCode]
        mode = "fuzzy" if record.Flags & ControllerFlag.FUZZY else "conventional"
        if self.controller.last_seen == -float("inf"):
            # first sight (the bridge joined now): what happened before is not news
            self.waypoints_reached = self._reached_on_bus
        else:
            if self.controller.alive(received) and mode != self.mode:
                events.append(("mode_changed", {"mode": mode}))
            events += _transition(before, state, faults, self.progress)
            if state in RUNNING:
                events += self._waypoints(self._reached_on_bus)
        self.controller = NodeView(state, faults, record.BadFrames, received)
        self.mode = mode
        self.clock = "lockstep" if record.Flags & ControllerFlag.LOCKSTEP else "realtime"
        self.deadline_misses = record.Extra
        return events

    def _on_plant(self, record: Any, received: float) -> list[Event]:
        faults = [flag.name.lower() for flag in PlantFault if flag & record.FaultCode]
        collision = bool(record.Flags & PlantFlag.COLLISION)
        events: list[Event] = []
        if collision and not self.collision:
            events.append(("collision", {"node": "plant"}))
        self.collision = collision
        self.at_stop = [
            flag.name.lower().removesuffix("_at_stop")
            for flag in PlantFlag
            if flag != PlantFlag.COLLISION and flag & record.Flags
        ]
        self.plant = NodeView(
            NodeState(record.State).name.lower(), faults, record.BadFrames, received
        )
        self.steps = record.Extra
        self.world = record.World
        return events

    def _on_run(self, record: Any) -> list[Event]:
        events: list[Event] = []
        reached = self._reached_on_bus = record.Waypoint
        if self.controller.state in RUNNING:
            events += self._waypoints(reached)
        elif reached < self.waypoints_reached:
            # a new run: a run frame goes out just before its status frame, so the waypoints
            # of a run that has just started wait for the status that says so (in order)
            self.waypoints_reached = 0
        self.progress = record.Progress
        self.holds = record.Holds
        self.lateness_max_us = record.LatenessMax
        self._behaviour = Behaviour(record.Behaviour).name.lower()
        if self.coordination is not None:
            self.coordination["behaviour"] = self._behaviour
        return events

    def _waypoints(self, reached: int) -> list[Event]:
        """The waypoints reached since the last look, one event each."""
        events: list[Event] = [
            ("waypoint_reached", {"index": index})
            for index in range(self.waypoints_reached, reached)
        ]
        self.waypoints_reached = max(self.waypoints_reached, reached)
        return events

    # --- payloads out --------------------------------------------------------------------

    def joints_payload(self) -> dict[str, Any] | None:
        if self.joints is None:
            return None
        position, velocity = self.joints
        return {"t": self.joints_time, "position": list(position), "velocity": list(velocity)}

    def tcp_payload(self) -> dict[str, Any] | None:
        if self.joints is None:
            return None
        x, y, z = forward(self.robot, *self.joints[0])
        return {"t": self.joints_time, "x": x, "y": y, "z": z}

    def coordination_payload(self) -> dict[str, Any] | None:
        if self.coordination is None:
            return None
        return {"t": self.coordination_time} | self.coordination

    def status_payload(self, now: float, bridge: dict[str, Any]) -> dict[str, Any]:
        controller, plant = self.controller, self.plant
        return {
            "t": now,
            "controller": {
                "alive": controller.alive(now),
                "state": controller.state,
                "faults": controller.faults,
                "mode": self.mode,
                "clock": self.clock,
                "bad_frames": controller.bad_frames,
                "deadline_misses": self.deadline_misses,
                "lateness_max_us": self.lateness_max_us,
                "holds": self.holds,
                "waypoints_reached": self.waypoints_reached,
                "progress": self.progress,
            },
            "plant": {
                "alive": plant.alive(now),
                "state": plant.state,
                "faults": plant.faults,
                "bad_frames": plant.bad_frames,
                "collision": self.collision,
                "at_stop": self.at_stop,
                "steps": self.steps,
                "world": self.world,
            },
            "bridge": bridge,
        }


def _transition(before: str, after: str, faults: list[str], progress: int) -> list[Event]:
    """The events of the controller's state going from ``before`` to ``after``."""
    if before == after:
        return []
    started: list[Event] = []
    if after in RUNNING and before not in RUNNING:  # a run may say HOLD before RUNNING
        started = [("run_started", {})]
    if after == "running" and before == "hold":
        return [("resumed", {})]
    if after == "hold":
        return [*started, ("hold", {})]
    if after == "running":
        return started
    if after == "fault":
        return [("fault", {"faults": faults})]
    if after == "estop":
        return [("estop", {})]
    if after == "ready" and before in RUNNING:
        return [("run_finished" if progress >= 100 else "run_stopped", {"progress": progress})]
    if after == "ready" and before in ("fault", "estop"):
        return [("reset", {})]
    return []
