"""ISO-TP on a pair of IDs that one controller and two operators (bridges) share, as on the
robot's bus: each operator sends on ScenarioUpload and receives on ScenarioDownload, so each
sees the controller's flow control for the other's uploads, and the controller's transfers to
the other. Over python-can's ``virtual`` bus, stepped by hand (no thread, no clock)."""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable, Iterator
from typing import Any

import can
import pytest
from support import wait_until

from protocol.isotp_link import FLOW_CONTROL, IsoTpLink
from protocol.messages import SCENARIO_DOWNLOAD, SCENARIO_UPLOAD
from protocol.scenario import encode_task, load_scenario

TASK = encode_task(load_scenario("reference"), 7)
"""A task as the bridge sends it and the controller describes it back: 54 frames."""
_channels = itertools.count()


class End:
    """One node's link on its own bus: what it sent, received and got wrong."""

    def __init__(self, channel: str, txid: int, rxid: int, **options: Any) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.sent: list[can.Message] = []
        self.received: list[bytes] = []
        self.errors: list[Exception] = []
        self.link = IsoTpLink(self._send, txid, rxid, on_error=self.errors.append, **options)

    def _send(self, message: can.Message) -> None:
        self.sent.append(message)
        self.bus.send(message)

    def step(self) -> None:
        while (message := self.bus.recv(timeout=0.0)) is not None:
            if message.arbitration_id == self.link.rxid:
                self.link.feed(message)
        self.received += self.link.poll()

    def flow_controls(self) -> int:
        return sum(message.data[0] >> 4 == FLOW_CONTROL for message in self.sent)


class Bus:
    """A controller's link and two operators' on one channel."""

    def __init__(self, **operator_options: Any) -> None:
        channel = f"isotp-{next(_channels)}"
        self.controller = End(channel, SCENARIO_DOWNLOAD.frame_id, SCENARIO_UPLOAD.frame_id)
        self.operators = [
            End(channel, SCENARIO_UPLOAD.frame_id, SCENARIO_DOWNLOAD.frame_id, **options)
            for options in operator_options.get("each", [{}, {}])
        ]
        self.ends = [self.controller, *self.operators]

    def run_until(self, done: Callable[[], bool], what: str) -> None:
        """Step every end in turn until ``done()``."""

        def stepped() -> bool:
            for end in self.ends:
                end.step()
            return done()

        wait_until(stepped, 5.0, what)

    def close(self) -> None:
        for end in self.ends:
            end.bus.shutdown()


@pytest.fixture
def make_bus() -> Iterator[Callable[..., Bus]]:
    made: list[Bus] = []

    def make(**operator_options: Any) -> Bus:
        made.append(Bus(**operator_options))
        return made[-1]

    yield make
    for bus in made:
        bus.close()


def test_the_controllers_flow_control_for_one_operator_is_dropped_by_the_other_silently(
    make_bus: Callable[..., Bus], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING)
    bus = make_bus()
    sender, other = bus.operators
    sender.link.send(TASK)
    bus.run_until(lambda: bool(bus.controller.received) and not sender.link.sending, "the upload")

    assert bus.controller.received == [TASK]
    assert bus.controller.flow_controls() == 1
    assert [record.getMessage() for record in caplog.records] == []
    assert other.errors == [] and other.received == [] and other.sent == []
    assert sender.errors == [] and bus.controller.errors == []
    assert other.link.stray_flow_controls == 1  # seen, dropped, counted


def test_only_the_operator_that_asked_answers_a_transfer_and_the_other_listens(
    make_bus: Callable[..., Bus], caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING)
    bus = make_bus(each=[{"asked": lambda: True}, {"asked": lambda: False}])
    asker, other = bus.operators
    bus.controller.link.send(TASK)  # a describe's answer, to the operator that asked
    bus.run_until(lambda: bool(asker.received and other.received), "the transfer")

    assert asker.received == [TASK] and other.received == [TASK]  # both learn the task
    assert asker.flow_controls() == 1 and len(asker.sent) == 1
    assert other.sent == []  # one receiver answers one sender
    assert bus.controller.link.stray_flow_controls == 0
    assert [end.errors for end in bus.ends] == [[], [], []]
    assert [record.getMessage() for record in caplog.records] == []


def test_an_operator_answers_a_transfer_only_while_it_awaits_one(
    make_bus: Callable[..., Bus],
) -> None:
    awaiting = [False]
    bus = make_bus(each=[{"asked": lambda: awaiting[0]}])
    (operator,) = bus.operators
    bus.controller.link.send(TASK)  # nobody asked: nobody answers, both ends give up
    bus.run_until(  # after can-isotp's timeouts, on its own (real) clock
        lambda: bool(bus.controller.errors) and operator.link.overheard_errors == 1,
        "the unanswered transfer to time out at both ends",
    )
    assert operator.sent == [] and operator.received == [] and operator.errors == []

    awaiting[0] = True
    bus.controller.link.send(TASK)
    bus.run_until(lambda: bool(operator.received), "the awaited transfer")
    assert operator.received == [TASK] and operator.flow_controls() == 1
    assert operator.errors == [] and operator.link.overheard_errors == 1


def test_the_controllers_link_answers_every_transfer(make_bus: Callable[..., Bus]) -> None:
    bus = make_bus()
    first, second = bus.operators
    first.link.send(TASK)
    bus.run_until(lambda: len(bus.controller.received) == 1, "the first upload")
    second.link.send(TASK)
    bus.run_until(lambda: len(bus.controller.received) == 2, "the second upload")
    assert bus.controller.received == [TASK, TASK]
    assert bus.controller.flow_controls() == 2


def test_a_transfer_with_a_bit_flipped_on_the_wire_is_dropped_and_counted(
    make_bus: Callable[..., Bus],
) -> None:
    """ISO-TP checks frame order and length, not bytes: without the CRC a digit flipped on
    the wire (``"x":0.2`` read as ``"x":0.3``) was a valid, different task."""
    bus = make_bus(each=[{}])
    (operator,) = bus.operators
    flipped = [False]

    def flip_one_digit(message: can.Message) -> None:
        data = bytearray(message.data)
        if not flipped[0] and data[0] >> 4 == 2 and any(0x30 <= b <= 0x38 for b in data[1:]):
            at = next(i for i, b in enumerate(data) if i and 0x30 <= b <= 0x38)
            data[at] ^= 0x01  # another digit, still JSON
            flipped[0] = True
        operator._send(
            can.Message(arbitration_id=message.arbitration_id, data=data, is_extended_id=False)
        )

    operator.link._send_frame = flip_one_digit  # type: ignore[method-assign]
    operator.link.send(TASK)
    bus.run_until(lambda: bool(bus.controller.errors), "the flipped transfer to be refused")
    assert bus.controller.received == [] and bus.controller.link.corrupt == 1
    assert "CRC" in str(bus.controller.errors[0])

    operator.link.send(TASK)  # the next one, whole, goes through
    bus.run_until(lambda: bool(bus.controller.received), "the whole transfer")
    assert bus.controller.received == [TASK] and bus.controller.link.corrupt == 1
