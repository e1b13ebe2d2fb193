"""``scara-monitor``: the robot's state live in a terminal, and the paper's buttons as keys.

It joins a Zenoh router as a client (loopback by default, no scouting), subscribes to the
robot's state keys, asks their queryables once so it shows the arm at once, and draws
joints, TCP, a top view of the path and the obstacle, the coordination (k_T, k_C, d_L, d_R,
beta), node states, faults, rates and the latency from the bridge's CAN receive to here.
Keys send the commands; with a read-only user the router refuses them and the reply says so.

``--json`` prints one JSON line per sample instead (``{"key", "received", "payload"}``), for
scripts. :class:`MonitorModel` is the pure part: what was heard, turned into text.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, ClassVar

import zenoh
from textual.app import App, ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, Vertical
from textual.widgets import Footer, Header, RichLog, Static

from bridge.session import ZenohEndpoint, add_zenoh_arguments, endpoint_from_args
from protocol.cli import (
    add_verbosity,
    configure_logging,
    interruptible,
    number,
    quiet_on_closed_pipe,
)
from protocol.errors import ScaraError
from protocol.keys import STATE_KEYS, check_robot, command_key, state_key
from protocol.scenario import Scenario, load_scenario, task_document

RATE_WINDOW = 2.0
"""s of samples behind a key's rate."""
PATH_POINTS = 3000
"""TCP positions kept for the top view (30 s at 100 Hz)."""
EVENTS_SHOWN = 12
PANELS = ("arm", "nodes", "top", "events")
COMMAND_TIMEOUT = 5.0
"""s a command may wait for its reply (the bridge waits 2 s for the controller)."""


