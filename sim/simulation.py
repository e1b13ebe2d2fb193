"""The in-process simulation: control law and plant model stepped in one fixed-step loop.

Deterministic: the same scenario and mode give bit-identical logs, since nothing here reads a
clock or draws a random number. The joint state and the command are quantised on their way as
the CAN codec quantises them (``protocol.messages``), so the values are exactly those between
the processes.
"""

from __future__ import annotations

from dataclasses import dataclass

from controller.control_law import ControlLaw
from controller.run_end import OUTCOMES, UNWATCHED, ending, run_end_of
from controller.runlog import RunLog, row_of
from plant_sim.model import PlantModel
from protocol.messages import joints_on_the_wire, rates_on_the_wire
from protocol.ops import SCALAR
from protocol.scenario import Mode, Scenario
from sim.measures import Measures, compute_measures


@dataclass(frozen=True, slots=True)
class SimulationRun:
    scenario: Scenario
    log: RunLog
    measures: Measures


def simulate(scenario: Scenario, mode: Mode | None = None) -> SimulationRun:
    """Run ``scenario`` (in ``mode`` if given) from its first waypoint until it ends
    (:mod:`controller.run_end`): its task done, no progress, its timeout reached, or no safe
    motion left."""
    if mode is not None:
        scenario = scenario.with_mode(mode)
    law = ControlLaw.for_scenario(scenario)
    plant = PlantModel(scenario.robot, scenario.plant, position=scenario.initial_joints())
    period = scenario.controller.period
    end = run_end_of(scenario)
    start = scenario.waypoints[0].t
    log = RunLog(end.end_tick + 1)  # a run done on time; a later one's log grows
    code = tick = 0
    watch = UNWATCHED
    while not code:
        t = start + tick * period
        position, velocity = joints_on_the_wire(SCALAR, plant.position, plant.velocity)
        output = law.step(t, position)
        log.append(row_of(t, position, velocity, output, t))
        plant.advance(rates_on_the_wire(SCALAR, output.command), period)
        code, watch = ending(SCALAR, end, law.state.reached, output, velocity, tick, tick, watch)
        tick += 1
    return SimulationRun(scenario, log, compute_measures(scenario, log, OUTCOMES[code - 1]))
