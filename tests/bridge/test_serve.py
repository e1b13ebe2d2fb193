"""``scara-run --serve``: router, plant, controller service and bridge from one command; the
scenario is the task in force, so ``run`` alone runs it; Ctrl-C stops everything."""

from __future__ import annotations

import json
import signal
import threading
from typing import Any

from robot_stack import COMMS, ROBOT, START, command, latest, open_client
from support import SIGINT_IGNORED, Processes, free_port, wait_until

from protocol.zenoh_can.config import router_reachable


def test_serve_runs_the_scenario_on_command_and_stops_on_ctrl_c(processes: Processes) -> None:
    port = free_port()
    launcher = processes.start(  # as a script's `scara-run ... &` starts it: SIGINT ignored
        "sim.launch", "reference", "--serve", *COMMS, "--interface", "zenoh",
        "--channel", "served", "--bus-option", f"port={port}", name="scara-run",
        prefix=SIGINT_IGNORED,
    )  # fmt: skip
    wait_until(lambda: router_reachable("127.0.0.1", port), START, "the launcher's router")
    session = open_client(port)
    events: list[str] = []
    lock = threading.Lock()

    def on_event(sample: Any) -> None:
        with lock:
            events.append(json.loads(sample.payload.to_bytes())["event"])

    subscriber = session.declare_subscriber(f"scara/{ROBOT}/events", on_event)

    def ready() -> bool:  # a run needs the plant too, holding the task's world (not its own)
        assert launcher.poll() is None, processes.outputs()
        status = latest(session, f"scara/{ROBOT}/status", timeout=1.0)
        return bool(
            status
            and status["controller"]["state"] == "ready"
            and status["plant"]["alive"]
            and status["plant"]["world"] != 0
        )

    wait_until(ready, START, "a ready controller and plant behind the bridge")
    wait_until(
        lambda: latest(session, f"scara/{ROBOT}/scenario", timeout=1.0) is not None,
        5.0,
        "the bridge to learn the task in force",
    )
    scenario = latest(session, f"scara/{ROBOT}/scenario")
    assert scenario is not None and scenario["name"] == "reference"
    ok, reply = command(session, "run")
    assert ok and reply == {"accepted": True, "reason": "none"}, reply
    wait_until(lambda: "run_finished" in events, 40.0, "the run to finish")
    subscriber.undeclare()
    session.close()  # type: ignore[no-untyped-call]

    launcher.signal(signal.SIGINT)
    assert launcher.wait(20.0) == 0, launcher.output()
    wait_until(lambda: not router_reachable("127.0.0.1", port), 2.0, "the launcher's router to go")