class MonitorModel:
    """What the monitor has heard, safe to feed from Zenoh's threads and read from the UI."""

    def __init__(self, clock: Callable[[], float] = time.time) -> None:
        self.clock = clock
        self.latest: dict[str, dict[str, Any]] = {}
        self.path: deque[tuple[float, float]] = deque(maxlen=PATH_POINTS)
        self.events: deque[dict[str, Any]] = deque(maxlen=EVENTS_SHOWN)
        self._arrivals: dict[str, deque[float]] = {name: deque() for name in STATE_KEYS}
        self._latency: dict[str, float] = {}
        self._lock = threading.Lock()

    def on_sample(self, name: str, payload: dict[str, Any], received: float) -> None:
        with self._lock:
            self.latest[name] = payload
            arrivals = self._arrivals[name]
            arrivals.append(received)
            while arrivals and arrivals[0] < received - RATE_WINDOW:
                arrivals.popleft()
            if "t" in payload:
                self._latency[name] = received - payload["t"]
            if name == "tcp":
                self.path.append((payload["x"], payload["y"]))
            elif name == "events":
                self.events.append(payload)

    def rate(self, name: str) -> float:
        """Samples per second of ``name`` over the last :data:`RATE_WINDOW`."""
        with self._lock:
            recent = [t for t in self._arrivals[name] if t >= self.clock() - RATE_WINDOW]
        return len(recent) / RATE_WINDOW

    # --- text ------------------------------------------------------------------------------

    def arm_text(self) -> str:
        with self._lock:
            joints, tcp, coordination = (self.latest.get(k) for k in STATE_KEYS[:3])
        lines = ["ARM"]
        if joints is None:
            lines.append("  joints: nothing heard yet")
        else:
            q1, q2, d3 = joints["position"]
            v1, v2, v3 = joints["velocity"]
            lines += [
                f"  theta1 {math.degrees(q1):8.2f} deg  {math.degrees(v1):8.2f} deg/s",
                f"  theta2 {math.degrees(q2):8.2f} deg  {math.degrees(v2):8.2f} deg/s",
                f"  d3     {d3 * 1000:8.1f} mm   {v3 * 1000:8.1f} mm/s",
            ]
        if tcp is not None:
            lines.append(f"  TCP  x {tcp['x']:.4f}  y {tcp['y']:.4f}  z {tcp['z']:.4f} m")
        lines.append("COORDINATION")
        if coordination is None:
            lines.append("  nothing heard yet")
        else:
            c = coordination
            lines += [
                f"  k_T {c['k_t']:.3f}  k_C {c['k_c']:.3f}  ({c['behaviour']})",
                f"  d_L {c['d_left']:.3f} m  d_R {c['d_right']:.3f} m",
                f"  beta {math.degrees(c['beta']):7.2f} deg  side {c['side']}",
            ]
        return "\n".join(lines)

    def nodes_text(self) -> str:
        with self._lock:
            status = self.latest.get("status")
            scenario = self.latest.get("scenario")
            latency = dict(self._latency)
        lines = ["NODES"]
        if status is None:
            lines.append("  no status yet (is the bridge running?)")
        else:
            for name in ("controller", "plant"):
                node = status[name]
                alive = node["state"] if node["alive"] else "SILENT"
                faults = ",".join(node["faults"]) or "-"
                lines.append(f"  {name:<10} {alive:<9} faults {faults}  bad {node['bad_frames']}")
            controller = status["controller"]
            lines.append(
                f"  mode {controller['mode']}  progress {controller['progress']} %  "
                f"waypoints {controller['waypoints_reached']}  holds {controller['holds']}"
            )
            lines.append(
                f"  loop: misses {controller['deadline_misses']}  "
                f"late max {controller['lateness_max_us']} us"
            )
            dropped = sum(status["bridge"]["dropped"].values())
            lines.append(f"  bridge: {status['bridge']['frames']} frames, {dropped} dropped")
        if scenario is not None:
            lines.append(f"TASK {scenario['name']}: {len(scenario['waypoints'])} waypoints")
        lines.append("RATES, LATENCY (bridge CAN receive to here)")
        for name in ("joints", "tcp", "coordination", "status"):
            delay = latency.get(name)
            shown = "-" if delay is None else f"{delay * 1000:6.2f} ms"
            lines.append(f"  {name:<13}{self.rate(name):6.1f} Hz  {shown}")
        return "\n".join(lines)

    def events_text(self) -> str:
        with self._lock:
            events = list(self.events)
        lines = ["EVENTS"]
        for event in events:
            stamp = time.strftime("%H:%M:%S", time.localtime(event["t"]))
            detail = " ".join(f"{k}={v}" for k, v in event["detail"].items())
            lines.append(f"  {stamp} {event['event']} {detail}")
        return "\n".join(lines)

    def top_view(self, width: int = 44, height: int = 18) -> str:
        """The XY plane seen from above: path ``.``, obstacle ``#``, waypoints ``1``..,
        TCP ``@``; x to the right, y up, equal scale (a terminal cell is twice as tall)."""
        with self._lock:
            path = list(self.path)
            scenario = self.latest.get("scenario")
        waypoints = [(w["x"], w["y"]) for w in scenario["waypoints"]] if scenario else []
        obstacle = scenario.get("obstacle") if scenario else None
        points = path + waypoints
        if obstacle is not None:
            reach = obstacle["long_diameter"] / 2
            points += [(obstacle["x"] - reach, obstacle["y"] - reach)]
            points += [(obstacle["x"] + reach, obstacle["y"] + reach)]
        if not points:
            points = [(0.0, -0.4), (0.6, 0.4)]
        xs, ys = [p[0] for p in points], [p[1] for p in points]
        span = max(max(xs) - min(xs), (max(ys) - min(ys)) * width / (2 * height), 0.05) * 1.1
        x0 = (max(xs) + min(xs)) / 2 - span / 2
        y0 = (max(ys) + min(ys)) / 2 - span * height / width
        cell = span / width  # metres per column; a row is two columns tall
        grid = [[" "] * width for _ in range(height)]

        def put(x: float, y: float, mark: str) -> None:
            column, row = int((x - x0) / cell), height - 1 - int((y - y0) / (2 * cell))
            if 0 <= column < width and 0 <= row < height:
                grid[row][column] = mark

        if obstacle is not None:
            yaw = math.radians(obstacle["yaw_deg"])
            for row in range(height):
                for column in range(width):
                    dx = x0 + (column + 0.5) * cell - obstacle["x"]
                    dy = y0 + (height - row - 0.5) * 2 * cell - obstacle["y"]
                    u = dx * math.cos(yaw) + dy * math.sin(yaw)
                    v = -dx * math.sin(yaw) + dy * math.cos(yaw)
                    semi_long, semi_short = obstacle["long_diameter"], obstacle["short_diameter"]
                    if (2 * u / semi_long) ** 2 + (2 * v / semi_short) ** 2 <= 1:
                        grid[row][column] = "#"
        for x, y in path:
            put(x, y, ".")
        for index, (x, y) in enumerate(waypoints):
            put(x, y, str(index + 1)[-1])
        if path:
            put(*path[-1], "@")
        return "\n".join("".join(row) for row in grid)


