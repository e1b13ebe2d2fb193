"""What the bridge makes of the frames it hears (pure: records in, payloads and events out),
every payload checked against its key's JSON Schema."""

from __future__ import annotations

from typing import Any

import jsonschema
import pytest

from bridge.view import ALIVE_FOR, Event, RobotView
from protocol.keys import schema
from protocol.kinematics import forward
from protocol.messages import (
    CONTROLLER_STATUS,
    COORDINATION,
    PLANT_STATUS,
    RUN_STATUS,
    Behaviour,
    ControllerFault,
    ControllerFlag,
    NodeState,
    PlantFlag,
    Side,
)
from protocol.scenario import load_scenario

ROBOT = load_scenario("reference").robot


class Bus:
    """Feeds a view the status-rate frames in the order a controller sends them."""

    def __init__(self) -> None:
        self.view = RobotView(ROBOT)
        self.now = 1000.0
        self.events: list[Event] = []

    def controller(
        self, state: NodeState, *, waypoint: int = 0, progress: int = 0, flags: int = 2,
        faults: int = 0, behaviour: Behaviour = Behaviour.TRACKING,
    ) -> list[str]:  # fmt: skip
        """One status period of the controller: coordination, run, status (that order)."""
        self.now += 0.1
        coordination = COORDINATION.Record(
            Side=Side.LEFT, KT=0.25, KC=0.75, Beta=1.5, DLeft=0.05, DRight=0.12
        )
        run = RUN_STATUS.Record(
            Behaviour=behaviour, Holds=0, Waypoint=waypoint, Progress=progress, LatenessMax=40
        )
        status = CONTROLLER_STATUS.Record(
            State=state, FaultCode=faults, Flags=flags, BadFrames=0, Extra=3
        )
        before = len(self.events)
        for codec, record in (
            (COORDINATION, coordination),
            (RUN_STATUS, run),
            (CONTROLLER_STATUS, status),
        ):
            self.events += self.view.on_frame(codec, record, self.now)
        return [name for name, _ in self.events[before:]]

    def plant(self, flags: int = 0) -> list[str]:
        record = PLANT_STATUS.Record(
            State=NodeState.RUNNING, FaultCode=0, Flags=flags, BadFrames=1, World=4, Extra=77
        )
        return [name for name, _ in self.view.on_frame(PLANT_STATUS, record, self.now)]


def valid(name: str, payload: dict[str, Any] | None, seq: int = 0) -> None:
    assert payload is not None
    jsonschema.validate(payload | {"seq": seq}, schema(name))


def test_a_run_reads_as_events_in_order_started_waypoints_finished() -> None:
    bus = Bus()
    assert bus.controller(NodeState.READY) == []
    # The run frame of the tick that started the run comes before the status saying so:
    assert bus.controller(NodeState.RUNNING, waypoint=1, progress=1) == [
        "run_started",
        "waypoint_reached",
    ]
    assert bus.controller(NodeState.RUNNING, waypoint=3, progress=60) == ["waypoint_reached"] * 2
    assert bus.controller(NodeState.HOLD, waypoint=3, progress=61) == ["hold"]
    assert bus.controller(NodeState.RUNNING, waypoint=3, progress=62) == ["resumed"]
    assert bus.controller(NodeState.READY, waypoint=4, progress=100) == [
        "waypoint_reached",
        "run_finished",
    ]
    assert [detail["index"] for name, detail in bus.events if name == "waypoint_reached"] == [
        0,
        1,
        2,
        3,
    ]
    # The next run counts its waypoints from the start again:
    assert bus.controller(NodeState.RUNNING, waypoint=0, progress=0) == ["run_started"]
    assert bus.controller(NodeState.READY, waypoint=1, progress=20) == [
        "waypoint_reached",
        "run_stopped",
    ]
    for name, detail in bus.events:
        valid("events", {"t": 0.0, "event": name, "detail": detail})


