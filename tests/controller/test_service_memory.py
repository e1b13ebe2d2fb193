"""A controller service that runs 100 tasks keeps its memory flat: this process's resident
memory (``VmRSS`` of ``/proc/self/status``, after a garbage collection) after the 100th task
is within 5 MB of what it was after the first.

The service runs as in its process: :func:`~protocol.realtime.settle_memory` first, then its
own real-time loop (``run_realtime``), writing each run's result and log to ``--out``. Around
it, in this process, on python-can's ``virtual`` bus and a fake clock: a real
:class:`~plant_sim.node.PlantNode` and the bridge's :class:`~bridge.operator.OperatorNode`.
The service's sleep to each deadline moves the clock (a little late, at random, as on a
loaded host) and runs the plant and the operator, which uploads the next task over ISO-TP
and asks to run it whenever a run ended. The tasks go there and back between two points, 2 s
each: 100 tasks are 100,000 ticks, after which the statistics' former per-tick lists held
200,000 floats (6.4 MB).
"""

from __future__ import annotations

import gc
import itertools
import json
import random
from pathlib import Path
from typing import Any

import can
import pytest
from support import FakeClock

from bridge.operator import Answer, OperatorNode
from controller.service import ServiceNode
from plant_sim.node import PlantNode
from protocol.messages import NodeState, Request
from protocol.node import ClockMode
from protocol.realtime import settle_memory
from protocol.scenario import Scenario, load_scenario, parse_task, task_document

TASKS = 100
ALLOWED_GROWTH = 5 * 2**20
"""bytes: resident memory after the last task may exceed that after the first by this much."""
REFERENCE = load_scenario("reference")
BASE = Scenario("service", (), None)
LATE = 100e-6
"""s: each tick starts up to this late (uniformly at random)."""


def task(name: str, mode: str, waypoints: list[dict[str, float]]) -> Scenario:
    """A task of the reference's obstacle: from the first of ``waypoints`` (at t = 0) on."""
    document = task_document(REFERENCE) | {"name": name, "mode": mode, "settle_time": 0.5}
    return parse_task(document | {"waypoints": waypoints}, BASE)


START, END = (task_document(REFERENCE)["waypoints"][i] for i in (0, 1))
THERE = task("there", "fuzzy", [START | {"t": 0.0}, END | {"t": 1.5}])
BACK = task("back", "conventional", [END | {"t": 0.0}, START | {"t": 1.5}])


def resident_memory() -> int:
    """This process's resident memory in bytes, after a garbage collection."""
    gc.collect()
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):  # "VmRSS:    54712 kB"
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS in /proc/self/status")


class World:
    """The plant and the operator around the service, run from the service's sleep."""

    def __init__(self, channel: str, out: Path) -> None:
        self.buses = [can.Bus(interface="virtual", channel=channel) for _ in range(3)]
        self.clock = FakeClock()
        self.late = random.Random(0)
        self.service = ServiceNode(self.buses[0], BASE, out=out, clock=self.clock, sleep=self.sleep)
        self.plant = PlantNode(self.buses[1], REFERENCE, ClockMode.REALTIME, clock=self.clock)
        self.operator = OperatorNode(
            self.buses[2], BASE, lambda *event: None, lambda received: None, clock=self.clock
        )
        self.tasks = itertools.cycle((THERE, BACK))
        self.started = 0
        self.ended = 0
        self.memory: dict[int, int] = {}
        """Resident memory (bytes) after the run of that number."""

    def sleep(self, seconds: float) -> None:
        self.clock.now += seconds + self.late.uniform(0.0, LATE)
        self.plant.drain()
        self.plant.take_worlds()
        self.plant.on_period(self.clock.now)
        self.plant.send_status_if_due(self.clock.now)
        self.operator.step(0.0)
        if self.service.runs > self.ended:
            self.ended = self.service.runs
            if self.ended in (1, TASKS):
                self.memory[self.ended] = resident_memory()
            if self.ended == TASKS:
                self.service.stop()
        if self.started == self.ended < TASKS and self.service.state is not None:
            self.started += 1
            self.operator.set_task(next(self.tasks), self._on_task_set)

    def _on_task_set(self, answer: Answer) -> None:
        assert answer.accepted, (self.started, answer)
        self.operator.request(Request.RUN, self._on_run_started)

    def _on_run_started(self, answer: Answer) -> None:
        assert answer.accepted, (self.started, answer)
        assert self.service.node_state is NodeState.RUNNING

    def close(self) -> None:
        for bus in self.buses:
            bus.shutdown()


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads Linux's /proc")
def test_a_service_that_ran_100_tasks_kept_its_resident_memory_flat(tmp_path: Path) -> None:
    world = World(f"service-memory-{tmp_path.name}", tmp_path)
    try:
        settle_memory()
        world.service.run_realtime()
    finally:
        gc.unfreeze()  # settle_memory froze this process's objects: the next tests' again
        world.close()
    result: dict[str, Any] = json.loads((tmp_path / "controller.json").read_text())
    assert world.ended == TASKS and result["completed"] and not result["faults"], result
    assert result["loop"]["ticks"] == world.service.ticks_to_run, result["loop"]  # its own run's
    first, last = world.memory[1], world.memory[TASKS]
    print(f"resident memory after task 1: {first / 2**20:.2f} MB, after task {TASKS}: "
          f"{last / 2**20:.2f} MB ({(last - first) / 2**20:+.2f} MB)")  # fmt: skip
    assert last - first <= ALLOWED_GROWTH, (first, last)
