"""Fuzzing the ISO-TP task upload of a real controller service (``controller/service.py``).

A :class:`ServiceNode` on python-can's ``virtual`` bus, stepped tick by tick on an injected
clock (as ``tests/controller/test_service.py`` does), gets tasks as ISO-TP transfers on
ScenarioUpload (0x600): well-formed ones from can-isotp on the test's side carrying valid,
broken or random task JSON, and hand-built frames cut short, reordered, repeated, dropped,
edited, interleaved, too long for one transfer, with a wrong length, or marked extended,
remote, error or FD. Between them the test asks it to run, stop, reset and describe.

Properties, after every step: the node never raises; every transfer it completes gets
exactly one ControllerAnswer, the one its rules give; the task in force changes only when a
valid task is accepted; and every command frame it sends while not running a task is zero
with Enable 0 (the robot does not move).
"""

from __future__ import annotations

import itertools
import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import can
import isotp.tools
import pytest
from fuzzing import deep, fuzz, json_texts, json_values, mutated, mutated_json
from hypothesis import example, given
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule, run_state_machine_as_test
from support import FakeClock, frame

from controller.planner import check_plan
from controller.service import ServiceNode
from protocol.codec import WIRE
from protocol.errors import ConfigError
from protocol.isotp_link import MAX_PAYLOAD, IsoTpLink, seal
from protocol.messages import (
    COMMAND,
    CONTROLLER_ANSWER,
    NODE_COMMAND,
    SCENARIO_DOWNLOAD,
    SCENARIO_UPLOAD,
    STATE,
    Answered,
    NodeId,
    NodeState,
    Reason,
    Request,
    reason_of,
)
from protocol.scenario import Scenario, load_scenario, parse_task, read_task, task_document

pytestmark = pytest.mark.fuzz

REFERENCE = load_scenario("reference")
BASE = Scenario("service", (), None)
TASK = task_document(REFERENCE)
UPLOAD, DOWNLOAD = SCENARIO_UPLOAD.frame_id, SCENARIO_DOWNLOAD.frame_id
_channels = itertools.count()
CLOCK = FakeClock()
"""The one clock of every machine, and of can-isotp's timers (see ``isotp_on_the_clock``):
a transfer times out after a second of the test's time, never of the machine's."""


# --- what is sent ----------------------------------------------------------------------------


REFUSED = {
    "unreachable": (1, {"x": 2.0}),  # each answered with its own reason
    "inside the obstacle": (1, {"x": 0.455, "y": -0.01}),
    "time going back": (2, {"t": 0.5}),
}


@st.composite
def task_payloads(draw: st.DrawFn) -> bytes:
    """A transfer's payload: a task with its ticket, valid, one the rules refuse, edited, or
    any JSON at all."""
    ticket = draw(st.one_of(st.integers(0, 255), json_values), label="ticket")
    moved = draw(st.sampled_from([0.0, -0.02, 0.01]), label="moved by")
    waypoints = [w | {"x": w["x"] + moved} for w in TASK["waypoints"]]
    refused = draw(st.sampled_from([None, *REFUSED]), label="refused as")
    if refused is not None:
        index, change = REFUSED[refused]
        waypoints[index] = waypoints[index] | change
    valid = TASK | {"ticket": ticket, "waypoints": waypoints}
    documents = st.one_of(st.just(valid), mutated_json(valid), json_values)
    return draw(json_texts(documents))[:MAX_PAYLOAD]


def segments(payload: bytes) -> list[bytes]:
    """ISO-TP frames (normal addressing, classic CAN, 0xCC padding) carrying ``payload`` (a
    transfer: :func:`seal` it for its CRC)."""
    if len(payload) <= 7:
        return [bytes([len(payload)]) + payload + b"\xcc" * (7 - len(payload))]
    if len(payload) <= 4095:
        head = bytes([0x10 | len(payload) >> 8, len(payload) & 0xFF]) + payload[:6]
        rest = payload[6:]
    else:  # the 32-bit length escape: more than one transfer on classic CAN carries
        head = bytes([0x10, 0x00]) + len(payload).to_bytes(4, "big") + payload[:2]
        rest = payload[2:]
    frames = [head]
    for sequence, start in enumerate(range(0, len(rest), 7), start=1):
        chunk = rest[start : start + 7]
        frames.append(bytes([0x20 | sequence & 0x0F]) + chunk + b"\xcc" * (7 - len(chunk)))
    return frames


@dataclass(frozen=True)
class Raw:
    """A hand-built frame on ScenarioUpload, maybe with odd flags."""

    data: bytes
    flags: frozenset[str] = frozenset()


