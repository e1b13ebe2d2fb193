"""GUI benchmark: what ``scara-gui``'s page draws, how soon a press of run shows, and what the
GUI costs the controller.

Plant, controller (service, with ``--out``) and bridge as processes on CAN-over-Zenoh, with
the reference task. Runs alternate, side by side in one sitting: with ``scara-gui`` joined to
the same router and two pages open in headless Chromium (Debian's, as the browser tests:
``tools/browser-setup``; WebGL in software), and without them (started by a Zenoh query).

1. **Page rate**: frames each page drew per second during a run (the page's own count: a
   frame is drawn when an update has come since the last one), over the run's first seconds.
2. **Run to first move**: in the page, the time from pressing its run button to the browser
   frame that first draws the arm away from where it stood (``performance.now()`` on both
   ends: one clock). The path: page, WebSocket, scara-gui, Zenoh query, bridge, CAN,
   controller, plant, CAN, bridge, Zenoh, scara-gui, WebSocket, page.
3. **Controller tick lateness**: p99 of each run, from the controller's own result file;
   the median of the runs with the GUI over the median of those without.

Run from the project root: ``python benchmarks/bench_gui.py [--runs 10] [--json PATH]``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from tqdm import tqdm

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from bench_bridge import ROBOT, bus_args, lateness_rows, node, query, verdict, wait_for  # noqa: E402
from bench_link import background, router  # noqa: E402

from bridge.session import ZenohEndpoint  # noqa: E402
from protocol.keys import command_key, state_key  # noqa: E402
from protocol.scenario import load_scenario, task_document  # noqa: E402
from tests.support import BROWSER_ARGS, CHROMIUM, VIEWPORT, free_port  # noqa: E402

TARGET_FPS = 30.0
TARGET_FIRST_MOVE_MS = 100.0
MEASURED = 3.0
"""s of each run over which the pages' frames are counted (the reference run lasts 6.6 s)."""
SETTLE = 1.0
"""s left after the pages close and scara-gui stops, before a run without them: a run
without the GUI is not to be measured beside a browser still tearing two pages down."""

PRESS_RUN = """() => {
  const page = window.scara;
  const start = page.latest.joints.position.slice();
  const bench = window.bench = { pressed: performance.now(), moved: null };
  const draw = window.frame;  // the page asks for a browser frame by this name when it has news
  window.frame = (now) => {
    const drawn = page.stats.frames;
    draw(now);
    // the time the page's frame has drawn the arm moved: now, not the frame's time stamp
    // (its start, which may come before the update)
    const moved = page.latest.joints.position.some((value, i) => value !== start[i]);
    if (bench.moved === null && page.stats.frames > drawn && moved) {
      bench.moved = performance.now();
    }
  };
  document.querySelector("[data-command=run]").click();
}"""
COUNTS = "() => ({ at: performance.now(), frames: window.scara.stats.frames, "
COUNTS += "messages: window.scara.stats.messages })"


