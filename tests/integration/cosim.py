"""What the co-simulation tests share (``test_cosim.py``, ``test_hil_clients.py``): the
reference run in-process, starting and reading runs, decoding what the nodes said, and the
checks of a clean and of a bit-identical run."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from support import SLOWDOWN, Process, Processes, Transport

from plant_sim.node import PlantNode
from protocol.codec import WIRE
from protocol.errors import DecodeError
from protocol.messages import (
    COMMAND,
    CONTROLLER_STATUS,
    COORDINATION,
    PLANT_STATUS,
    RUN_STATUS,
    STATE_IDS,
    STEP,
)
from protocol.scenario import Mode, load_scenario
from sim.report import read_run
from sim.simulation import SimulationRun, simulate

SCENARIO = "reference"
CONTROLLER_IDS = frozenset(
    codec.frame_id for codec in (COMMAND, STEP, CONTROLLER_STATUS, COORDINATION, RUN_STATUS)
)
PLANT_IDS = frozenset({*STATE_IDS, PLANT_STATUS.frame_id})
PLANT_LISTENS = frozenset(codec.frame_id for codec in PlantNode.listens)
"""What the plant decodes (and so counts when corrupt) of the controller's frames."""
FAULTS = "drop=0.05,corrupt=0.01"
STARTUP = 15.0
"""s a node may take to start (import, open the bus) and reach the state a test waits for."""
STALE_TICKS = 3
RUN_TIMEOUT = 200.0
"""s a run started with :func:`launch` may take (times SLOWDOWN): scara-run's ``--timeout``,
which in lockstep becomes the controller's ``--max-wall-time`` (its default, 600 s, unstretched,
is too short for the emulated VM on a loaded host: 2156 of the reference scenario's 3251
lockstep ticks took 268 s there, 8 ticks/s, and more load slows it further)."""


# --------------------------------------------------------------------------- helpers


@cache
def reference_run(mode: Mode, scenario: str = SCENARIO) -> SimulationRun:
    return simulate(load_scenario(scenario), mode)


def launch(
    processes: Processes,
    transport: Transport,
    out: Path,
    clock: str,
    *extra: str,
    scenario: str = SCENARIO,
) -> tuple[int, dict[str, Any]]:
    """Run ``scara-run`` on ``scenario`` to the end; its exit code and the run's report as a
    dict: the controller's result, ``"plant"`` the plant's, ``"measures"`` those of the log."""
    launcher = processes.start(
        "sim.launch", scenario, "--clock", clock, "--out", str(out), *transport.cli(),
        "--timeout", f"{RUN_TIMEOUT * SLOWDOWN:g}", *extra, name="launch",
    )  # fmt: skip
    code = launcher.wait(RUN_TIMEOUT + 30.0)  # the run's time, then the nodes' stop
    return code, run_result(out, launcher)


def run_result(out: Path, *processes: Process) -> dict[str, Any]:
    """The run in ``out`` as a dict (see :func:`launch`); fails showing the outputs if absent."""
    outputs = "\n".join(process.output() for process in processes)
    assert (out / "controller.json").exists(), f"no controller result\n{outputs}"
    assert (out / "plant_sim.json").exists(), f"no plant result\n{outputs}"
    report = read_run(out)
    result = dict(report.controller)
    result["plant"] = report.plant
    result["measures"] = report.measures.as_dict() if report.measures else None
    return result


def finish_clean(
    processes: Processes, controller: Process, plant: Process, out: Path
) -> dict[str, Any]:
    """Wait for the controller to end its run, stop the plant, and check the run was clean."""
    code = controller.wait(60)
    assert plant.interrupt() == 0, plant.output()
    result = run_result(out, controller, plant)
    outputs = processes.outputs()
    assert code == 0, f"{brief(result)}\n{outputs}"
    assert_run_is_clean(result, outputs)
    return result


def node_args(transport: Transport, clock: str, out: Path, *extra: str) -> list[str]:
    return [SCENARIO, "--clock", clock, *transport.cli(), "--out", str(out), *extra]


def decode(message: can.Message) -> tuple[Any, int, Any] | None:
    """(codec, counter, record), or None for a frame that does not decode (corrupt)."""
    try:
        return WIRE.decode(message.arbitration_id, bytes(message.data))
    except DecodeError:
        return None


def status_of(message: can.Message) -> tuple[int, int] | None:
    """(State, FaultCode) of a valid ControllerStatus frame, else None."""
    if message.arbitration_id != CONTROLLER_STATUS.frame_id:
        return None
    decoded = decode(message)
    return None if decoded is None else (decoded[2].State, decoded[2].FaultCode)


def command_of(message: can.Message) -> tuple[int, tuple[float, float, float]] | None:
    """(Enable, rates) of a valid JointVelocityCommand frame, else None."""
    if message.arbitration_id != COMMAND.frame_id:
        return None
    decoded = decode(message)
    if decoded is None:
        return None
    record = decoded[2]
    return record.Enable, (record.Theta1Rate, record.Theta2Rate, record.D3Rate)


def controller_in(state: Any) -> Callable[[can.Message], bool]:
    def matches(message: can.Message) -> bool:
        status = status_of(message)
        return status is not None and status[0] == state

    return matches


def by_time(frames: list[can.Message]) -> list[can.Message]:
    return sorted(frames, key=lambda message: message.timestamp)


def brief(result: dict[str, Any]) -> str:
    """What a failure message should show of a result."""
    keys = ("completed", "state", "faults", "e2e", "injected", "loop", "wall_time_s", "plant")
    return json.dumps({key: result.get(key) for key in keys})


def assert_run_is_clean(result: dict[str, Any], outputs: str) -> None:
    """Completed, no faults, collision-free; the plant saw no collision; every stop of the
    arm is one the controller held for (the coordination itself never stops it)."""
    assert result["completed"], f"not completed: {brief(result)}\n{outputs}"
    assert result["faults"] == [], f"controller faults: {brief(result)}\n{outputs}"
    measures = result["measures"]
    assert measures is not None, result
    assert measures["collision_free"] is True, measures
    plant = result["plant"]
    assert plant["stats"]["collisions"] == 0, plant
    assert "COLLISION" not in plant["faults"], plant
    assert measures["stops"] <= result["loop"]["holds"], (measures, result["loop"])


def same(a: Any, b: Any) -> bool:
    """Exact equality of JSON values, types included; NaN equals NaN."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    return bool(a == b)


def assert_bit_identical(
    result: dict[str, Any], out: Path, mode: Mode, scenario: str = SCENARIO
) -> None:
    """Measures equal to the in-process simulation's of ``scenario`` (after a JSON round trip,
    floats exact), and the logged time series equal bit for bit."""
    expected = reference_run(mode, scenario)
    want = json.loads(json.dumps(expected.measures.as_dict()))
    got = json.loads(json.dumps(result["measures"]))
    differing = {k: (got.get(k), want[k]) for k in want if not same(got.get(k), want[k])}
    assert same(got, want), f"measures differ from the in-process simulation: {differing}"
    data = read_run(out).log.data  # (the log's columns are checked as it is read)
    simulated = expected.log.data
    assert data.dtype == simulated.dtype and data.shape == simulated.shape
    if data.tobytes() != simulated.tobytes():
        rows = np.flatnonzero(np.any(data != simulated, axis=1))
        pytest.fail(f"log not bit-identical; first differing rows {rows[:5].tolist()}")
