"""Regression replay: a recorded lockstep run's joint states fed to the control law again, and
its commands compared with the recorded ones, field by field, on the wire's quantisation.

In lockstep the controller sends, with ``StepSync(Tick=n)``, the command it computed at
``t = start + (n - 1) * period`` from the joint state that answered step ``n - 1``. So for
each new StepSync tick (a retry repeats one and is skipped) the law gets the last complete
joint state before it, and what it commands now must equal what was recorded, bit for bit,
for the same software and scenario. Pure: frames in, a report out.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import can

from controller.control_law import ControlLaw
from protocol.codec import WIRE
from protocol.errors import DecodeError
from protocol.messages import COMMAND, STATE_IDS, STEP, JointStateParts, command_record
from protocol.scenario import Scenario


@dataclass(frozen=True, slots=True)
class Divergence:
    tick: int
    field: str
    recorded: float
    now: float


@dataclass(slots=True)
class RegressionReport:
    ticks: int = 0
    identical: int = 0
    first: Divergence | None = None
    largest: dict[str, float] = field(default_factory=dict)
    """Per command field, the largest difference seen (recorded vs now)."""

    @property
    def passed(self) -> bool:
        return self.ticks > 0 and self.first is None

    def summary(self) -> str:
        if self.ticks == 0:
            return "no lockstep steps in the recording: nothing compared"
        lines = [f"{self.identical} of {self.ticks} commands identical to the recording"]
        if self.first is not None:
            first = self.first
            lines.append(
                f"first divergence: tick {first.tick}, JointVelocityCommand.{first.field}: "
                f"recorded {first.recorded:.6g}, now {first.now:.6g}"
            )
            differences = ", ".join(f"{k} {v:.6g}" for k, v in self.largest.items() if v)
            lines.append(f"largest differences: {differences}")
        return "\n".join(lines)


def regress(frames: Iterable[can.Message], scenario: Scenario) -> RegressionReport:
    """Compare the recorded commands of a lockstep run of ``scenario`` with the law's now."""
    law = ControlLaw.for_scenario(scenario)
    start, period = scenario.waypoints[0].t, scenario.controller.period
    report = RegressionReport(largest=dict.fromkeys(COMMAND.Record._fields, 0.0))
    parts = JointStateParts()
    position: Any = None
    step_tick = 0
    command: tuple[int, Any] | None = None  # (counter, record) of the last command frame
    for message in frames:
        if message.is_extended_id or message.is_error_frame or message.is_remote_frame:
            continue
        try:
            codec, counter, record = WIRE.decode(message.arbitration_id, message.data)
        except (DecodeError, KeyError):
            continue  # corrupt, or not ours: the controller did not act on it either
        if codec.frame_id in STATE_IDS:
            complete = parts.add(STATE_IDS.index(codec.frame_id), counter, record)
            if complete is not None:
                position = complete[0]
        elif codec is COMMAND:
            command = (counter, record)
        elif codec is STEP and command is not None and record.CommandCounter == command[0]:
            if record.Tick > step_tick and position is not None:  # not a retry
                step_tick = record.Tick
                tick = record.Tick - 1
                output = law.step(start + tick * period, position)
                expected = COMMAND.quantise(command_record(output.command))
                _compare(report, tick, command[1], expected)
            command = None
    return report


def _compare(report: RegressionReport, tick: int, recorded: Any, now: Any) -> None:
    report.ticks += 1
    same = True
    for name in COMMAND.Record._fields:
        before, after = getattr(recorded, name), getattr(now, name)
        if before != after:
            same = False
            report.largest[name] = max(report.largest[name], abs(before - after))
            if report.first is None:
                report.first = Divergence(tick, name, before, after)
    report.identical += same
