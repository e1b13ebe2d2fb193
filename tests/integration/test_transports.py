"""Lockstep over transports other than Zenoh gives the in-process simulation's results too.

- ``virtual``: python-can's in-process bus, plant and controller in two threads (also with
  the controller's side flooded by other systems' frames);
- ``udp_multicast``: two real processes inside a network namespace made for the test, whose
  loopback carries the multicast group (never on the host's network: ``docs/design.md``).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import can
import numpy as np
import pytest
from support import LATE_DETOUR, ROOT, SLOWDOWN, frame

from controller.node import (
    GIVE_UP_VARIABLE,
    LOCKSTEP_GIVE_UP,
    LOCKSTEP_STARTUP,
    STARTUP_VARIABLE,
    ControllerNode,
)
from controller.run_end import RunOutcome
from plant_sim.node import PlantNode
from protocol.errors import ConfigError
from protocol.node import ClockMode
from protocol.scenario import Mode, Scenario, load_scenario
from sim.measures import compute_measures
from sim.report import read_run
from sim.simulation import simulate

FOREIGN_ID = 0x7E8
"""A standard ID the DBC does not define (an OBD-II answer)."""
NAMESPACE_SETUP = (
    "ip link set lo up && ip link set lo multicast on && ip route add 239.0.0.0/8 dev lo"
)


def lockstep_on_virtual(
    scenario: Scenario,
    channel: str,
    controller_side: Callable[[can.BusABC], can.BusABC] = lambda bus: bus,
) -> ControllerNode:
    """A lockstep run on a ``virtual`` channel, the plant in a thread; ``controller_side``
    may wrap the controller's bus."""
    plant_bus = can.Bus(interface="virtual", channel=channel)
    controller_bus = can.Bus(interface="virtual", channel=channel)
    plant = PlantNode(plant_bus, scenario, ClockMode.LOCKSTEP)
    server = threading.Thread(target=plant.run, daemon=True)
    server.start()
    try:
        controller = ControllerNode(controller_side(controller_bus), scenario, ClockMode.LOCKSTEP)
        controller.run_lockstep(startup_timeout=10.0 * SLOWDOWN)
    finally:
        plant.stop()
        server.join(timeout=5.0 * SLOWDOWN)
        plant_bus.shutdown()
        controller_bus.shutdown()
    return controller


def test_lockstep_over_the_virtual_bus_is_bit_identical_to_the_simulation() -> None:
    scenario = load_scenario("reference").with_mode(Mode.CONVENTIONAL)
    controller = lockstep_on_virtual(scenario, "lockstep-virtual")
    expected = simulate(scenario)
    assert controller.finished
    assert np.array_equal(controller.log_rows.data, expected.log.data)
    assert controller.outcome is not None
    assert compute_measures(scenario, controller.log_rows, controller.outcome) == expected.measures


@pytest.mark.parametrize("timed_out", [False, True], ids=["late", "timed-out"])
def test_lockstep_of_a_late_run_ends_as_the_simulations(timed_out: bool) -> None:
    """A run that a detour made late ends when its task is done, or (its timeout as short
    as its plan) in TASK_TIMEOUT, on the simulation's tick and with its log and measures."""
    scenario = load_scenario(LATE_DETOUR)
    if timed_out:
        scenario = replace(scenario, timeout=scenario.duration)
    controller = lockstep_on_virtual(scenario, f"lockstep-late-{timed_out}")
    expected = simulate(scenario)
    assert controller.outcome is expected.measures.outcome
    assert np.array_equal(controller.log_rows.data, expected.log.data)
    measures = compute_measures(scenario, controller.log_rows, controller.outcome)
    assert repr(measures) == repr(expected.measures)  # exact, and NaN (never completed) too
    result = controller.result()
    assert result["outcome"] == ("task_timeout" if timed_out else "done")
    assert result["completed"] is not timed_out
    assert result["faults"] == (["TASK_TIMEOUT"] if timed_out else [])
    assert controller.exit_code == int(timed_out)


@pytest.mark.usefixtures("no_safe_motion_near")
def test_lockstep_without_safe_motion_faults_on_the_simulations_tick() -> None:
    scenario = load_scenario(LATE_DETOUR)
    controller = lockstep_on_virtual(scenario, "lockstep-unsafe")
    expected = simulate(scenario)
    assert controller.outcome is expected.measures.outcome is RunOutcome.NO_SAFE_MOTION
    assert np.array_equal(controller.log_rows.data, expected.log.data)
    result = controller.result()
    assert result["outcome"] == "no_safe_motion" and result["faults"] == ["NO_SAFE_MOTION"]
    assert result["state"] == "FAULT" and controller.exit_code == 1