def subscribe(
    session: zenoh.Session, robot: str, on_sample: Callable[[str, dict[str, Any], float], None]
) -> list[Any]:
    """Subscribe to every state key (one subscriber each, as the secure router's rules name
    them), then fill in the latest values from the queryables."""

    def handler(name: str) -> Callable[[zenoh.Sample], None]:
        def on_zenoh_sample(sample: zenoh.Sample) -> None:
            received = time.time()
            try:
                payload = json.loads(sample.payload.to_bytes())
            except ValueError:
                return  # not the bridge's JSON: nothing to show
            on_sample(name, payload, received)

        return on_zenoh_sample

    subscribers = [
        session.declare_subscriber(state_key(robot, name), handler(name)) for name in STATE_KEYS
    ]
    for name in STATE_KEYS:
        if name == "events":
            continue  # past events are not kept: the queryable has none
        for reply in session.get(state_key(robot, name), timeout=2.0):
            if reply.ok is not None:
                handler(name)(reply.ok)
    return subscribers


def send_command(session: zenoh.Session, robot: str, name: str, body: Any) -> str:
    """Send a command; the reply as one line of text (or why there was none)."""
    payload = None if body is None else json.dumps(body)
    replies = list(session.get(command_key(robot, name), payload=payload, timeout=COMMAND_TIMEOUT))
    if not replies:
        return f"{name}: no reply (not authorised to command, or no bridge)"
    reply = replies[0]
    if reply.ok is not None:
        return f"{name}: {reply.ok.payload.to_string()}"
    error = reply.err
    return f"{name}: error {error.payload.to_string() if error is not None else '?'}"


