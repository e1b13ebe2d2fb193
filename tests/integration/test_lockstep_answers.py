"""Which joint state answers a lockstep tick: the controller against a scripted plant on a
``virtual`` bus, which sends what a real plant sends late (``controller/node.py``,
``_answers``).

A plant answers every StepSync it takes, also one repeated after it had answered (without
stepping again), and echoes the counter of the last command it took. Such late answers reach
the controller after it has moved on to the next tick; the echo alone cannot tell them from
the answer it waits for, since counters repeat every 16 commands:

- at the start a plant echoes 0 before any command, and the first command of a run was
  counter 0. Seen in the emulated VM: a plant that started late answered the StepSyncs(0) the
  controller had repeated meanwhile after tick 1 was sent, and the controller took one of
  these answers for tick 1's (harmless there only because the first command is zero and the
  plant went on to step tick 1 from its queue). Had tick 1's frames been lost (5 % are, in
  the fault-injection test), the controller would have asked for tick 2 of a plant at tick 0,
  which takes every such StepSync for an unknown one, until STALE_STATE: most likely the
  failure once seen in the ordinary tier (STALE_STATE at tick 1, the plant 0 steps and 10
  unknown step requests);
- a tick retried 16 times or more has used every counter, that of a late answer too (the 1 s
  give-up leaves time for about 12 sends; a longer one, for more).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator

import can
import pytest
from support import SLOWDOWN

from controller.node import LOCKSTEP_RETRY_MAX, ControllerNode
from protocol.codec import WIRE
from protocol.messages import STATE, STEP, Counter
from protocol.node import ClockMode
from protocol.scenario import Scenario, load_scenario

WAIT = 5.0
"""s the test waits for one frame of the controller (times SLOWDOWN)."""


class ScriptedPlant:
    """The plant's side of a virtual bus, driven by the test: it reads the controller's
    frames and sends joint states when told."""

    def __init__(self, bus: can.BusABC, scenario: Scenario) -> None:
        self.bus = bus
        self.position = scenario.initial_joints()
        self.counter = Counter()

    def next_step(self, after: int = -1) -> tuple[int, int]:
        """(Tick, CommandCounter) of the controller's next StepSync for a tick after
        ``after``: retries of a tick that were sent before its answer arrived are passed over
        (a slow test thread lets the controller retry before the plant answers)."""
        while True:
            message = self.bus.recv(WAIT * SLOWDOWN)
            assert message is not None, "the controller sent no StepSync"
            decoded = WIRE.decode(message.arbitration_id, bytes(message.data))
            if decoded[0] is STEP and int(decoded[2].Tick) > after:
                record = decoded[2]
                return int(record.Tick), int(record.CommandCounter)

    def answer(self, echo: int) -> None:
        """A joint state (at rest where the arm starts) echoing command counter ``echo``."""
        counter = self.counter.next()
        for codec, position in zip(STATE, self.position, strict=True):
            record = codec.Record(CommandEcho=echo, Position=position, Velocity=0.0)
            data = codec.encode(record, counter)
            self.bus.send(
                can.Message(arbitration_id=codec.frame_id, data=data, is_extended_id=False)
            )


@pytest.fixture
def plant(
    request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch
) -> Iterator[ScriptedPlant]:
    """A scripted plant, and a lockstep controller running in a thread against it. It gives
    the plant up after ``give_up`` s without an answer, which the tests never let happen;
    ``retry_max`` s is the longest wait between its retries at the default give-up (both
    from the test's ``plant`` parameter, if any)."""
    give_up, retry_max = getattr(request, "param", (60.0, LOCKSTEP_RETRY_MAX))
    monkeypatch.setattr("controller.node.LOCKSTEP_RETRY_MAX", retry_max)
    scenario = load_scenario("reference")
    channel = f"lockstep-answers-{id(scenario)}"
    controller_bus = can.Bus(interface="virtual", channel=channel)
    plant_bus = can.Bus(interface="virtual", channel=channel)
    controller = ControllerNode(controller_bus, scenario, ClockMode.LOCKSTEP)
    thread = threading.Thread(
        target=controller.run_lockstep,
        kwargs={"startup_timeout": WAIT * SLOWDOWN, "give_up": give_up * SLOWDOWN},
        daemon=True,
    )
    thread.start()
    try:
        yield ScriptedPlant(plant_bus, scenario)
    finally:
        controller.stop()
        thread.join(WAIT * SLOWDOWN)
        controller_bus.shutdown()
        plant_bus.shutdown()


def test_a_late_answer_to_a_start_up_step_sync_is_not_taken_for_tick_1s(
    plant: ScriptedPlant,
) -> None:
    assert plant.next_step() == (0, 0)
    plant.answer(0)  # a new plant echoes 0: no command yet
    tick, command = plant.next_step(after=0)
    assert tick == 1
    assert command != 0  # numbered on from the echo
    plant.answer(0)  # late: to a StepSync(0) of the start, sent again before the answer came
    assert plant.next_step()[0] == 1, "took a late answer to tick 0 for the answer to tick 1"
    plant.answer(command)
    assert plant.next_step(after=1)[0] == 2


@pytest.mark.parametrize("plant", [(10.0, 0.01)], indirect=True, ids=["quick retries"])
def test_a_late_answer_to_the_last_tick_is_not_taken_after_16_retries(
    plant: ScriptedPlant,
) -> None:
    assert plant.next_step() == (0, 0)
    plant.answer(0)
    tick, first = plant.next_step(after=0)
    tick_again, retried = plant.next_step()  # no answer yet: tick 1 sent again
    assert (tick, tick_again) == (1, 1)
    plant.answer(first)  # the answer to the first; the one to the retry comes late
    sent = []
    while len(sent) < 17:
        tick, command = plant.next_step(after=1)
        assert tick == 2, "tick 2 answered without an answer"
        sent.append(command)
    assert retried in sent, sent  # every counter used again by tick 2's retries
    plant.answer(retried)  # late: the plant answering tick 1's retry again
    assert plant.next_step()[0] == 2, "took a late answer to tick 1 for the answer to tick 2"
    plant.answer(sent[-1])
    tick = plant.next_step()[0]
    while tick == 2:  # retries sent before the answer arrived
        tick = plant.next_step()[0]
    assert tick == 3
