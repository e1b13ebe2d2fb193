"""The disturbances of a schedule, done to the live stack at their times: processes paused
and killed, the bus flooded with foreign IDs, commands at the worst times (the wire faults
are each node's own, set as it starts: ``stack.py``).

Each disturbance runs in a thread of its own, so that a long one (a pause, a flood, a burst
waiting for replies) does not hold the next one up; what it did and when it ended is kept
for the report, which measures from that end how long the system took to be back.
"""

from __future__ import annotations

import random
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import can

from protocol.codec import WIRE
from protocol.zenoh_can.config import DEFAULT_HOST
from soak.drive import Driver, Operator
from soak.schedule import FLOOD_RATE, Disturbance, Kind
from soak.stack import Stack

FOREIGN_IDS = tuple(i for i in range(0x780, 0x7F0) if i not in WIRE.defined_ids)
"""Standard IDs of another system on the bus (the DBC defines none of them)."""
BURST_GAP = 0.05
"""s between the commands of a burst."""
READ_ONLY_WAIT = 1.0
"""s a read-only user's command waits for the reply that must not come."""


@dataclass
class Done:
    """A disturbance as done: when it began and ended (monotonic s), and what it met."""

    disturbance: Disturbance
    began: float
    ended: float = 0.0
    replies: list[str] = field(default_factory=list)
    error: str = ""


class Disturber:
    """Walks a schedule from ``start`` (monotonic s) and does each disturbance at its time."""

    def __init__(self, stack: Stack, operator: Operator, driver: Driver, seed: int) -> None:
        self.stack = stack
        self.operator = operator
        self.driver = driver
        self.seed = seed
        self.done: list[Done] = []
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()

    def run(self, disturbances: tuple[Disturbance, ...], start: float) -> None:
        for number, disturbance in enumerate(disturbances):
            if self._stop.wait(max(0.0, start + disturbance.at - time.monotonic())):
                return
            done = Done(disturbance, time.monotonic())
            self.done.append(done)
            thread = threading.Thread(
                target=self._do, args=(done, number), name=f"disturb-{number}", daemon=True
            )
            self._threads.append(thread)
            thread.start()

    def _do(self, done: Done, number: int) -> None:
        disturbance = done.disturbance
        try:
            self._act(disturbance, done, number)
        except Exception as error:  # kept for the report, never lost
            done.error = f"{type(error).__name__}: {error}"
        done.ended = time.monotonic()

    def _act(self, disturbance: Disturbance, done: Done, number: int) -> None:
        kind = disturbance.kind
        if kind is Kind.PAUSE:
            self.stack.pause(disturbance.target, disturbance.duration)
        elif kind is Kind.KILL:
            self.stack.restart(disturbance.target)
        elif kind is Kind.FLOOD:
            self._flood(disturbance.duration, random.Random(f"soak-{self.seed}-flood-{number}"))
        elif kind is Kind.RUN_TWICE:
            self._commands(done, [("run", None), ("run", None)])
        elif kind is Kind.OBSTACLE_IN_RUN:
            self._commands(done, [("obstacle", self.driver.current_obstacle())])
        elif kind is Kind.RESET:
            self._commands(done, [("reset", None)])
        elif kind is Kind.ESTOP_BURST:
            self._commands(done, [("estop", None)] * disturbance.count)
        elif kind is Kind.STOP_BURST:
            self._commands(done, [("stop", None)] * disturbance.count)
        elif kind is Kind.READ_ONLY:
            names = ("run", "estop", "reset", "stop")
            self._commands(
                done, [(names[i % len(names)], None) for i in range(disturbance.count)], True
            )

    def _commands(
        self, done: Done, commands: list[tuple[str, Any]], read_only: bool = False
    ) -> None:
        """Send ``commands`` a burst gap apart; keep each reply's reason (``no_reply``)."""
        for name, body in commands:
            reply = self.operator.command(
                name, body, read_only=read_only, timeout=READ_ONLY_WAIT if read_only else 5.0
            )
            reason = "no_reply" if reply is None else str(reply.get("reason", "error"))
            done.replies.append(f"{name}:{reason}")
            time.sleep(BURST_GAP)

    def _flood(self, duration: float, draw: random.Random) -> None:
        """Foreign frames at :data:`FLOOD_RATE` for ``duration`` s, standard and extended."""
        with can.Bus(
            interface="zenoh",
            channel=self.stack.args.channel,
            host=DEFAULT_HOST,
            port=self.stack.can_port,
        ) as bus:
            end = time.monotonic() + duration
            sent = 0
            begin = time.monotonic()
            while time.monotonic() < end:
                extended = draw.random() < 0.3
                frame_id = draw.randrange(2**29) if extended else draw.choice(FOREIGN_IDS)
                bus.send(
                    can.Message(
                        arbitration_id=frame_id,
                        is_extended_id=extended,
                        data=draw.randbytes(draw.randint(0, 8)),
                    )
                )
                sent += 1
                ahead = begin + sent / FLOOD_RATE - time.monotonic()
                if ahead > 0:
                    time.sleep(ahead)

    def stop(self) -> None:
        """No further disturbance; wait for those under way (a pause ends with SIGCONT)."""
        self._stop.set()
        for thread in self._threads:
            thread.join(10.0)
