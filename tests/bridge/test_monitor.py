"""``scara-monitor``: its model on made-up samples; the real app, driven by textual's pilot,
and its ``--json`` lines against a real bridge on the secure router."""

from __future__ import annotations

import argparse
import asyncio
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from robot_stack import PASSWORDS, ROBOT, START, Stack
from support import SLOWDOWN

from bridge.monitor import MonitorApp, MonitorModel
from bridge.session import ZenohEndpoint, add_zenoh_arguments, endpoint_from_args
from protocol.keys import schema
from protocol.scenario import load_scenario, task_document

REFERENCE = task_document(load_scenario("reference"))


def test_the_model_turns_samples_into_rates_latency_and_a_top_view() -> None:
    now = [100.0]
    model = MonitorModel(clock=lambda: now[0])
    model.on_sample("scenario", REFERENCE, 99.0)
    for step in range(200):  # 100 Hz for 2 s, each sample 1.5 ms after the bridge got it
        now[0] = 100.0 + step / 100
        x = 0.30 + 0.15 * step / 200
        model.on_sample(
            "tcp", {"t": now[0] - 0.0015, "seq": step, "x": x, "y": -0.25, "z": 0.2}, now[0]
        )
    assert 95.0 <= model.rate("tcp") <= 100.0
    assert model.rate("joints") == 0.0
    assert "1.50 ms" in model.nodes_text()
    view = model.top_view(40, 16)
    rows = view.splitlines()
    assert len(rows) == 16 and all(len(row) == 40 for row in rows)
    assert view.count("@") == 1 and "#" in view and "." in view
    assert {"1", "2", "3", "4"} <= set(view)
    # the path runs along y = -0.25, below the obstacle (y = -0.01): lower rows, not upper
    path_rows = [index for index, row in enumerate(rows) if "." in row or "@" in row]
    obstacle_rows = [index for index, row in enumerate(rows) if "#" in row]
    assert min(path_rows) > max(obstacle_rows)
    model.on_sample(
        "events", {"t": 100.0, "seq": 0, "event": "run_started", "detail": {"run": 1}}, 100.0
    )
    assert "run_started run=1" in model.events_text()


def test_the_dashboard_runs_the_arm_from_its_keys_and_shows_it(make_stack: Any) -> None:
    stack: Stack = make_stack(secure=True)
    session = ZenohEndpoint("127.0.0.1", stack.zenoh_port, "operator", PASSWORDS["operator"]).open()
    try:
        stack.wait_ready(session)
        app = MonitorApp(session, ROBOT, load_scenario("reference"))
        events = every_event(app.model)
        asyncio.run(drive(app))
    finally:
        session.close()  # type: ignore[no-untyped-call]
    assert app.replies[:3] == [
        f'{name}: {{"accepted": true, "reason": "none"}}'
        for name in ("waypoints", "obstacle", "run")
    ]
    # every event the model was given: it shows only the last few, and on a busy machine
    # holds and resumes (allowed) may have pushed the run's start out of them
    assert "run_started" in events, events


def every_event(model: MonitorModel) -> list[str]:
    """The names of the events ``model`` is given from now on (it keeps only the last few)."""
    seen: list[str] = []
    take = model.on_sample

    def on_sample(name: str, payload: dict[str, Any], received: float) -> None:
        if name == "events":
            seen.append(payload["event"])
        take(name, payload, received)

    model.on_sample = on_sample  # type: ignore[method-assign]
    return seen


async def drive(app: MonitorApp) -> None:
    async def until(condition: Any, timeout: float, what: str) -> None:
        timeout *= SLOWDOWN
        for _ in range(int(timeout / 0.1)):
            if condition():
                return
            await asyncio.sleep(0.1)
        raise AssertionError(f"timed out after {timeout} s waiting for {what}")

    async with app.run_test(size=(140, 45)) as pilot:
        await until(lambda: "status" in app.model.latest, START, "the first status")
        for key, count in (("w", 1), ("o", 2)):
            await pilot.press(key)
            await until(lambda count=count: len(app.replies) == count, 10.0, f"reply to {key}")
        await pilot.press("r")
        await until(lambda: len(app.replies) == 3, 10.0, "the reply to run")
        await until(lambda: len(app.model.path) > 150, 20.0, "the arm to move")
        await pilot.pause(0.3)  # a panel refresh
        nodes = str(app.query_one("#nodes").render())
        top = str(app.query_one("#top").render())
        arm = str(app.query_one("#arm").render())
    assert "controller" in nodes and ("running" in nodes or "ready" in nodes)
    assert "@" in top and "#" in top
    assert "k_T" in arm and "theta1" in arm


def test_json_lines_for_scripts_with_a_read_only_user(make_stack: Any) -> None:
    stack: Stack = make_stack(secure=True)
    password = stack.processes.folder / "monitor.password"
    password.write_text(PASSWORDS["monitor"])
    command = [
        sys.executable, "-m", "bridge.monitor", "--json", "--count", "60",
        "--zenoh-port", str(stack.zenoh_port), "--user", "monitor",
        "--password-file", str(password),
    ]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, timeout=(START + 30) * SLOWDOWN)
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    assert len(lines) == 60
    for line in lines:
        jsonschema.validate(line["payload"], schema(line["key"]))
        assert line["received"] >= line["payload"].get("t", 0)
    assert {"joints", "tcp", "status"} <= {line["key"] for line in lines}


@pytest.mark.parametrize(("tls", "warned"), [([], True), (["--zenoh-tls-ca", "CA"], False)])
def test_a_router_off_loopback_without_tls_is_warned_of(
    tls: list[str], warned: bool, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    parser = argparse.ArgumentParser()
    add_zenoh_arguments(parser)
    (tmp_path / "CA").write_text("PEM")
    tls = [str(tmp_path / part) if part == "CA" else part for part in tls]
    args = parser.parse_args(["--zenoh-host", "192.0.2.7", "--allow-remote", *tls])
    endpoint = endpoint_from_args(args, "scara-monitor")
    warning = capsys.readouterr().err
    assert ("scara-monitor: warning" in warning and "in clear" in warning) is warned, warning
    assert str(endpoint).startswith("tls/") is not warned
