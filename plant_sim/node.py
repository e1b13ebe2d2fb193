"""``plant_sim``: the plant simulator process. It owns a bus and integrates the joint model.

Real time: the plant runs on its own monotonic clock and integrates in whole periods. When a
valid command arrives it brings the joints up to the last whole period, answers at once with
that joint state, and applies the command from then on. It also integrates every period on
its own, and sends the state then too while no command comes, so a controller that starts
later finds it. Its drives brake to zero when no valid command has come for
``COMMAND_TIMEOUT``, also while the process itself was not scheduled: catching up after a
stall, it integrates the last command only until the brake would have acted.

Lockstep: time moves only on StepSync frames. Each one advances exactly one control period
under the command it names, and the plant answers (see the DBC's comment on StepSync).

Both modes: the joint limits are hard stops reported as faults; a collision of the tool with
the obstacle (ground truth: the obstacle grown by the tool radius) is reported in PlantStatus.
The obstacle is the world's (:mod:`protocol.world`): the scenario file's at start, then the one
the controller service sends over ISO-TP (WorldUpload) for the task in force; PlantStatus.World
says which. A reset brings the arm back to its start and clears the faults; the world stays.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import can

from plant_sim.model import PlantModel
from protocol.bus import enlarge_receive_buffer, receive_drops
from protocol.cli import number, quiet_on_closed_pipe
from protocol.codec import MessageCodec
from protocol.errors import ConfigError
from protocol.kinematics import forward
from protocol.messages import (
    COMMAND,
    CONTROLLER_STATUS,
    PLANT_STATUS,
    STATE,
    STEP,
    WORLD_FLOW,
    WORLD_UPLOAD,
    Counter,
    NodeId,
    NodeState,
    PlantFault,
    PlantFlag,
)
from protocol.node import ClockMode, Node, NodeSetup, add_node_arguments, node_main
from protocol.scenario import Scenario, load_scenario
from protocol.world import STARTUP_WORLD, World, read_world

COMMAND_TIMEOUT = 0.020
"""s without a valid command before the plant brakes to zero (real-time mode)."""
ZERO = (0.0, 0.0, 0.0)
_AT_STOP = ("THETA1_AT_STOP", "THETA2_AT_STOP", "D3_AT_STOP")


@dataclass(slots=True)
class PlantStats:
    steps: int = 0
    commands_applied: int = 0
    states_sent: int = 0
    collisions: int = 0
    command_timeouts: int = 0
    unknown_step_requests: int = 0
    worlds_received: int = 0
    worlds_refused: int = 0


class PlantNode(Node):
    """The plant's side of the wire around a :class:`PlantModel`."""

    name = "plant_sim"
    node_id = NodeId.PLANT
    status = PLANT_STATUS
    listens = (COMMAND, STEP, CONTROLLER_STATUS)  # ControllerStatus: checked and counted only
    Fault = PlantFault

    def __init__(
        self,
        bus: can.BusABC,
        scenario: Scenario,
        clock_mode: ClockMode,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(bus, clock)
        self.scenario = scenario
        self.clock_mode = clock_mode
        if clock_mode is ClockMode.LOCKSTEP:
            # Every StepSync counts: one dropped by a full receive queue (the default holds
            # about 950 frames) costs a live run a retry, but a replay that does not wait for
            # the plant (canplayer) its whole rest. A queue as large as the recorder's keeps
            # what arrives while the plant is not scheduled.
            enlarge_receive_buffer(bus)
        self.period = scenario.controller.period
        self.world = World.of(scenario, STARTUP_WORLD)
        self.obstacle = self.world.touched()
        self.stats = PlantStats()
        self._state_counter = Counter()
        self.worlds = self.add_link(WORLD_FLOW.frame_id, WORLD_UPLOAD.frame_id, "world")
        self._restart()

    def on_reset(self) -> None:
        """NodeCommand reset: start again, and say where the arm is."""
        self._restart()
        self._send_state()

    def _restart(self) -> None:
        """Back to the scenario's first waypoint, at rest, faults cleared (the world kept)."""
        self.model = PlantModel(
            self.scenario.robot, self.scenario.plant, position=self.scenario.initial_joints()
        )
        self.command: tuple[float, float, float] = ZERO
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

    def on_frame(
        self, codec: MessageCodec, counter: int, record: Any, message: can.Message
    ) -> None:
        if codec is COMMAND:
            self._on_command(counter, record)
        elif codec is STEP:
            self._on_step(record.CommandCounter, record.Tick)

    def emergency_stop(self) -> None:
        super().emergency_stop()
        self.command = ZERO

    def _on_command(self, counter: int, record: Any) -> None:
        if self.clock_mode is ClockMode.REALTIME:
            self._integrate_to(self.clock())
        if self.node_state is NodeState.ESTOP or not record.Enable:
            self.command = ZERO
        else:
            self.command = (record.Theta1Rate, record.Theta2Rate, record.D3Rate)
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

    def take_worlds(self) -> None:
        """The worlds completed since the last look: the last valid one is the plant's."""
        for payload in self.worlds.poll():
            try:
                world = read_world(payload)
            except ConfigError as error:
                self.stats.worlds_refused += 1
                self.log.warning("world refused: %s", error)
                continue
            self.world = world
            self.obstacle = world.touched()
            self.stats.worlds_received += 1
            self.log.info("world %d: %s", world.number, world.obstacle or "no obstacle")

    # --- the model ---------------------------------------------------------------------------

    def _advance(self, dt: float) -> None:
        self.model.advance(self.command, dt)
        self.stats.steps += 1
        if any(self.model.at_limit):
            self.enter_fault(PlantFault.JOINT_LIMIT)
        if self.obstacle is not None:
            x, y, z = forward(self.scenario.robot, *self.model.position)
            inside = self.obstacle.holds(x, y, z)
            if inside and not self.collided:
                self.stats.collisions += 1
            self.collided = inside
            if inside:
                self.fault |= PlantFault.COLLISION

    def _integrate_to(self, now: float) -> None:
        """Real time: advance the model in whole periods up to ``now``, braking on the way
        where the drives' watchdog would have (a plant process that was not scheduled for a
        while catches up with what the drives did meanwhile)."""
        while self.model_time + self.period <= now:
            self._watchdog(self.model_time)
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
            if self.command != ZERO:
                self.stats.command_timeouts += 1
            self.command = ZERO
            self.fault |= PlantFault.COMMAND_TIMEOUT
        else:
            self.fault &= ~PlantFault.COMMAND_TIMEOUT

    # --- frames out --------------------------------------------------------------------------

    def _send_state(self) -> None:
        """JointState1-3 with one alive counter: together they are one joint state."""
        counter = self._state_counter.next()
        self.send_together(
            [
                (
                    codec,
                    codec.Record(CommandEcho=self.command_echo, Position=p, Velocity=v),
                    counter,
                )
                for codec, p, v in zip(STATE, self.model.position, self.model.velocity, strict=True)
            ]
        )
        self.stats.states_sent += 1

    def reported(self) -> tuple[Any, ...]:
        """The world too: the controller service runs a task once the plant holds its world."""
        return (*super().reported(), self.world.number)

    def statuses(self) -> list[tuple[MessageCodec, Any]]:
        flags = PlantFlag(0)
        if self.collided:
            flags |= PlantFlag.COLLISION
        for name, hit in zip(_AT_STOP, self.model.at_limit, strict=True):
            if hit:
                flags |= PlantFlag[name]
        status = PLANT_STATUS.Record(
            State=self.node_state,
            FaultCode=int(self.fault),
            Flags=int(flags),
            BadFrames=min(self.monitor.counts.bad, 0xFFFF),
            World=self.world.number,
            Extra=self.stats.steps & 0xFF,
        )
        return [(PLANT_STATUS, status)]

    # --- loop ----------------------------------------------------------------------------------

    def run(self, duration: float | None = None) -> None:
        """Serve until stopped (NodeCommand stop, SIGINT/SIGTERM) or ``duration`` passes."""
        start = self.clock()
        next_tick = start + self.period
        self._send_state()
        while self.running and (duration is None or self.clock() - start < duration):
            now = self.clock()
            next_status = self._next_status
            wait = next_tick - now if self.clock_mode is ClockMode.REALTIME else next_status - now
            message = self.bus.recv(timeout=max(0.0, min(wait, next_status - now)))
            if message is not None:
                self.handle(message)
            self.take_worlds()
            now = self.clock()
            if self.clock_mode is ClockMode.REALTIME and now >= next_tick:
                self.on_period(now)
                next_tick += self.period * max(1, int((now - next_tick) / self.period) + 1)
            self.send_status_if_due(now)

    def result(self) -> dict[str, Any]:
        """``receive_drops``: frames the kernel dropped for want of room in the SocketCAN
        receive queue (None on another transport)."""
        return super().result() | {
            "stats": asdict(self.stats),
            "receive_drops": receive_drops(self.bus),
        }


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="plant_sim",
        description="The SCARA plant simulator: integrates the joints under the commands it "
        "receives over CAN and answers with the joint state.",
    )
    add_node_arguments(parser, "real time on its own clock, or lockstep driven by StepSync")
    parser.add_argument(
        "--duration", type=number(0.0, low_open=True), metavar="S", help="stop after S seconds"
    )
    return parser


def make(setup: NodeSetup) -> PlantNode:
    return PlantNode(setup.bus, setup.scenario, setup.clock_mode)


def run(node: PlantNode, args: argparse.Namespace) -> None:
    node.run(args.duration)


@quiet_on_closed_pipe
def main(argv: Sequence[str] | None = None) -> int:
    return node_main(build_parser(), argv, load_scenario, make, run)


if __name__ == "__main__":
    raise SystemExit(main())
