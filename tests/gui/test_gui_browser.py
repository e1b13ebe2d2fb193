"""scara-gui's page in headless Chromium against real processes: plant, controller service,
bridge and the GUI servers (``conftest.py``). What a user sees and does, checked against
what the robot did on its Zenoh keys. Screenshots are saved in each test's ``tmp_path``."""

from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from gui_stack import Robot, start_gui
from robot_stack import REFERENCE, ROBOT, RUN_TIME, command, latest
from support import SLOWDOWN, Processes, free_port, wait_until

pytestmark = pytest.mark.browser

BUTTONS = ("waypoints", "obstacle", "mode", "reset", "run", "stop", "estop")
STATUS = f"scara/{ROBOT}/status"
COUNT_FRAMES_ASKED = """() => {
  window.framesAsked = 0;
  const ask = window.requestAnimationFrame;
  window.requestAnimationFrame = (callback) => { window.framesAsked += 1; return ask(callback); };
}"""
"""From now on, count the browser frames the page asks for."""
WEIGHTS_ALONE = """() => new Promise((resolve) => {
  const page = window.scara;
  const drawn = { top: 0, view3d: 0, frames: page.stats.frames };
  const top = page.topView.draw.bind(page.topView);
  page.topView.draw = () => { drawn.top += 1; top(); };
  const render = page.view3d.render.bind(page.view3d);
  page.view3d.render = () => { const done = render(); drawn.view3d += done; return done; };
  const asked = performance.now();
  onState({ type: "state", robot: page.robot, time: page.time, full: false, restarted: false,
    path: [], trace: [], events: [], plan: null,
    latest: { coordination: { t: page.time, k_t: 0.25, k_c: 0.75, behaviour: "AO" } } });
  const weights = document.getElementById("weights");
  const drawnYet = () => {
    if (page.stats.frames === drawn.frames) return setTimeout(drawnYet, 5);
    requestAnimationFrame(() => resolve({ ...drawn, waited: performance.now() - asked,
      frames: page.stats.frames - drawn.frames, weights: weights.textContent }));
  };
  drawnYet();
})"""
"""An update of the weights alone, as the page gets them: what the page draws for it (the
numbers, in one frame, after SOON; the arm's views are not drawn again)."""
MOVE_STARTS = """() => new Promise((resolve) => {
  const page = window.scara;
  const seen = { top: 0, plot: 0, frames: [] };
  const top = page.topView.draw.bind(page.topView);
  page.topView.draw = () => { seen.top += 1; top(); };
  const plot = page.plot.update.bind(page.plot);
  page.plot.update = (mode) => { seen.plot += 1; plot(mode); };
  const theta1 = document.getElementById("theta1");
  const before = theta1.textContent;
  const draw = window.frame;
  window.frame = (now) => {
    draw(now);
    seen.frames.push({ top: seen.top, plot: seen.plot, theta1: theta1.textContent });
    if (theta1.textContent !== before) {
      window.frame = draw;
      resolve({ before, frames: seen.frames });
    }
  };
  const joints = page.latest.joints;
  const position = [joints.position[0] + 0.5, ...joints.position.slice(1)];
  onState({ type: "state", robot: page.robot, time: page.time, full: false, restarted: false,
    path: [], trace: [[page.time, 0.4, 0.6]], events: [], plan: null,
    latest: { joints: { ...joints, position },
              coordination: { t: page.time, k_t: 0.4, k_c: 0.6, behaviour: "AO" } } });
})"""
"""The arm moves after standing still, with new weights beside it (as a run starts): the
frames the page draws, each with the views and plot drawn so far and theta1 as it shows."""


def canvas(page: Any) -> bytes:
    """The 3D view's pixels (a PNG of the element)."""
    return bytes(page.locator("#view3d canvas").screenshot())


def controller_state(robot: Robot) -> str:
    status = latest(robot.session, STATUS)
    assert status is not None
    return str(status["controller"]["state"])


def set_task(robot: Robot, obstacle: dict[str, Any] | None) -> None:
    """The reference waypoints and ``obstacle`` as the robot's task, through Zenoh."""
    ok, reply = command(robot.session, "waypoints", {"waypoints": REFERENCE["waypoints"]})
    assert ok and reply["accepted"], reply
    ok, reply = command(robot.session, "obstacle", {"obstacle": obstacle})
    assert ok and reply["accepted"], reply


def wait_until_ready(robot: Robot) -> None:
    """Until the run in progress (if any) is over, then a fault it ended in cleared."""
    wait_until(
        lambda: controller_state(robot) not in ("running", "hold"), RUN_TIME, "the run to end"
    )
    if controller_state(robot) != "ready":
        ok, reply = command(robot.session, "reset")
        assert ok and reply["accepted"], reply
    wait_until(lambda: controller_state(robot) == "ready", 10.0, "the controller to be ready")