def test_a_run_whose_first_status_is_a_hold_still_reads_as_started() -> None:
    """A controller that holds in its first ticks (the plant's state late, on a loaded
    machine) may say HOLD before it ever says RUNNING: the run has started all the same
    (CI saw a run with no run_started)."""
    bus = Bus()
    assert bus.controller(NodeState.READY) == []
    assert bus.controller(NodeState.HOLD, waypoint=0, progress=0) == ["run_started", "hold"]
    assert bus.controller(NodeState.RUNNING, waypoint=1, progress=5) == [
        "waypoint_reached",  # the run frame comes before the status
        "resumed",
    ]
    assert bus.controller(NodeState.READY, waypoint=1, progress=100) == ["run_finished"]


def test_a_bridge_that_joins_mid_run_reports_nothing_of_the_past() -> None:
    bus = Bus()
    assert bus.controller(NodeState.RUNNING, waypoint=2, progress=40) == []
    assert bus.controller(NodeState.RUNNING, waypoint=3, progress=70) == ["waypoint_reached"]
    assert bus.events[-1][1] == {"index": 2}


@pytest.mark.parametrize(
    ("state", "faults", "event"),
    [
        (NodeState.FAULT, ControllerFault.STALE_STATE, "fault"),
        (NodeState.ESTOP, ControllerFault.ESTOP, "estop"),
    ],
)
def test_faults_and_estops_are_events_and_a_reset_ends_them(
    state: NodeState, faults: int, event: str
) -> None:
    bus = Bus()
    bus.controller(NodeState.READY)
    assert bus.controller(state, faults=faults) == [event]
    assert bus.view.controller.faults == [ControllerFault(faults).name.lower()]
    assert bus.controller(NodeState.READY) == ["reset"]


def test_a_mode_change_is_an_event() -> None:
    bus = Bus()
    bus.controller(NodeState.READY, flags=ControllerFlag.FUZZY)
    assert bus.controller(NodeState.READY, flags=0) == ["mode_changed"]
    assert bus.events[-1][1] == {"mode": "conventional"}
    assert bus.view.mode == "conventional"


def test_a_collision_is_an_event_once() -> None:
    bus = Bus()
    assert bus.plant(PlantFlag.COLLISION | PlantFlag.D3_AT_STOP) == ["collision"]
    assert bus.plant(PlantFlag.COLLISION) == []
    assert bus.view.at_stop == []
    assert bus.plant(PlantFlag.THETA2_AT_STOP) == []
    assert bus.view.at_stop == ["theta2"]


def test_payloads_fit_their_schemas_and_say_what_the_frames_said() -> None:
    bus = Bus()
    assert bus.view.joints_payload() is None and bus.view.coordination_payload() is None
    position, velocity = (0.1, 0.8, 0.05), (0.01, -0.02, 0.0)
    bus.view.on_joint_state(position, velocity, 1234.5)
    bus.controller(NodeState.RUNNING, behaviour=Behaviour.BLENDED)
    bus.plant()
    joints = bus.view.joints_payload()
    valid("joints", joints)
    assert joints == {"t": 1234.5, "position": list(position), "velocity": list(velocity)}
    tcp = bus.view.tcp_payload()
    valid("tcp", tcp)
    assert (tcp["x"], tcp["y"], tcp["z"]) == pytest.approx(forward(ROBOT, *position))
    coordination = bus.view.coordination_payload()
    valid("coordination", coordination)
    assert coordination is not None
    assert (coordination["k_t"], coordination["k_c"], coordination["side"]) == (0.25, 0.75, "left")
    assert coordination["behaviour"] == "blended"
    bridge = {"frames": 9, "bad_frames": 0, "published": {}, "dropped": {}, "rates_hz": {}}
    status = bus.view.status_payload(bus.now, bridge)
    valid("status", status)
    assert status["controller"]["state"] == "running" and status["plant"]["steps"] == 77
    assert status["plant"]["world"] == 4


def test_a_node_whose_status_stops_counts_as_dead() -> None:
    bus = Bus()
    bus.controller(NodeState.READY)
    assert bus.view.controller.alive(bus.now + ALIVE_FOR)
    assert not bus.view.controller.alive(bus.now + ALIVE_FOR + 0.01)
    assert not bus.view.plant.alive(bus.now)
