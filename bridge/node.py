"""``scara-bridge``: the robot's state on Zenoh for remote monitors, and the paper's GUI buttons
as remote commands.

Two sides that never wait for each other:

- the CAN side (this process's main thread) hears every frame (:class:`OperatorNode`), keeps
  the robot's view, and hands what is to be published to a bounded queue: when that queue is
  full the sample is dropped and counted, so a slow Zenoh side never stalls the CAN side;
- the Zenoh side (a publisher thread, and Zenoh's own threads for queries) publishes under
  ``scara/<robot>/`` (``protocol/keys.py``), answers a query on each state key with its
  latest value (a monitor that joins late sees the arm at once), holds a liveliness token per
  live process, and takes commands as queries on ``cmd/...``: checked (``bridge/commands.py``),
  forwarded over CAN, answered with the controller's own answer.

Joint state and TCP go out as they arrive, at most at their configured rate (100 Hz by
default); one that comes before its turn waits for it, a newer one replacing it, so the last
state before the arm stops is always published, and the first of an arm that starts to
move goes out at once (``bridge/rate.py``). The other keys go out on change.
Access control is the Zenoh router's (``config/zenoh/secure-router.json5``).

With ``--foxglove-port`` the same samples, the arm in 3D and (with ``--foxglove-commands``)
the commands are also served to Foxglove (``bridge/foxglove_server.py``); a command from
there takes the same checks (:meth:`Bridge.call`).
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

import can
import zenoh

from bridge.commands import (
    TASK_COMMANDS,
    MalformedCommandError,
    RefusedError,
    edit_task,
    parse_payload,
)
from bridge.foxglove_gate import FOXGLOVE_APP_ORIGINS, check_origin
from bridge.foxglove_server import FoxgloveServer, FoxgloveSettings
from bridge.operator import ANSWER_TIMEOUT, Answer, OperatorNode, Reply
from bridge.rate import RateLimit, StartOfMotion
from bridge.session import add_zenoh_arguments, endpoint_from_args
from bridge.view import Event
from controller.task_rules import load_task
from protocol.bus import add_bus_arguments, open_bus_from_args
from protocol.cli import add_verbosity, configure_logging, number, quiet_on_closed_pipe
from protocol.errors import ScaraError
from protocol.keys import (
    COMMANDS,
    EVERY_SAMPLE_KEYS,
    STATE_KEYS,
    alive_key,
    check_robot,
    command_key,
    state_key,
)
from protocol.messages import Request
from protocol.node import stop_on_signals
from protocol.realtime import yield_to_the_nodes
from protocol.scenario import Scenario, task_document
from protocol.zenoh_can.config import DEFAULT_HOST, check_host, close, is_loopback, warn_in_clear

QUEUE_SIZE = 256
"""Samples waiting for the Zenoh side before new ones are dropped."""
DEFAULT_RATES = {"joints": 100.0, "tcp": 100.0}
"""Hz at most per key; keys not named here go out on every change."""
MOTION_KEYS = ("joints", "tcp")
"""The keys whose sample goes out at once when the arm starts to move (``bridge/rate.py``)."""
STILL = 0.1
"""s the arm stands still before its next move is such news."""
STATUS_PERIOD = 0.1
"""s between two looks at whether the status changed (the nodes' status rate)."""
STEP = 0.005
"""s the CAN side waits for a frame before it looks at its timers again."""
CALL_TIMEOUT = ANSWER_TIMEOUT + 1.0
"""s a caller that waits for its reply (a Foxglove service) waits at most: the controller's
time to answer, and the CAN side's time to notice it did not."""


class Bridge:
    """Both sides of the bridge around an :class:`OperatorNode` and a Zenoh session."""

    def __init__(
        self,
        bus: can.BusABC,
        session: zenoh.Session,
        robot: str,
        base: Scenario,
        rates: dict[str, float],
        foxglove: FoxgloveSettings | None = None,
    ) -> None:
        self.robot = robot
        self.base = base
        self.session = session
        self.rates = rates
        self.running = True
        self.node = OperatorNode(bus, base, self._on_event, self._on_joint_state)
        self.log = self.node.log
        self._outbox: queue.Queue[tuple[str, Any]] = queue.Queue(QUEUE_SIZE)
        self._commands: queue.SimpleQueue[tuple[str, Any, Reply]] = queue.SimpleQueue()
        self.published = dict.fromkeys(STATE_KEYS, 0)
        self.dropped = dict.fromkeys(STATE_KEYS, 0)
        self._seq = dict.fromkeys(STATE_KEYS, 0)
        self._limits: dict[str, RateLimit[dict[str, Any]]] = {
            name: RateLimit(rate) for name, rate in rates.items() if rate
        }
        self._start_of_motion = StartOfMotion(STILL)
        self._last_payload: dict[str, dict[str, Any]] = {}
        self._latest: dict[str, bytes] = {}
        self._latest_lock = threading.Lock()
        self._alive: dict[str, Any] = {}
        """Liveliness tokens, owned by the publishing thread."""
        self._heard: set[str] = set()
        """The nodes whose tokens are (or are queued to be) declared: the CAN thread's."""
        self._task_published: Scenario | None = None
        self.foxglove = (  # first: a port taken fails before anything is declared
            None
            if foxglove is None
            else FoxgloveServer(
                foxglove,
                base.robot,
                lambda: self.node.task,
                self.call if foxglove.commands else None,
            )
        )
        self._publishers = {
            name: session.declare_publisher(
                state_key(robot, name),
                congestion_control=zenoh.CongestionControl.BLOCK
                if name in EVERY_SAMPLE_KEYS
                else zenoh.CongestionControl.DROP,
                express=True,
            )
            for name in STATE_KEYS
        }
        self._queryables = [
            session.declare_queryable(state_key(robot, name), self._latest_reply(name))
            for name in STATE_KEYS
        ] + [
            session.declare_queryable(command_key(robot, name), self._command_query(name))
            for name in COMMANDS
        ]
        self._alive["bridge"] = session.liveliness().declare_token(alive_key(robot, "bridge"))
        self._publisher = threading.Thread(target=self._publish_loop, name="publish", daemon=True)
        self._publisher.start()

    # --- the CAN side ----------------------------------------------------------------------

    def run(self) -> None:
        """Serve until stopped: frames, commands, timers."""
        next_status = time.monotonic()
        while self.running:
            self.node.step(STEP)
            self._run_commands()
            now = time.monotonic()
            for name, limit in self._limits.items():
                waited = limit.due(now)
                if waited is not None:
                    self._send(name, waited)
            if now >= next_status:
                next_status = now + STATUS_PERIOD
                self._offer("status", self.node.view.status_payload(time.time(), self._counters()))
                self._offer_task()
                self._watch_alive()

    def _on_joint_state(self, received: float) -> None:
        view = self.node.view
        joints = view.joints_payload()
        started = joints is not None and self._start_of_motion.moved(
            time.monotonic(), joints["position"]
        )
        for name, payload in (
            ("joints", joints),
            ("tcp", view.tcp_payload()),
            ("coordination", view.coordination_payload()),
        ):
            if payload is not None:
                self._offer(name, payload, news=started and name in MOTION_KEYS)

    def _on_event(self, event: Event, received: float) -> None:
        name, detail = event
        self.log.info("event %s %s", name, detail)
        self._offer("events", {"t": received, "event": name, "detail": detail})

    def _offer_task(self) -> None:
        task = self.node.task
        if task is not None and task is not self._task_published:
            self._task_published = task
            self._offer("scenario", task_document(task))

    def _offer(self, name: str, payload: dict[str, Any], news: bool = False) -> None:
        """Send ``payload`` for ``name`` if its rate allows (else it waits) or it is news,
        or, for a key without a rate, if it changed."""
        limit = self._limits.get(name)
        if limit is not None:
            allowed = limit.offer(time.monotonic(), payload, news)
            if allowed is not None:
                self._send(name, allowed)
            return
        content = {k: v for k, v in payload.items() if k != "t"}
        if name != "events" and self._last_payload.get(name) == content:
            return
        self._last_payload[name] = content
        self._send(name, payload)

    def _send(self, name: str, payload: dict[str, Any]) -> None:
        """Queue ``payload`` for the Zenoh side, numbered, or drop and count it when full."""
        if name != "scenario":
            payload = payload | {"seq": self._seq[name]}
        try:
            self._outbox.put_nowait((name, payload))
        except queue.Full:
            self.dropped[name] += 1
            return
        self._seq[name] += 1

    def _counters(self) -> dict[str, Any]:
        return {
            "frames": self.node.frames,
            "bad_frames": self.node.monitor.counts.bad,
            "published": dict(self.published),
            "dropped": dict(self.dropped),
            "rates_hz": dict(self.rates),
        }

    def _watch_alive(self) -> None:
        """A liveliness token per node while its status frames keep coming."""
        view = self.node.view
        wall = time.time()
        for process, seen in (("controller", view.controller), ("plant", view.plant)):
            alive = seen.alive(wall)
            if alive == (process in self._heard):
                continue
            if not self._outbox_control(("alive", (process, alive))):
                continue  # the next look at the nodes tries again
            if alive:
                self._heard.add(process)
                if process == "controller":  # just heard (or back): ask for the task it holds
                    self.node.request(Request.DESCRIBE, lambda answer: None)
            else:
                self._heard.discard(process)

    def _outbox_control(self, item: tuple[str, Any]) -> bool:
        try:
            self._outbox.put_nowait(item)
        except queue.Full:
            return False
        return True

    # --- commands ----------------------------------------------------------------------------

    def _command_query(self, command: str) -> Any:
        key = command_key(self.robot, command)

        def on_query(query: zenoh.Query) -> None:
            """Zenoh thread: check the command, then leave it to the CAN side."""
            if str(query.key_expr) != key:  # a wildcard reaches every command: none was meant
                _refuse_malformed(query, "key", f"name one command, such as {key}")
                return
            payload = query.payload.to_bytes() if query.payload is not None else b""
            try:
                work = self.check_command(command, payload)
            except MalformedCommandError as error:
                _refuse_malformed(query, error.field, error.message)
                return
            except RefusedError as refusal:
                query.reply(query.key_expr, json.dumps(refusal.reply()).encode())
                _drop(query)
                return
            self._commands.put((command, work, _replier(query)))

        return on_query

    def check_command(self, command: str, payload: bytes) -> Any:
        """What ``command`` with ``payload`` asks the CAN side to do, checked: the one path
        of every command, from Zenoh or Foxglove. :class:`MalformedCommandError` or
        :class:`RefusedError` if it must not reach the bus."""
        body = parse_payload(command, payload)
        if command not in TASK_COMMANDS:
            return body
        if self.node.view.controller.state in ("running", "hold"):
            raise RefusedError("busy", message="the controller is running a task")
        return edit_task(command, body, self.node.task, self.base)

    def call(self, command: str, payload: bytes) -> dict[str, Any]:
        """A command from a caller that waits for its reply (a Foxglove service): the reply
        a Zenoh query gets; :class:`MalformedCommandError` if the payload is malformed."""
        try:
            work = self.check_command(command, payload)
        except RefusedError as refusal:
            return refusal.reply()
        answers: queue.SimpleQueue[Answer] = queue.SimpleQueue()
        self._commands.put((command, work, answers.put))
        try:
            return reply_body(answers.get(timeout=CALL_TIMEOUT))
        except queue.Empty:  # the CAN side is stuck: the controller cannot have answered
            return reply_body(Answer(False, "no_answer"))

    def _run_commands(self) -> None:
        """CAN side: forward the checked commands; each query is answered when the
        controller answers (or does not, in time)."""
        while True:
            try:
                command, work, reply = self._commands.get_nowait()
            except queue.Empty:
                return
            if command in TASK_COMMANDS:
                self.node.set_task(work, reply)
            elif command == "estop":
                self.node.estop()
                reply(Answer(True, "none"))
            else:
                self.node.request(Request[command.upper()], reply)

    # --- the Zenoh side ----------------------------------------------------------------------

    def _publish_loop(self) -> None:
        while self.running:
            try:
                name, payload = self._outbox.get(timeout=0.1)
            except queue.Empty:
                continue
            if name == "alive":
                self._set_alive(*payload)
                continue
            data = json.dumps(payload).encode()
            with self._latest_lock:
                self._latest[name] = data
            try:
                self._publishers[name].put(data)
                self.published[name] += 1
            except zenoh.ZError as error:
                self.dropped[name] += 1
                self.log.warning("%s not published: %s", name, error)
            if self.foxglove is not None:
                self.foxglove.on_sample(name, payload)

    def _set_alive(self, process: str, alive: bool) -> None:
        if alive:
            self._alive[process] = self.session.liveliness().declare_token(
                alive_key(self.robot, process)
            )
        else:
            self._alive.pop(process).undeclare()

    def _latest_reply(self, name: str) -> Any:
        def on_query(query: zenoh.Query) -> None:
            """Zenoh thread: the latest value of the key, if there is one yet."""
            with self._latest_lock:
                data = self._latest.get(name)
            if data is not None:
                query.reply(query.key_expr, data)
            _drop(query)

        return on_query

    def stop(self) -> None:
        """End :meth:`run` (from a signal handler)."""
        self.running = False

    def close(self) -> None:
        self.running = False
        self._publisher.join(2.0)
        if self.foxglove is not None:
            self.foxglove.stop()
        for token in self._alive.values():
            token.undeclare()
        entities: list[Any] = [*self._queryables, *self._publishers.values()]
        for entity in entities:
            entity.undeclare()


def _refuse_malformed(query: zenoh.Query, field: str, message: str) -> None:
    """The error reply (``error.schema.json``): nothing was done."""
    error = {"error": "malformed", "field": field, "message": message}
    query.reply_err(json.dumps(error).encode())
    _drop(query)


def _drop(query: Any) -> None:
    """Finish a query (its replies are complete); zenoh's stub leaves ``drop`` unannotated."""
    query.drop()


def reply_body(answer: Answer) -> dict[str, Any]:
    """The reply to a command (``reply.schema.json``)."""
    return {"accepted": answer.accepted, "reason": answer.reason}


def _replier(query: zenoh.Query) -> Reply:
    def reply(answer: Answer) -> None:
        query.reply(query.key_expr, json.dumps(reply_body(answer)).encode())
        _drop(query)

    return reply


# --- the process ---------------------------------------------------------------------------


def parse_rate(text: str) -> tuple[str, float]:
    """``KEY=HZ`` for ``--rate``."""
    key, separator, value = text.partition("=")
    if not separator or key not in STATE_KEYS:
        raise argparse.ArgumentTypeError(
            f"{text!r}: use KEY=HZ with KEY one of {', '.join(STATE_KEYS)}"
        )
    return key, number(0.0, 1000.0)(value)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-bridge",
        description="Publish the robot's state on Zenoh under scara/<robot>/ and take the "
        "operator's commands as Zenoh queries on scara/<robot>/cmd/...",
    )
    parser.add_argument(
        "scenario",
        nargs="?",
        help="scenario file or name for the robot's parameters (default: the packaged ones)",
    )
    parser.add_argument(
        "--rate",
        action="append",
        type=parse_rate,
        default=[],
        metavar="KEY=HZ",
        help="most samples per second of a key (default joints=100, tcp=100; 0: every change)",
    )
    add_zenoh_arguments(parser)
    group = parser.add_argument_group(
        "Foxglove (the arm in 3D, the state and, if asked, the commands in the Foxglove app)"
    )
    group.add_argument(
        "--foxglove-port",
        type=number(1, 65535, integer=True),
        metavar="PORT",
        help="serve Foxglove's WebSocket protocol on PORT (default: no Foxglove server); "
        "open ws://HOST:PORT in Foxglove with config/foxglove/scara.json",
    )
    group.add_argument(
        "--foxglove-host",
        default=DEFAULT_HOST,
        metavar="ADDRESS",
        help="address the Foxglove server listens on (default %(default)s; another than "
        "loopback needs --allow-remote)",
    )
    group.add_argument(
        "--foxglove-commands",
        action="store_true",
        help="also take the commands (waypoints, obstacle, mode, reset, run, stop, estop) as "
        "Foxglove services; without it Foxglove is read-only (its protocol has no users: "
        "anyone who reaches the port may call them), refused on an address not on loopback",
    )
    group.add_argument(
        "--foxglove-allow-origin",
        action="append",
        metavar="ORIGIN",
        help="a web origin whose pages may connect (repeatable; default: the Foxglove app's, "
        f"{', '.join(FOXGLOVE_APP_ORIGINS)}, and none else: a connection from another, or "
        "without one, is refused)",
    )
    add_bus_arguments(parser)
    add_verbosity(parser)
    return parser