@st.composite
def raw_transfers(draw: st.DrawFn) -> list[Raw]:
    """The frames of a transfer, then broken as a transfer: cut short, reordered, repeated,
    dropped, edited, interleaved with another, too long, with a wrong length, or flagged."""
    payload = draw(task_payloads(), label="payload")
    if draw(st.integers(0, 9), label="oversize") == 0:
        payload = payload * (MAX_PAYLOAD // max(len(payload), 1) + 1)
    frames = [Raw(data) for data in segments(seal(payload))]
    for _ in range(draw(st.integers(0, 3), label="breaks")):
        kind = draw(
            st.sampled_from(
                ["cut", "drop", "repeat", "swap", "edit", "length", "interleave", "flag"]
            )
        )
        at = draw(st.integers(0, len(frames) - 1))
        if kind == "cut":
            frames = frames[: at + 1]
        elif kind == "drop" and len(frames) > 1:
            del frames[at]
        elif kind == "repeat":
            frames.insert(at, frames[at])
        elif kind == "swap" and at + 1 < len(frames):
            frames[at], frames[at + 1] = frames[at + 1], frames[at]
        elif kind == "edit":
            frames[at] = Raw(draw(mutated(frames[at].data, max_edits=2))[:64], frames[at].flags)
        elif kind == "length":
            claimed = draw(st.sampled_from([0, 1, 7, 8, 4095, 4096, 2**32 - 1]))
            if claimed <= 4095:
                head = bytes([0x10 | claimed >> 8, claimed & 0xFF])
            else:
                head = bytes([0x10, 0x00]) + claimed.to_bytes(4, "big")
            frames[0] = Raw(head + frames[0].data[len(head) :], frames[0].flags)
        elif kind == "interleave":
            other = segments(seal(draw(task_payloads(), label="other payload")))
            frames[at:at] = [Raw(data) for data in other[: draw(st.integers(1, len(other)))]]
        else:
            flag = draw(st.sampled_from(["extended", "remote", "error", "fd"]))
            frames[at] = Raw(frames[at].data, frames[at].flags | {flag})
    return frames[:700]


# --- the machine -----------------------------------------------------------------------------


@dataclass
class Delivered:
    """A transfer the service completed, and what the service was when it took it."""

    payload: bytes
    state: Any
    expected: tuple[int, Any, Scenario | None] | None = None
    """What the controller's rules make of it: ``(ticket, reason, task)``."""

    def outcome(self) -> tuple[int, Any, Scenario | None]:
        if self.expected is None:
            self.expected = expected(self)
        return self.expected


class ServiceUploads(RuleBasedStateMachine):
    """A controller service, a plant that sends its joint state, and an operator that sends
    tasks and requests: the test's own ISO-TP end and raw frames."""

    def __init__(self) -> None:
        super().__init__()
        channel = f"fuzz-service-{next(_channels)}"
        # Every frame keeps the time the test stamps it with (the test's clock): the E2E
        # checks and the timeouts see the same times however slow the machine is.
        self.node_bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        self.bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        self.clock = CLOCK
        self.clock.now = 100.0
        self.service = ServiceNode(
            self.node_bus, BASE, clock=self.clock, sleep=lambda seconds: None
        )
        self.tool = IsoTpLink(self.bus.send, UPLOAD, DOWNLOAD)
        self.delivered: list[Delivered] = []
        self.checked = 0
        self.task: Scenario | None = None
        """The task in force by the controller's rules, applied to the transfers in turn."""
        self.answers: list[Any] = []
        self.commands_called: list[tuple[Any, tuple[float, ...], bool]] = []
        self.command_frames: list[Any] = []
        self.state_counter = 0
        self.ticket = 0
        self._spy()

    def _spy(self) -> None:
        """Record the transfers the service completes (and its state when it takes them),
        and the state it is in each time it sends a command."""
        service = self.service
        poll = service.transfers.poll
        send_command = service._send_command

        def polled() -> list[bytes]:
            payloads = poll()
            for payload in payloads:
                self.delivered.append(Delivered(payload, service.node_state))
            return payloads

        def commanded(rates: tuple[float, float, float], enable: bool) -> int:
            self.commands_called.append((service.node_state, rates, enable))
            return send_command(rates, enable)

        service.transfers.poll = polled  # type: ignore[method-assign]
        service._send_command = commanded  # type: ignore[method-assign]

    def teardown(self) -> None:
        self.node_bus.shutdown()
        self.bus.shutdown()

    # --- the test's side of the bus ----------------------------------------------------------

    def tick(self, count: int = 1, state: bool = True) -> None:
        """``count`` control periods: the plant's joint state, the service's tick (which must
        not raise), then what the service sent, read and checked."""
        for _ in range(count):
            if state:
                self.send_state()
            self.clock.now += self.service.period
            self.service.realtime_tick(self.clock.now)
            self.read_bus()
            self.check_answers()

    def send_state(self) -> None:
        position = REFERENCE.initial_joints()
        for codec, joint in zip(STATE, position, strict=True):
            record = codec.Record(CommandEcho=0, Position=joint, Velocity=0.0)
            self.send(frame(codec.frame_id, codec.encode(record, self.state_counter)))
        self.state_counter = (self.state_counter + 1) % 16

    def read_bus(self) -> None:
        while (message := self.bus.recv(timeout=0.0)) is not None:
            if message.arbitration_id == DOWNLOAD:
                self.tool.feed(message)
            elif message.arbitration_id == CONTROLLER_ANSWER.frame_id:
                self.answers.append(WIRE.decode(message.arbitration_id, message.data)[2])
            elif message.arbitration_id == COMMAND.frame_id:
                self.command_frames.append(WIRE.decode(message.arbitration_id, message.data)[2])
        self.tool.poll()

    def send(self, message: can.Message) -> None:
        message.timestamp = self.clock.now
        self.bus.send(message)

    def send_raw(self, raw: Raw) -> None:
        self.send(
            can.Message(
                arbitration_id=UPLOAD,
                data=raw.data,
                dlc=len(raw.data) if "remote" not in raw.flags else 8,
                is_extended_id="extended" in raw.flags,
                is_remote_frame="remote" in raw.flags,
                is_error_frame="error" in raw.flags,
                is_fd="fd" in raw.flags,
                check=False,
            )
        )

    # --- rules -----------------------------------------------------------------------------

    @rule(payload=task_payloads())
    def upload(self, payload: bytes) -> None:
        """A well-formed transfer (can-isotp's segmentation and flow control): it completes,
        and it is answered."""
        payload = payload or b" "  # ISO-TP carries no empty transfer
        self.settle()
        before = len(self.delivered)
        self.tool.send(payload)
        for _ in range(40):
            self.tool.poll()
            self.tick()
            if not self.tool.sending and len(self.delivered) > before:
                break
        assert [d.payload for d in self.delivered[before:]] == [payload], (
            f"transfer lost: tool sending {self.tool.sending}, tool state "
            f"{self.tool._stack.tx_state}/{self.tool._stack.rx_state}, service "
            f"{self.service.transfers._stack.tx_state}/{self.service.transfers._stack.rx_state}, "
            f"errors {self.service.transfers.errors}, clock {self.clock.now}, "
            f"queued {len(self.service.transfers._inbox)}"
        )

    @rule(frames=raw_transfers(), one_a_tick=st.booleans(), ticks=st.integers(1, 4))
    def raw_upload(self, frames: list[Raw], one_a_tick: bool, ticks: int) -> None:
        for raw in frames:
            self.send_raw(raw)
            if one_a_tick:
                self.tick()
        self.tick(ticks)
        self.settle()

    def settle(self) -> None:
        """Tick until the service has read every frame sent (it reads at most DRAIN_LIMIT a
        tick): a frame of an old transfer must not land in the middle of the next one."""
        for _ in range(20):
            if self.node_bus.queue.empty():  # type: ignore[attr-defined]
                break
            self.tick()
        self.tick()

    @rule(request=st.sampled_from([Request.RUN, Request.STOP, Request.RESET, Request.DESCRIBE]))
    def request(self, request: Any) -> None:
        self.ticket = self.ticket % 255 + 1
        record = NODE_COMMAND.Record(
            Command=request, Target=NodeId.CONTROLLER, Source=NodeId.OPERATOR, Ticket=self.ticket
        )
        self.send(frame(NODE_COMMAND.frame_id, NODE_COMMAND.encode(record, self.ticket % 16)))
        self.tick(2)

    @rule()
    def silence(self) -> None:
        """Nothing on the bus for longer than ISO-TP waits for a frame: a transfer cut short
        times out (and the service, without a joint state, holds or faults)."""
        self.clock.now += 1.5
        self.tick()

    @rule(ticks=st.sampled_from([1, 2, 5, 60]), plant=st.booleans())
    def time_passes(self, ticks: int, plant: bool) -> None:
        """Ticks with or without the plant's joint state (60 without: a hold, then a fault
        after the comms-loss timeout)."""
        self.tick(ticks, state=plant)

    # --- properties --------------------------------------------------------------------------

    def check_answers(self) -> None:
        """Each completed transfer got one answer, the one the controller's rules give, and
        the task changed only if it was accepted."""
        answers = [a for a in self.answers if a.Request == Answered.SCENARIO]
        assert len(answers) == len(self.delivered), "a completed transfer without one answer"
        for delivered, answer in zip(
            self.delivered[self.checked :], answers[self.checked :], strict=True
        ):
            ticket, reason, task = delivered.outcome()
            assert (answer.Ticket, answer.Reason) == (ticket, reason), delivered.payload[:200]
            assert answer.Accepted == (reason == Reason.NONE)
            if reason == Reason.NONE:
                assert task is not None and task.waypoints
                self.task = task
        self.checked = len(self.delivered)
        assert self.service.task == self.task, "the task in force is not the last one accepted"

    @invariant()
    def idle_means_still(self) -> None:
        """Commands are zero with Enable 0 unless a run of an accepted task goes on."""
        assert len(self.command_frames) == len(self.commands_called)
        for (state, rates, enable), sent in zip(
            self.commands_called, self.command_frames, strict=True
        ):
            if state is not NodeState.RUNNING:
                assert not enable and rates == (0.0, 0.0, 0.0), (state, rates, enable)
                assert sent.Enable == 0
                assert (sent.Theta1Rate, sent.Theta2Rate, sent.D3Rate) == (0.0, 0.0, 0.0)
        if self.service.node_state is NodeState.RUNNING:
            assert self.service.task is not None


def expected(delivered: Delivered) -> tuple[int, Any, Scenario | None]:
    """The controller's rules, written out: ``(ticket, reason, task)`` for a transfer."""
    try:
        ticket, document = read_task(delivered.payload)
    except ConfigError:
        return 0, Reason.MALFORMED, None
    if delivered.state in (NodeState.RUNNING, NodeState.HOLD):
        return ticket, Reason.BUSY, None
    try:
        task = parse_task(document, BASE)
        check_plan(task)
    except ConfigError as error:
        return ticket, reason_of(error), None
    return ticket, Reason.NONE, task


@pytest.fixture
def isotp_on_the_clock(monkeypatch: pytest.MonkeyPatch) -> None:
    """can-isotp's timers read the test's clock (they read ``time.perf_counter_ns``)."""
    monkeypatch.setattr(
        isotp.tools, "time", SimpleNamespace(perf_counter_ns=lambda: round(CLOCK.now * 1e9))
    )


@pytest.fixture
def quiet() -> Iterator[None]:
    """The service's and can-isotp's warnings about broken transfers (thousands) unlogged."""
    loggers = [logging.getLogger(name) for name in ("scara", "isotp")]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.CRITICAL)
    yield
    for logger, level in zip(loggers, levels, strict=True):
        logger.setLevel(level)