class Events:
    """The robot's events, heard by the benchmark's own Zenoh subscriber."""

    def __init__(self, session: zenoh.Session) -> None:
        self.names: list[str] = []
        self._lock = threading.Lock()
        self._subscriber = session.declare_subscriber(state_key(ROBOT, "events"), self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.names.append(json.loads(sample.payload.to_bytes())["event"])

    def ended(self) -> int:
        """Runs ended so far: finished, or stopped short (a fault, a stop)."""
        with self._lock:
            return sum(name in ("run_finished", "run_stopped") for name in self.names)

    def finished(self) -> int:
        with self._lock:
            return self.names.count("run_finished")

    def close(self) -> None:
        self._subscriber.undeclare()


def wait_ready(session: zenoh.Session) -> None:
    def ready() -> bool:
        status = query(session, state_key(ROBOT, "status"), timeout=1.0)
        return bool(status and status["controller"]["state"] == "ready")

    wait_for(ready, 30.0, "the controller to be ready")


def lateness_p99(out: Path) -> float:
    """The last run's tick lateness p99 (us), from the controller's result file."""
    result = json.loads((out / "controller.json").read_text())
    value: float = result["loop"]["lateness_p99_us"]
    return value


def gui_run(browser: Any, port: int, session: zenoh.Session, events: Events) -> dict[str, Any]:
    """One run pressed in the first of two pages of a scara-gui started for it."""
    gui_port = free_port()
    url = f"http://127.0.0.1:{gui_port}/"
    command = node("gui.cli", "--zenoh-port", str(port), "--port", str(gui_port))
    with background([command]):

        def serves() -> bool:
            try:
                with urllib.request.urlopen(url, timeout=1.0) as response:
                    return bool(response.status == 200)
            except OSError:
                return False

        wait_for(serves, 30.0, "scara-gui to serve its page")
        pages = [browser.new_page(viewport=VIEWPORT) for _ in range(2)]
        try:
            for page in pages:
                page.goto(url)
                page.wait_for_function("window.scara.latest.joints !== undefined", timeout=30e3)
            time.sleep(0.5)  # both pages settled on the arm at rest
            ended = events.ended()
            pages[0].evaluate(PRESS_RUN)
            page = pages[0]
            page.wait_for_function("window.bench.moved !== null", timeout=30e3)
            moved_ms = float(page.evaluate("window.bench.moved - window.bench.pressed"))
            before = [p.evaluate(COUNTS) for p in pages]
            time.sleep(MEASURED)
            after = [p.evaluate(COUNTS) for p in pages]
            wait_for(lambda: events.ended() > ended, 60.0, "the run's end")
        finally:
            for page in pages:
                page.close()
    rates = []
    for first, last in zip(before, after, strict=True):
        seconds = (last["at"] - first["at"]) / 1e3
        rates.append(
            {
                "frames_per_s": (last["frames"] - first["frames"]) / seconds,
                "updates_per_s": (last["messages"] - first["messages"]) / seconds,
            }
        )
    return {"first_move_ms": moved_ms, "pages": rates}


def plain_run(session: zenoh.Session, events: Events) -> None:
    """One run started by a Zenoh query, no GUI anywhere."""
    ended = events.ended()
    reply = query(session, command_key(ROBOT, "run"))
    if not (reply and reply["accepted"]):
        raise SystemExit(f"run refused: {reply}")
    wait_for(lambda: events.ended() > ended, 60.0, "the run's end")


def measure(runs: int, priority: int | None) -> dict[str, Any]:
    from playwright.sync_api import sync_playwright

    task = task_document(load_scenario("reference"))
    realtime = [] if priority is None else ["--realtime-priority", str(priority)]
    with router() as port, tempfile.TemporaryDirectory() as folder:
        out = Path(folder)
        stack = [
            node("plant_sim.node", *realtime, *bus_args(port)),
            node("controller.cli", "--out", str(out), *realtime, *bus_args(port)),
            node("bridge.node", "--zenoh-port", str(port), *bus_args(port)),
        ]
        with background(stack), sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=BROWSER_ARGS)
            session = ZenohEndpoint("127.0.0.1", port).open()
            events = Events(session)
            wait_ready(session)
            for name, body in (
                ("waypoints", {"waypoints": task["waypoints"]}),
                ("obstacle", {"obstacle": task["obstacle"]}),
            ):
                reply = query(session, command_key(ROBOT, name), body)
                if not (reply and reply["accepted"]):
                    raise SystemExit(f"{name} refused: {reply}")
            with_gui: list[dict[str, Any]] = []
            without: list[float] = []
            for index in tqdm(range(2 * runs), desc="runs, with and without", file=sys.stderr):
                wait_ready(session)
                if index % 2:
                    with_gui.append(gui_run(browser, port, session, events))
                    with_gui[-1]["lateness_p99_us"] = lateness_p99(out)
                    time.sleep(SETTLE)
                else:
                    plain_run(session, events)
                    without.append(lateness_p99(out))
            finished = events.finished()
            events.close()
            session.close()  # type: ignore[no-untyped-call]
            browser.close()
    return {"with_gui": with_gui, "lateness_without_us": without, "runs_finished": finished}


def table(numbers: dict[str, Any]) -> str:
    runs = numbers["with_gui"]
    fps = [page["frames_per_s"] for run in runs for page in run["pages"]]
    updates = [page["updates_per_s"] for run in runs for page in run["pages"]]
    moves = [run["first_move_ms"] for run in runs]
    with_ = [run["lateness_p99_us"] for run in runs]
    without = numbers["lateness_without_us"]
    p99 = float(np.percentile(moves, 99))
    lines = [
        "| measure | result | target | |",
        "|---|---|---|---|",
        f"| frames drawn per second by each of two pages during a run, min / median "
        f"({len(fps)} page-runs; updates received per second: median "
        f"{statistics.median(updates):.0f}) | {min(fps):.1f} / {statistics.median(fps):.1f} "
        f"| >= {TARGET_FPS:g} | {verdict(min(fps) >= TARGET_FPS)} |",
        f"| run pressed to the arm's first move drawn, p50 / p99 / max ({len(moves)} runs) "
        f"| {np.percentile(moves, 50):.0f} / {p99:.0f} / {max(moves):.0f} ms "
        f"| p99 < {TARGET_FIRST_MOVE_MS:g} ms | {verdict(p99 < TARGET_FIRST_MOVE_MS)} |",
    ]
    lines += lateness_rows(without, with_, "the GUI", "scara-gui and two pages open")
    total = len(runs) + len(without)
    finished = numbers["runs_finished"]
    lines.append(
        f"| runs finished (the others stopped short: a fault) | {finished} of {total} "
        f"| all | {verdict(finished == total)} |"
    )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument(
        "--runs", type=int, default=10, help="runs of each kind (default %(default)s)"
    )
    parser.add_argument(
        "--realtime-priority",
        type=int,
        metavar="N",
        help="run the plant and the controller under SCHED_FIFO at priority N, as "
        "scara-run --realtime-priority N does, in both kinds of runs (default: normal "
        "scheduling, as scara-run starts them)",
    )
    parser.add_argument("--json", type=Path, help="also write the numbers as JSON here")
    args = parser.parse_args(argv)
    if not CHROMIUM.exists():
        raise SystemExit(f"no {CHROMIUM}: install it with tools/browser-setup")
    numbers = measure(args.runs, args.realtime_priority)
    print(table(numbers))
    if args.json:
        args.json.write_text(json.dumps(numbers, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
