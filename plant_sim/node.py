"""``plant_sim``: the plant simulator process. It owns a bus and integrates the joint model.

Real-time mode: the plant runs on its own monotonic clock and integrates in whole periods.
When a valid command arrives it brings the joints up to the last whole period, answers at
once with that joint state, and applies the command from then on. It also
integrates every period on its own, and sends the state then too while no command comes, so
a controller that starts later finds it. If no valid command arrives for ``COMMAND_TIMEOUT``
it brakes to zero.

Lockstep mode: time moves only on StepSync frames. Each one advances exactly one control
period under the command it names, and the plant answers (see the DBC's comment on StepSync).

Both modes: the joint limits are hard stops reported as faults; a collision of the tool with
the obstacle (ground truth: the obstacle grown by the tool radius) is reported in PlantStatus.
Frames that fail the CRC, length, range or alive-counter checks are counted and ignored.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import can

from controller.process import (
    ClockMode,
    add_node_arguments,
    open_node,
    settle_memory,
    stop_on_signals,
)
from controller.scenario import Scenario
from plant_sim.model import PlantModel
from protocol.e2e import E2EMonitor
from protocol.kinematics import forward
from protocol.messages import (
    COMMAND,
    CONTROLLER_STATUS,
    NODE_COMMAND,
    PLANT_STATUS,
    STATE,
    STATUS_PERIOD,
    STEP,
    STOP,
    Counter,
    NodeId,
    NodeState,
    PlantFault,
    Request,
    encode_status,
    send_frame,
)

COMMAND_TIMEOUT = 0.020
"""s without a valid command before the plant brakes to zero (real-time mode)."""


@dataclass(slots=True)
class PlantStats:
    steps: int = 0
    commands_applied: int = 0
    states_sent: int = 0
    collisions: int = 0
    command_timeouts: int = 0
    unknown_step_requests: int = 0


class PlantNode:
    """The plant's side of the wire around a :class:`PlantModel`."""

    def __init__(
        self,
        bus: can.BusABC,
        scenario: Scenario,
        clock_mode: ClockMode,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.bus = bus
        self.scenario = scenario
        self.clock_mode = clock_mode
        self.clock = clock
        self.period = scenario.controller.period
        self.obstacle = scenario.touched_obstacle()
        self.monitor = E2EMonitor()
        self.stats = PlantStats()
        self.state_counter = Counter()
        self.status_counter = Counter()
        self.running = True
        self.reset()

    def reset(self) -> None:
        """Back to the scenario's first waypoint, at rest, faults cleared."""
        self.model = PlantModel(
            self.scenario.robot, self.scenario.plant, position=self.scenario.initial_joints()
        )
        self.command: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.command_echo = 0
        self.command_fresh = False  # lockstep: a command has come since the last step
        self.last_command_time = -float("inf")
        self.model_time = self.clock()
        self.tick = 0
        self.fault = PlantFault(0)
        self.node_state = NodeState.READY
        self.collided = False
        self.monitor.forget()

    # --- frames in -------------------------------------------------------------------------

    def handle(self, message: can.Message) -> None:
        """Act on one received frame, or count it and drop it."""
        accepted = self.monitor.accept(message, _RECEIVED)
        if accepted is None:
            return
        codec, counter, values = accepted
        if codec is COMMAND:
            self._on_command(counter, values)
        elif codec is STEP:
            self._on_step(int(values[0]), int(values[1]))
        elif codec is STOP:
            self.fault |= PlantFault.ESTOP
            self.node_state = NodeState.ESTOP
            self.command = (0.0, 0.0, 0.0)
        elif codec is NODE_COMMAND:
            request, target = int(values[0]), int(values[1])
            if target in (NodeId.PLANT, NodeId.ALL):
                if request == Request.RESET:
                    self.reset()
                    self._send_state()
                elif request == Request.STOP:
                    self.running = False

    def _on_command(self, counter: int, values: tuple[float, ...]) -> None:
        if self.clock_mode is ClockMode.REALTIME:
            self._integrate_to(self.clock())
        enable = int(values[0])
        if self.node_state is NodeState.ESTOP or not enable:
            self.command = (0.0, 0.0, 0.0)
        else:
            self.command = (values[1], values[2], values[3])
            if self.node_state is NodeState.READY:
                self.node_state = NodeState.RUNNING
        self.command_echo = counter
        self.command_fresh = True
        self.last_command_time = self.clock()
        self.stats.commands_applied += 1
        if self.clock_mode is ClockMode.REALTIME:
            self._send_state()

    def _on_step(self, command_counter: int, tick: int) -> None:
        if self.clock_mode is not ClockMode.LOCKSTEP:
            return
        if tick == self.tick:
            self._send_state()  # the answer was lost: say it again, without stepping
        elif tick == self.tick + 1 and self.command_fresh and command_counter == self.command_echo:
            self._advance(self.period)
            self.tick = tick
            self.command_fresh = False
            self._send_state()
        else:
            self.stats.unknown_step_requests += 1

    # --- the model ---------------------------------------------------------------------------

    def _advance(self, dt: float) -> None:
        self.model.advance(self.command, dt)
        self.stats.steps += 1
        if any(self.model.at_limit):
            self.fault |= PlantFault.JOINT_LIMIT
            if self.node_state is not NodeState.ESTOP:
                self.node_state = NodeState.FAULT
        if self.obstacle is not None:
            x, y, z = forward(self.scenario.robot, *self.model.position)
            inside = z < self.obstacle.height + self.obstacle.inflation and self.obstacle.contains(
                x, y
            )
            if inside and not self.collided:
                self.stats.collisions += 1
            self.collided = inside
            if inside:
                self.fault |= PlantFault.COLLISION

    def _integrate_to(self, now: float) -> None:
        """Real-time: advance the model in whole periods up to ``now``."""
        while self.model_time + self.period <= now:
            self._advance(self.period)
            self.model_time += self.period

    def on_period(self, now: float) -> None:
        """Real time, once a period: integrate, brake if commands stopped, report if idle."""
        self._integrate_to(now)
        self._watchdog(now)
        if now - self.last_command_time > self.period:
            self._send_state()  # nobody is commanding: keep them informed anyway

    def _watchdog(self, now: float) -> None:
        if now - self.last_command_time > COMMAND_TIMEOUT:
            if self.command != (0.0, 0.0, 0.0):
                self.stats.command_timeouts += 1
            self.command = (0.0, 0.0, 0.0)
            self.fault |= PlantFault.COMMAND_TIMEOUT
        else:
            self.fault &= ~PlantFault.COMMAND_TIMEOUT

    # --- frames out --------------------------------------------------------------------------

    def _send_state(self) -> None:
        counter = self.state_counter.next()
        for codec, position, velocity in zip(
            STATE, self.model.position, self.model.velocity, strict=True
        ):
            self._send(
                codec.frame_id, codec.encode((self.command_echo, position, velocity), counter)
            )
        self.stats.states_sent += 1

    def _send_status(self) -> None:
        flags = int(self.collided) | sum(
            1 << (joint + 1) for joint, hit in enumerate(self.model.at_limit) if hit
        )
        data = encode_status(
            PLANT_STATUS,
            self.status_counter.next(),
            self.node_state,
            int(self.fault),
            flags,
            self.monitor.counts.bad,
            self.stats.steps & 0xFFFF,
        )
        self._send(PLANT_STATUS.frame_id, data)

    def _send(self, frame_id: int, data: bytes) -> None:
        send_frame(self.bus, frame_id, data, "plant_sim")

    # --- loops -------------------------------------------------------------------------------

    def run(self, duration: float | None = None) -> None:
        """Serve until stopped (NodeCommand stop, SIGINT/SIGTERM) or ``duration`` passes."""
        start = self.clock()
        next_tick = start + self.period
        next_status = start
        self._send_state()
        while self.running and (duration is None or self.clock() - start < duration):
            now = self.clock()
            wait = next_tick - now if self.clock_mode is ClockMode.REALTIME else STATUS_PERIOD
            message = self.bus.recv(timeout=max(0.0, min(wait, next_status - now)))
            if message is not None:
                self.handle(message)
            now = self.clock()
            if self.clock_mode is ClockMode.REALTIME and now >= next_tick:
                self.on_period(now)
                next_tick += self.period * max(1, int((now - next_tick) / self.period) + 1)
            if now >= next_status:
                self._send_status()
                next_status += STATUS_PERIOD

    def stop(self) -> None:
        self.running = False


# ControllerStatus is only counted (checked, never acted on): the plant needs nothing from it.
_RECEIVED = {codec.frame_id for codec in (COMMAND, STEP, STOP, NODE_COMMAND, CONTROLLER_STATUS)}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="plant_sim",
        description="The SCARA plant simulator: integrates the joints under the commands it "
        "receives over CAN and answers with the joint state.",
    )
    add_node_arguments(parser, "real time on its own clock, or lockstep driven by StepSync")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument("--stats", type=Path, help="write counters as JSON here on exit")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    setup = open_node(args, "plant_sim")
    if setup is None:
        return 2
    node = PlantNode(setup.bus, setup.scenario, ClockMode(args.clock))
    stop_on_signals(node.stop)
    settle_memory()
    try:
        node.run(args.duration)
    finally:
        if args.stats:  # before closing the bus, which may take a while to flush
            report = {
                "stats": asdict(node.stats),
                "e2e": asdict(node.monitor.counts),
                "faults": int(node.fault),
                "state": node.node_state.name,
                "injected": asdict(setup.injector.counts) if setup.injector else None,
            }
            args.stats.write_text(json.dumps(report, indent=2) + "\n")
        setup.bus.shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