class Flooded(can.BusABC):
    """A bus busier than its reader: whenever nothing of the run is waiting, a frame of an ID
    the DBC does not define is (another system's traffic, without end)."""

    def __init__(self, inner: can.BusABC) -> None:
        super().__init__(channel=None)
        self.inner = inner

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message, bool]:
        message = self.inner.recv(timeout=0.0)
        if message is None:
            time.sleep(0)  # the plant's thread gets the interpreter now and then, as on a bus
        return message or frame(FOREIGN_ID, bytes(8)), False


def test_lockstep_under_a_flood_that_never_runs_dry_is_bit_identical(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A node drains at most DRAIN_LIMIT frames before it looks at its own work: reading
    until the bus is quiet, the controller never took the answer it had read."""
    monkeypatch.setattr("protocol.node.DRAIN_LIMIT", 8)  # the test's own time, not the bound
    scenario = load_scenario("reference").with_mode(Mode.CONVENTIONAL)
    controller = lockstep_on_virtual(scenario, "lockstep-flooded", Flooded)
    assert controller.finished
    assert np.array_equal(controller.log_rows.data, simulate(scenario).log.data)
    assert controller.monitor.counts.unknown >= controller.tick


def _can_make_namespace() -> bool:
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return False
    probe = subprocess.run(
        ["unshare", "-n", "sh", "-c", NAMESPACE_SETUP], capture_output=True, timeout=10 * SLOWDOWN
    )
    return probe.returncode == 0


@pytest.mark.skipif(
    not _can_make_namespace(), reason="cannot create a network namespace (unshare -n) here"
)
def test_lockstep_over_udp_multicast_in_a_namespace(tmp_path: Path) -> None:
    pytest.importorskip("msgpack", reason="python-can[multicast] is not installed")
    launch = [
        sys.executable, "-m", "sim.launch", "reference", "--clock", "lockstep",
        "--interface", "udp_multicast", "--channel", "239.74.163.2", "--out", str(tmp_path),
    ]  # fmt: skip
    command = f"{NAMESPACE_SETUP} && exec {' '.join(launch)}"
    completed = subprocess.run(
        ["unshare", "-n", "sh", "-c", command],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120 * SLOWDOWN,
    )
    assert completed.returncode == 0, completed.stderr[-2000:]
    result = json.loads((tmp_path / "controller.json").read_text())
    expected = simulate(load_scenario("reference"))
    log = read_run(tmp_path).log  # from the run's recording, which holds it
    assert np.array_equal(log.data, expected.log.data)
    assert result["e2e"]["corrupt"] == 0


def test_lockstep_controller_faults_when_the_plant_goes_away() -> None:
    scenario = load_scenario("reference")
    plant_bus = can.Bus(interface="virtual", channel="lockstep-gone")
    controller_bus = can.Bus(interface="virtual", channel="lockstep-gone")
    plant = PlantNode(plant_bus, scenario, ClockMode.LOCKSTEP)
    server = threading.Thread(target=plant.run, kwargs={"duration": 0.3}, daemon=True)
    server.start()
    try:
        controller = ControllerNode(controller_bus, scenario, ClockMode.LOCKSTEP)
        controller.run_lockstep(
            startup_timeout=5.0 * SLOWDOWN, max_wall_time=20.0 * SLOWDOWN, give_up=0.2
        )
    finally:
        server.join(timeout=5.0 * SLOWDOWN)
        plant_bus.shutdown()
        controller_bus.shutdown()
    assert not controller.finished
    assert controller.tick > 0
    assert controller.result()["faults"] == ["STALE_STATE"]


def test_the_lockstep_waits_are_the_environments_where_set(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    for variable in (GIVE_UP_VARIABLE, STARTUP_VARIABLE):  # (the tests may stretch them)
        monkeypatch.delenv(variable, raising=False)
    scenario = load_scenario("reference")
    bus = can.Bus(interface="virtual", channel="lockstep-waits")
    try:
        default = ControllerNode(bus, scenario, ClockMode.LOCKSTEP)
        assert (default.lockstep_give_up, default.lockstep_startup) == (
            LOCKSTEP_GIVE_UP,
            LOCKSTEP_STARTUP,
        )
        monkeypatch.setenv(GIVE_UP_VARIABLE, "2.5")
        monkeypatch.setenv(STARTUP_VARIABLE, " 45 ")
        stretched = ControllerNode(bus, scenario, ClockMode.LOCKSTEP)
        assert (stretched.lockstep_give_up, stretched.lockstep_startup) == (2.5, 45.0)
        monkeypatch.setenv(GIVE_UP_VARIABLE, "inf")
        with pytest.raises(ConfigError, match=GIVE_UP_VARIABLE):
            ControllerNode(bus, scenario, ClockMode.LOCKSTEP)
        ControllerNode(bus, scenario, ClockMode.REALTIME)  # not read in real time
    finally:
        bus.shutdown()