@pytest.mark.usefixtures("quiet", "isotp_on_the_clock")
def test_tasks_over_isotp_change_the_task_only_when_valid_and_never_move_the_arm() -> None:
    run_state_machine_as_test(ServiceUploads, settings=fuzz(30, stateful_step_count=10))


@pytest.mark.usefixtures("quiet", "isotp_on_the_clock")
@pytest.mark.parametrize(
    "flag",
    [
        "error",
        "remote",
        "extended",
    ],
)
@fuzz(10)
@given(payload=task_payloads())
@example(payload=json.dumps(TASK | {"ticket": 7}).encode())  # a valid task
def test_frames_that_are_no_data_frames_of_scenario_upload_carry_no_task(
    flag: str, payload: bytes
) -> None:
    """Error and remote frames, and extended-ID frames, are not ScenarioUpload's: whatever
    they carry is no transfer, and gets no answer."""
    machine = ServiceUploads()
    try:
        for data in segments(seal(payload or b" ")):
            machine.send_raw(Raw(data, frozenset({flag})))
        machine.tick(3)
        assert machine.delivered == [] and machine.answers == []
        assert machine.service.task is None
    finally:
        machine.teardown()


def _task(**changes: Any) -> bytes:
    return json.dumps(TASK | {"ticket": 9} | changes, ensure_ascii=False).encode()


@pytest.mark.usefixtures("quiet", "isotp_on_the_clock")
@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (_task(settle_time=10**400), Reason.BAD_FIELD),  # OverflowError in parse_task
        (b'{"ticket": 9, "waypoints": ' + deep(2000) + b"}", Reason.MALFORMED),  # RecursionError
        (_task(name="\u00e9" * 1500), Reason.BAD_FIELD),  # 3 kB taken, described as 9 kB
    ],
    ids=["huge-int", "deep", "long-name"],
)
def test_what_the_fuzzing_found_is_answered_and_the_service_goes_on(
    payload: bytes, reason: Any
) -> None:
    """Transfers that made the controller's loop raise before the fixes (found by
    ``test_fuzz_commands.py`` and ``test_fuzz_scenario.py`` in the parsers it shares)."""
    machine = ServiceUploads()
    try:
        machine.upload(payload)
        answer = machine.answers[-1]
        assert (answer.Request, answer.Accepted, answer.Reason) == (Answered.SCENARIO, 0, reason)
        assert machine.service.task is None
        machine.request(Request.DESCRIBE)
        assert machine.answers[-1].Reason == Reason.NO_SCENARIO
    finally:
        machine.teardown()
