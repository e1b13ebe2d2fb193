"""The robot as an attacker finds it: every socket we serve, up at once, on loopback.

- the CAN router (``tcp/``, loopback: the bus's trust boundary) with plant and controller;
- the secure router, TLS only (a ``scara-certs`` set), with authentication and access control;
- ``scara-bridge`` on it as ``bridge`` over TLS, with a Foxglove server that takes commands;
- a second bridge (robot ``watch``, on the CAN router's Zenoh) with a read-only Foxglove
  server;
- ``scara-gui`` as ``operator`` on plain http (the default set-up, where DNS rebinding is
  the hole) and as ``monitor`` on https;
- the test's own Zenoh session as ``operator`` over TLS, to read the robot's own keys.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
from support import ROOT, Processes, free_port, open_client

sys.path.insert(0, str(ROOT / "tests" / "bridge"))  # the robot as a service, its Foxglove client
sys.path.insert(0, str(ROOT / "tests" / "gui"))  # scara-gui as a process
from gui_stack import start_gui
from robot_stack import (
    COMMS,
    PASSWORDS,
    ROBOT,
    SECURE_CONFIG,
    Stack,
    latest,
    start_router,
)

WATCH = "watch"
"""The second bridge's robot name (the same arm, read-only on Foxglove)."""


@dataclass
class Site:
    processes: Processes
    certs: Path
    stack: Stack
    secure_port: int
    operator_url: str
    monitor_url: str
    foxglove_port: int
    watch_foxglove_port: int
    session: zenoh.Session

    @property
    def ca(self) -> Path:
        return self.certs / "ca.pem"

    def joints(self) -> list[float]:
        """The arm's joints as the robot's own key holds them now."""
        sample = latest(self.session, f"scara/{ROBOT}/joints")
        assert sample is not None, "no joint state on the robot's key"
        return list(sample["position"])

    def controller_state(self) -> str:
        status = latest(self.session, f"scara/{ROBOT}/status")
        assert status is not None
        return str(status["controller"]["state"])

    def status(self) -> dict[str, Any]:
        status = latest(self.session, f"scara/{ROBOT}/status")
        assert status is not None
        return status

    def every_process_alive(self) -> None:
        for process in self.processes.started:
            assert process.poll() is None, process.output()


def start_site(processes: Processes, certs: Path) -> Site:
    ca, server, key = certs / "ca.pem", certs / "server.pem", certs / "server-key.pem"
    passwords = {}
    for user in ("bridge", "operator", "monitor"):
        passwords[user] = processes.folder / f"{user}.password"
        passwords[user].write_text(PASSWORDS[user])
    can_port = start_router(processes, name="can-router")
    tls_only = ("--tls-cert", str(server), "--tls-key", str(key))
    secure_port = start_router(
        processes, "--config", str(SECURE_CONFIG), *tls_only, name="secure-router",
        user="bridge", ca=ca,
    )  # fmt: skip
    foxglove_port, watch_port = free_port(), free_port()
    login = ["--user", "bridge", "--password-file", str(passwords["bridge"])]
    stack = Stack(
        processes,
        can_port,
        secure_port,
        [*login, "--zenoh-tls-ca", str(ca), "--foxglove-port", str(foxglove_port),
         "--foxglove-commands"],
    )  # fmt: skip
    stack.plant = processes.start("plant_sim.node", "reference", *stack.bus, name="plant")
    stack.controller = processes.start(
        "controller.cli", "reference", "--service", *stack.bus, *COMMS, name="controller"
    )
    stack.start_bridge()
    processes.start(
        "bridge.node", "--robot", WATCH, "--zenoh-port", str(can_port),
        "--foxglove-port", str(watch_port), *stack.bus, name="watch-bridge",
    )  # fmt: skip
    zenoh_login = ["--zenoh-port", str(secure_port), "--zenoh-tls-ca", str(ca)]
    operator_url = start_gui(
        processes, *zenoh_login, "--user", "operator",
        "--password-file", str(passwords["operator"]), name="gui-operator",
    )  # fmt: skip
    monitor_url = start_gui(
        processes, *zenoh_login, "--user", "monitor",
        "--password-file", str(passwords["monitor"]), name="gui-monitor", https=certs,
    )  # fmt: skip
    session = open_client(secure_port, "operator", PASSWORDS["operator"], ca=ca)
    stack.wait_ready(session)  # holding the reference task: a run would move the arm
    return Site(
        processes,
        certs,
        stack,
        secure_port,
        operator_url,
        monitor_url,
        foxglove_port,
        watch_port,
        session,
    )