def page_on_reference_task(robot: Robot, open_page: Any) -> Any:
    """The robot ready with the reference waypoints and no obstacle; a page that shows them."""
    wait_until_ready(robot)
    set_task(robot, None)
    page = open_page(robot.operator_url)
    wait_until(lambda: page.locator("#waypoints tbody tr").count() == 4, 10.0, "4 waypoints")
    return page


def answer(page: Any, name: str) -> str:
    return str(page.inner_text(f"#answer-{name}"))


class TcpLog:
    """Every ``tcp`` sample the robot publishes while it lives."""

    def __init__(self, robot: Robot) -> None:
        self.points: list[tuple[float, float]] = []
        self.events: list[str] = []
        self._lock = threading.Lock()
        session = robot.session
        self._subscribers = [
            session.declare_subscriber(f"scara/{ROBOT}/tcp", self._on_tcp),
            session.declare_subscriber(f"scara/{ROBOT}/events", self._on_event),
        ]

    def _on_tcp(self, sample: Any) -> None:
        payload = json.loads(sample.payload.to_bytes())
        with self._lock:
            self.points.append((payload["x"], payload["y"]))

    def _on_event(self, sample: Any) -> None:
        with self._lock:
            self.events.append(json.loads(sample.payload.to_bytes())["event"])

    def close(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()


def webgl_renderer(page: Any) -> str:
    """The name of the browser's WebGL renderer ('' if it has no WebGL)."""
    return str(
        page.evaluate(
            """() => {
              const gl = document.createElement("canvas").getContext("webgl");
              const info = gl && gl.getExtension("WEBGL_debug_renderer_info");
              return info ? gl.getParameter(info.UNMASKED_RENDERER_WEBGL) : "";
            }"""
        )
    )


def test_where_webgl_runs_in_software_the_3d_view_is_drawn_with_canvas_2d(
    robot: Robot, open_page: Any
) -> None:
    page = open_page(robot.operator_url)
    renderer = webgl_renderer(page)
    if "SwiftShader" not in renderer:
        pytest.skip(f"this browser's WebGL is not SwiftShader: {renderer!r}")
    assert page.evaluate("window.scara.view3d.kind") == "canvas"


@pytest.mark.parametrize("renderer", ["canvas", "webgl"])
def test_the_page_shows_the_arm_moving_during_a_run(
    robot: Robot, open_page: Any, tmp_path: Path, renderer: str
) -> None:
    """With either way of drawing the 3D view (the page's address can ask for one)."""
    set_task(robot, REFERENCE["obstacle"])
    page = open_page(f"{robot.operator_url}?view3d={renderer}")
    assert page.evaluate("window.scara.view3d.kind") == renderer
    wait_until(lambda: page.locator("#waypoints tbody tr").count() == 4, 10.0, "4 waypoints")
    page.screenshot(path=tmp_path / "before.png")
    theta1, before = page.inner_text("#theta1"), canvas(page)
    page.click("[data-command=run]")
    wait_until(lambda: answer(page, "run") == "accepted", 10.0, "the run to be accepted")
    wait_until(
        lambda: page.inner_text("#theta1") != theta1 and canvas(page) != before,
        10.0,
        "the joints and the 3D view to move",
    )
    page.screenshot(path=tmp_path / "running.png")
    page.click("[data-command=stop]")
    wait_until(lambda: answer(page, "stop") == "accepted", 10.0, "the stop to be accepted")
    wait_until_ready(robot)


def test_an_out_of_reach_waypoint_shows_the_bridges_reason_and_nothing_moves(
    robot: Robot, open_page: Any, tmp_path: Path
) -> None:
    page = page_on_reference_task(robot, open_page)
    before = latest(robot.session, f"scara/{ROBOT}/joints")
    page.fill("#waypoints tbody tr:nth-child(2) input[data-field=x]", "0.9")
    page.dispatch_event("#waypoints tbody tr:nth-child(2) input[data-field=x]", "change")
    page.click("[data-command=waypoints]")
    wait_until(lambda: answer(page, "waypoints").startswith("refused"), 10.0, "the refusal")
    page.screenshot(path=tmp_path / "refused.png")
    shown = answer(page, "waypoints")
    assert "unreachable" in shown and "waypoints[1]" in shown and "out of reach" in shown, shown
    after = latest(robot.session, f"scara/{ROBOT}/joints")
    assert before is not None and after is not None
    assert after["position"] == pytest.approx(before["position"], abs=1e-4)
    scenario = latest(robot.session, f"scara/{ROBOT}/scenario")
    assert scenario is not None and scenario["waypoints"][1]["x"] == REFERENCE["waypoints"][1]["x"]
    assert controller_state(robot) == "ready"


def test_a_monitor_page_has_no_buttons_and_its_server_refuses_a_command(
    robot: Robot, open_page: Any, tmp_path: Path
) -> None:
    wait_until_ready(robot)
    page = open_page(robot.monitor_url)
    assert "read-only" in page.inner_text("#connection")
    for name in BUTTONS:
        assert page.is_disabled(f"[data-command={name}]"), name
    # every control that edits the task disabled too, the task's own included (+ and x)
    controls = "#left input, #left button, #left select, #right input, #right select"
    enabled = page.eval_on_selector_all(
        controls, "all => all.filter(c => !c.disabled).map(c => c.outerHTML)"
    )
    rows = page.locator("#waypoints tbody tr").count()
    assert rows > 0 and enabled == [], enabled
    box = page.locator("#top").bounding_box()
    page.mouse.click(box["x"] + box["width"] * 0.7, box["y"] + box["height"] * 0.3)
    assert page.locator("#waypoints tbody tr").count() == rows  # the mouse added no waypoint
    page.evaluate(
        "window.scara.socket.send(JSON.stringify({type: 'command', id: 7, name: 'run'}))"
    )  # what a page with its buttons enabled by hand would send
    wait_until(lambda: answer(page, "run") != "", 10.0, "the server's answer")
    page.screenshot(path=tmp_path / "monitor.png")
    assert "read-only" in answer(page, "run") and "monitor" in answer(page, "run")
    assert controller_state(robot) == "ready"


def test_two_pages_see_the_same_state_at_30_hz(
    robot: Robot, open_page: Any, tmp_path: Path
) -> None:
    wait_until_ready(robot)
    set_task(robot, REFERENCE["obstacle"])
    first, second = open_page(robot.operator_url), open_page(robot.operator_url)
    first.select_option("#mode-choice", "conventional")
    first.click("[data-command=mode]")
    wait_until(lambda: answer(first, "mode") == "accepted", 10.0, "the mode to be accepted")
    for page in (first, second):
        wait_until(lambda p=page: p.inner_text("#mode") == "conventional", 10.0, "the new mode")
    assert answer(first, "mode") == "accepted" and answer(second, "mode") == ""
    first.click("[data-command=run]")
    wait_until(lambda: controller_state(robot) == "running", 10.0, "the run")
    counts = [page.evaluate("({...window.scara.stats})") for page in (first, second)]
    began = time.monotonic()
    time.sleep(2.0)  # a measuring window, not a wait for anything
    elapsed = time.monotonic() - began
    rates = []
    for page, count in zip((first, second), counts, strict=True):
        now = page.evaluate("({...window.scara.stats})")
        rates.append({k: (now[k] - count[k]) / elapsed for k in ("messages", "frames")})
    print(f"two pages during a run: {rates}")
    (tmp_path / "rates.json").write_text(json.dumps(rates))
    first.click("[data-command=stop]")
    for rate in rates:  # 40 a second sent; this machine may be loaded by others (docs/gui.md)
        assert rate["messages"] >= 20 / SLOWDOWN and rate["frames"] >= 5 / SLOWDOWN, rates
    wait_until_ready(robot)

    def shown(page: Any) -> list[float]:
        return list(page.evaluate("window.scara.latest.joints.position"))

    def both_show_the_robot() -> bool:
        joints = latest(robot.session, f"scara/{ROBOT}/joints")
        assert joints is not None
        texts = [(p.inner_text("#theta1"), p.inner_text("#tcp")) for p in (first, second)]
        return shown(first) == shown(second) == joints["position"] and texts[0] == texts[1]

    # at rest, both pages come to show the robot's own joint state (from its Zenoh key)
    wait_until(both_show_the_robot, 5.0, "both pages to show the arm at rest")
    second.screenshot(path=tmp_path / "second.png")
    first.select_option("#mode-choice", "fuzzy")
    first.click("[data-command=mode]")
    wait_until(lambda: answer(first, "mode") == "accepted", 10.0, "fuzzy again")


def inside(obstacle: dict[str, Any], x: float, y: float, grow: float = 0.0) -> bool:
    yaw = math.radians(obstacle["yaw_deg"])
    dx, dy = x - obstacle["x"], y - obstacle["y"]
    u = dx * math.cos(yaw) + dy * math.sin(yaw)
    v = -dx * math.sin(yaw) + dy * math.cos(yaw)
    a, b = obstacle["long_diameter"] / 2 + grow, obstacle["short_diameter"] / 2 + grow
    return (u / a) ** 2 + (v / b) ** 2 <= 1


def test_an_obstacle_dragged_onto_the_path_is_gone_round(
    robot: Robot, open_page: Any, tmp_path: Path
) -> None:
    page = page_on_reference_task(robot, open_page)
    page.check("input[name=edit][value=obstacle]")
    box = page.locator("#top").bounding_box()

    def screen(x: float, y: float) -> tuple[float, float]:
        sx, sy = page.evaluate(f"window.scara.topView.toScreen({x}, {y})")
        return box["x"] + sx, box["y"] + sy

    page.mouse.click(*screen(0.15, 0.45))  # placed away from the path ...
    page.mouse.move(*screen(0.15, 0.45))
    page.mouse.down()
    for step in range(1, 11):  # ... and dragged onto the line from waypoint 2 to 3
        page.mouse.move(*screen(0.15 + 0.0287 * step, 0.45 - 0.037 * step))
    page.mouse.up()
    page.screenshot(path=tmp_path / "dragged.png")
    page.click("[data-command=obstacle]")
    wait_until(lambda: answer(page, "obstacle") == "accepted", 10.0, "the obstacle accepted")

    def task() -> dict[str, Any]:  # the controller describes its task back after accepting it
        scenario = latest(robot.session, f"scara/{ROBOT}/scenario")
        return scenario if scenario is not None and scenario.get("obstacle") else {}

    wait_until(lambda: bool(task()), 10.0, "the task with the obstacle on the scenario key")
    obstacle = task()["obstacle"]
    assert obstacle["x"] == pytest.approx(0.437, abs=0.006)
    assert obstacle["y"] == pytest.approx(0.08, abs=0.006)
    log = TcpLog(robot)
    try:
        page.click("[data-command=run]")
        wait_until(lambda: "run_finished" in log.events, RUN_TIME, "the run to finish")
        page.screenshot(path=tmp_path / "gone-round.png")
    finally:
        log.close()
    assert len(log.points) > 100
    assert not [p for p in log.points if inside(obstacle, *p)], "the tool went through it"
    last = REFERENCE["waypoints"][-1]
    assert math.dist(log.points[-1], (last["x"], last["y"])) < 0.01
    assert max(y for _, y in log.points) > obstacle["y"] + 0.1  # it got past the obstacle


def test_a_recording_plays_back_and_its_slider_moves_the_arm(
    browser: Any, open_page: Any, tmp_path: Path
) -> None:
    processes = Processes(tmp_path)
    try:
        port = free_port()
        run = tmp_path / "run"
        recorded = processes.start(
            "sim.launch", "reference", "--clock", "lockstep", "--out", str(run),
            "--interface", "zenoh", "--channel", f"rec{port}", "--bus-option", f"port={port}",
            name="scara-run",
        )  # fmt: skip
        assert recorded.wait(120.0) == 0, recorded.output()
        url = start_gui(processes, str(run / "run.mcap"), name="gui-recording")
        page = open_page(url)
        assert "recording" in page.inner_text("#connection")
        for name in BUTTONS:
            assert page.is_disabled(f"[data-command={name}]"), name
        duration = float(page.get_attribute("#slider", "max") or 0)
        assert duration > 1.0  # a lockstep run, recorded at the pace it ran
        page.evaluate(COUNT_FRAMES_ASKED)
        time.sleep(1.0)
        asked = page.evaluate("window.framesAsked")
        assert asked == 0, f"a page with nothing new asked for {asked} browser frames"

        def seek(fraction: float) -> None:
            shown, pixels = page.inner_text("#theta1"), canvas(page)
            page.evaluate(
                f"(() => {{ const s = document.getElementById('slider'); "
                f"s.value = {duration * fraction}; s.dispatchEvent(new Event('input')); }})()"
            )
            wait_until(
                lambda: page.inner_text("#theta1") != shown and canvas(page) != pixels,
                10.0,
                "the arm to move, in numbers and in 3D",
            )

        seek(0.15)
        assert page.evaluate("window.framesAsked") > 0
        seek(0.7)
        page.screenshot(path=tmp_path / "recording.png")
        drawn = page.evaluate(WEIGHTS_ALONE)
        assert drawn["weights"].startswith("k_T 0.25 k_C 0.75"), drawn
        assert drawn["frames"] == 1 and drawn["top"] == 0 and drawn["view3d"] == 0, drawn
        assert drawn["waited"] >= 50, drawn  # SOON: it waited for a motion's frame to join
        time.sleep(0.2)  # the arm has stood still (STILL, 0.1 s)
        moved = page.evaluate(MOVE_STARTS)
        first, last = moved["frames"][0], moved["frames"][-1]
        # the first frame of the move draws the arm alone; the numbers and the plot follow
        assert first == {"top": 1, "plot": 0, "theta1": moved["before"]}, moved
        assert len(moved["frames"]) == 2 and last["plot"] == 1, moved
        page.click("#play")
        position = page.inner_text("#position")
        wait_until(lambda: page.inner_text("#position") != position, 10.0, "the playback")
        assert page.inner_text("#play") == "pause"
    finally:
        processes.close()