def foxglove_from_args(args: argparse.Namespace) -> FoxgloveSettings | None:
    """The Foxglove server the arguments ask for; ``ValueError`` if they are wrong."""
    if args.foxglove_port is None:
        if args.foxglove_commands:
            raise ValueError("--foxglove-commands needs --foxglove-port")
        return None
    try:
        host = check_host(
            args.foxglove_host, allow_remote=args.allow_remote, name="--foxglove-host"
        )
    except can.CanInitializationError as error:
        raise ValueError(str(error)) from None
    if args.foxglove_commands:
        try:
            check_host(host, allow_remote=False)
        except can.CanInitializationError:
            raise ValueError(
                f"--foxglove-commands on {host}: Foxglove's protocol has no users, so commands "
                "are served on loopback only (a remote operator commands through the secure "
                "router as the operator user)"
            ) from None
    origins = tuple(args.foxglove_allow_origin or FOXGLOVE_APP_ORIGINS)
    for origin in origins:
        check_origin(origin)
    return FoxgloveSettings(host, args.foxglove_port, args.foxglove_commands, origins)


@quiet_on_closed_pipe
def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose)
    yield_to_the_nodes()
    try:
        robot = check_robot(args.robot)
        base = load_task(args.scenario) if args.scenario else Scenario("bridge", (), None)
        endpoint = endpoint_from_args(args, "scara-bridge")
        foxglove = foxglove_from_args(args)
        bus = open_bus_from_args(args)
    except (ScaraError, can.CanError, ValueError, OSError) as error:
        print(f"scara-bridge: {error}", file=sys.stderr)
        return 2
    try:
        session = endpoint.open()
    except zenoh.ZError as error:
        bus.shutdown()
        print(f"scara-bridge: no Zenoh session at {endpoint}: {error}", file=sys.stderr)
        return 2
    try:
        bridge = Bridge(bus, session, robot, base, DEFAULT_RATES | dict(args.rate), foxglove)
    except RuntimeError as error:  # the SDK's: the Foxglove port is taken
        close(session)
        bus.shutdown()
        print(f"scara-bridge: no Foxglove server: {error}", file=sys.stderr)
        return 2

    stop_on_signals(bridge.stop)
    if foxglove is not None:
        if not is_loopback(foxglove.host):
            warn_in_clear("scara-bridge", "the robot's state on the Foxglove port")
        access = "with commands" if foxglove.commands else "read-only"
        print(
            f"scara-bridge: Foxglove on ws://{foxglove.host}:{foxglove.port} ({access})",
            file=sys.stderr,
        )
    print(f"scara-bridge: {robot} on scara/{robot}/ (Ctrl-C to stop)", file=sys.stderr, flush=True)
    try:
        bridge.run()
    finally:
        bridge.close()
        close(session)
        bus.shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