class MonitorApp(App[None]):
    """The dashboard: three panels, an event list and the command keys."""

    TITLE = "scara-monitor"
    CSS = """
    #left { width: 1fr; }
    #right { width: 1fr; }
    Static { padding: 0 1; }
    #log { height: 8; border-top: solid $accent; }
    """
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("w", "command('waypoints')", "Set waypoints"),
        Binding("o", "command('obstacle')", "Set obstacle"),
        Binding("m", "command('mode')", "Mode"),
        Binding("r", "command('run')", "Run"),
        Binding("x", "command('reset')", "Reset"),
        Binding("s", "command('stop')", "Stop"),
        Binding("e", "command('estop')", "E-stop"),
        Binding("q", "quit", "Quit"),
    ]

    def __init__(self, session: zenoh.Session, robot: str, task: Scenario) -> None:
        super().__init__()
        self.session = session
        self.robot = robot
        self.scenario = task
        self.model = MonitorModel()
        self.replies: list[str] = []
        self._subscribers: list[Any] = []

    def compose(self) -> ComposeResult:
        yield Header()
        with Horizontal():
            with Vertical(id="left"):
                yield Static(id="arm", markup=False)
                yield Static(id="nodes", markup=False)
            with Vertical(id="right"):
                yield Static(id="top", markup=False)
                yield Static(id="events", markup=False)
        yield RichLog(id="log", markup=False)
        yield Footer()

    def on_mount(self) -> None:
        self.sub_title = f"scara/{self.robot}  task keys w/o: {self.scenario.name}"
        # held, not looked up on each refresh: a refresh may come while the app closes
        self._panels = {name: self.query_one(f"#{name}", Static) for name in PANELS}
        self._replies_log = self.query_one("#log", RichLog)
        self.run_worker(self._subscribe, thread=True)
        self.set_interval(0.1, self.refresh_panels)

    def _subscribe(self) -> None:
        self._subscribers = subscribe(self.session, self.robot, self.model.on_sample)

    def refresh_panels(self) -> None:
        model = self.model
        self._panels["arm"].update(model.arm_text())
        self._panels["nodes"].update(model.nodes_text())
        self._panels["top"].update("TOP VIEW\n" + model.top_view())
        self._panels["events"].update(model.events_text())

    def action_command(self, name: str) -> None:
        document = task_document(self.scenario)
        body: Any = None
        if name == "waypoints":
            body = {"waypoints": document["waypoints"]}
        elif name == "obstacle":
            body = {"obstacle": document.get("obstacle")}
        elif name == "mode":
            status = self.model.latest.get("status")
            now = status["controller"]["mode"] if status else "conventional"
            body = {"mode": "conventional" if now == "fuzzy" else "fuzzy"}

        def send() -> None:
            line = send_command(self.session, self.robot, name, body)
            self.call_from_thread(self._show_reply, line)

        self.run_worker(send, thread=True, group="commands")

    def _show_reply(self, line: str) -> None:
        self.replies.append(line)
        self._replies_log.write(line)


def print_json_lines(
    session: zenoh.Session, robot: str, count: int | None, duration: float | None
) -> int:
    """``--json``: one line per sample until ``count`` samples or ``duration`` s (or Ctrl-C)."""
    done = threading.Event()
    printed = 0
    lock = threading.Lock()

    def on_sample(name: str, payload: dict[str, Any], received: float) -> None:
        nonlocal printed
        with lock:
            if done.is_set():
                return
            line = json.dumps({"key": name, "received": received, "payload": payload})
            sys.stdout.write(line + "\n")
            sys.stdout.flush()
            printed += 1
            if count is not None and printed >= count:
                done.set()

    subscribers = subscribe(session, robot, on_sample)
    try:
        done.wait(duration)
    except KeyboardInterrupt:
        pass
    finally:
        done.set()
        for subscriber in subscribers:
            subscriber.undeclare()
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-monitor",
        description="Watch and command a SCARA through its Zenoh bridge, in a terminal.",
        epilog="keys: w waypoints, o obstacle, m mode, r run, x reset, s stop, e e-stop, q quit",
    )
    add_zenoh_arguments(parser)
    parser.add_argument(
        "--task",
        default="reference",
        help="scenario file or name whose waypoints and obstacle the w and o keys send "
        "(default %(default)s)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON line per sample")
    parser.add_argument(
        "--count", type=number(1, 10**9, integer=True), help="--json: stop after this many"
    )
    parser.add_argument("--duration", type=number(0.0, 1e9), help="--json: stop after s")
    add_verbosity(parser)
    return parser


@quiet_on_closed_pipe
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose)
    interruptible()
    try:
        check_robot(args.robot)
        endpoint: ZenohEndpoint = endpoint_from_args(args, "scara-monitor")
        task = load_scenario(args.task)
    except (ValueError, OSError, ScaraError) as error:
        print(f"scara-monitor: {error}", file=sys.stderr)
        return 2
    try:
        session = endpoint.open()
    except zenoh.ZError as error:
        print(f"scara-monitor: cannot join {endpoint}: {error}", file=sys.stderr)
        return 1
    try:
        if args.json:
            return print_json_lines(session, args.robot, args.count, args.duration)
        MonitorApp(session, args.robot, task).run()
        return 0
    finally:
        session.close()  # type: ignore[no-untyped-call]


if __name__ == "__main__":
    sys.exit(main())
