"""The in-process simulation: control law and plant model stepped in one fixed-step loop.

Deterministic: the same scenario and mode give bit-identical logs, since nothing here reads a
clock or draws a random number. The joint state and the command pass through the CAN codec
on their way, so the values are quantised exactly as they are between the processes.
"""

from __future__ import annotations

from dataclasses import dataclass

from controller.control_law import ControlLaw
from controller.runlog import RunLog, row_of
from plant_sim.model import PlantModel
from protocol.messages import on_the_wire_command, on_the_wire_state
from protocol.scenario import Mode, Scenario
from sim.measures import Measures, compute_measures


@dataclass(frozen=True, slots=True)
class SimulationRun:
    scenario: Scenario
    log: RunLog
    measures: Measures


def simulate(scenario: Scenario, mode: Mode | None = None) -> SimulationRun:
    """Run ``scenario`` (in ``mode`` if given) from its first waypoint to the settled end."""
    if mode is not None:
        scenario = scenario.with_mode(mode)
    law = ControlLaw.for_scenario(scenario)
    plant = PlantModel(scenario.robot, scenario.plant, position=scenario.initial_joints())
    period = scenario.controller.period
    ticks = round(scenario.duration / period) + 1
    start = scenario.waypoints[0].t
    log = RunLog(ticks)
    for tick in range(ticks):
        t = start + tick * period
        position, velocity = on_the_wire_state(plant.position, plant.velocity)
        output = law.step(t, position)
        log.append(row_of(t, position, velocity, output, t))
        plant.advance(on_the_wire_command(output.command), period)
    return SimulationRun(scenario, log, compute_measures(scenario, log))
