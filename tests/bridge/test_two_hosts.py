"""Across hosts: the robot (routers, plant, controller, bridge) in one network namespace, an
operator's machine in another, joined by a veth pair that the test creates. The secure
router listens on the robot's veth address, in clear or on a TLS link only (mutual TLS: the
operator shows a client certificate of the same ``scara-certs`` set); the operator is a plain
Zenoh client written here, in its own process inside the operator's namespace.

Needs root and iproute2 (``ip netns``); skipped where they are missing.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
from robot_stack import COMMS, PASSWORDS, REPO, ROBOT, SECURE_CONFIG, START
from support import SLOWDOWN, Processes, free_port, make_certificates

from protocol.scenario import load_scenario, task_document

ROBOT_ADDRESS = "10.231.7.1"
DESK_ADDRESS = "10.231.7.2"

OPERATOR = """
import json, sys, threading, time, zenoh
robot_address, port, password, robot, task, patience, slowdown, tls = sys.argv[1:9]
slowdown = float(slowdown)  # SCARA_TEST_SLOWDOWN: every bound below is stretched by it
task = json.loads(task)
config = zenoh.Config()
config.insert_json5("mode", '"client"')
scheme = "tls" if tls else "tcp"
config.insert_json5("connect/endpoints", json.dumps([f"{scheme}/{robot_address}:{port}"]))
if tls:  # the router's certificate checked against the set's CA, the client's own shown
    for name, file in (("root_ca_certificate", "ca.pem"), ("connect_certificate", "client.pem"),
                       ("connect_private_key", "client-key.pem")):
        config.insert_json5(f"transport/link/tls/{name}", json.dumps(f"{tls}/{file}"))
    config.insert_json5("transport/link/tls/enable_mtls", "true")
config.insert_json5("listen/endpoints", "[]")
config.insert_json5("scouting/multicast/enabled", "false")
config.insert_json5("scouting/gossip/enabled", "false")
config.insert_json5("transport/auth/usrpwd/user", '"operator"')
config.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
deadline = time.monotonic() + float(patience) * slowdown  # for the robot's side to come up
while True:
    try:
        session = zenoh.open(config)
        break
    except zenoh.ZError:
        if time.monotonic() > deadline:
            sys.exit("cannot open a session")
        time.sleep(0.5)
deadline = time.monotonic() + 60 * slowdown
events, tcp = [], []
def on_event(sample):
    events.append(json.loads(sample.payload.to_bytes())["event"])
def on_tcp(sample):
    tcp.append(json.loads(sample.payload.to_bytes()))
subscribers = [
    session.declare_subscriber(f"scara/{robot}/events", on_event),
    session.declare_subscriber(f"scara/{robot}/tcp", on_tcp),
]
def ask(key, body=None):
    payload = None if body is None else json.dumps(body)
    for reply in session.get(key, payload=payload, timeout=5.0 * slowdown):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return None
while True:
    status = ask(f"scara/{robot}/status")
    if status and status["controller"]["alive"] and status["controller"]["state"] == "ready":
        break
    if time.monotonic() > deadline:
        sys.exit("no ready controller")
    time.sleep(0.2)
replies = {}
for name, body in (
    ("waypoints", {"waypoints": task["waypoints"]}),
    ("obstacle", {"obstacle": task["obstacle"]}),
    ("run", None),
):
    replies[name] = ask(f"scara/{robot}/cmd/{name}", body)
while "run_finished" not in events and time.monotonic() < deadline:
    time.sleep(0.1)
print(json.dumps({"replies": replies, "events": events, "tcp": len(tcp)}))
session.close()
"""


@dataclass(frozen=True)
class Hosts:
    robot: list[str]
    desk: list[str]
    """Command prefixes that run a program in each namespace."""


def ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True)


@pytest.fixture
def hosts() -> Iterator[Hosts]:
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("needs root and iproute2 to create network namespaces")
    tag = f"{os.getpid() % 100000}"
    robot, desk = f"scara-robot-{tag}", f"scara-desk-{tag}"
    try:
        ip("netns", "add", robot)
    except subprocess.CalledProcessError as error:
        pytest.skip(f"cannot create a network namespace here: {error.stderr.strip()}")
    try:
        ip("netns", "add", desk)
        ip("link", "add", f"veth-r{tag}", "type", "veth", "peer", "name", f"veth-d{tag}")
        for namespace, device, address in (
            (robot, f"veth-r{tag}", ROBOT_ADDRESS),
            (desk, f"veth-d{tag}", DESK_ADDRESS),
        ):
            ip("link", "set", device, "netns", namespace)
            ip("-n", namespace, "addr", "add", f"{address}/30", "dev", device)
            ip("-n", namespace, "link", "set", device, "up")
            ip("-n", namespace, "link", "set", "lo", "up")
        yield Hosts(["ip", "netns", "exec", robot], ["ip", "netns", "exec", desk])
    finally:
        for namespace in (robot, desk):  # the veth pair goes with them
            subprocess.run(["ip", "netns", "del", namespace], capture_output=True)


@pytest.mark.parametrize("link", ["tcp", "mtls"])
def test_an_operator_on_another_host_runs_the_arm_through_the_secure_router(
    hosts: Hosts, processes: Processes, link: str
) -> None:
    can_port, zenoh_port = free_port(), free_port()
    bus = ["--interface", "zenoh", "--channel", "robot", "--bus-option", f"port={can_port}"]
    tls = ""
    router_tls: list[str] = []
    bridge_tls: list[str] = []
    if link == "mtls":
        certs = make_certificates(processes.folder / "certs", ROBOT_ADDRESS)
        tls = str(certs)
        router_tls = ["--tls-cert", f"{tls}/server.pem", "--tls-key", f"{tls}/server-key.pem"]
        router_tls += ["--tls-client-ca", f"{tls}/ca.pem"]
        bridge_tls = ["--zenoh-tls-ca", f"{tls}/ca.pem", "--zenoh-tls-cert", f"{tls}/client.pem"]
        bridge_tls += ["--zenoh-tls-key", f"{tls}/client-key.pem"]
    start = processes.start
    start("protocol.zenoh_can.router", "--port", str(can_port), prefix=hosts.robot, name="can")
    secure = start(
        "protocol.zenoh_can.router", "--host", ROBOT_ADDRESS, "--allow-remote",
        "--port", str(zenoh_port), "--config", str(SECURE_CONFIG), *router_tls,
        prefix=hosts.robot, name="secure-router",
    )  # fmt: skip
    start("plant_sim.node", *bus, prefix=hosts.robot, name="plant")
    start("controller.cli", *bus, *COMMS, prefix=hosts.robot, name="controller")
    password = processes.folder / "bridge.password"
    password.write_text(PASSWORDS["bridge"])
    bridge = start(
        "bridge.node", "--zenoh-host", ROBOT_ADDRESS, "--allow-remote",
        "--zenoh-port", str(zenoh_port), "--user", "bridge", "--password-file", str(password),
        *bridge_tls, *bus, prefix=hosts.robot, name="bridge",
    )  # fmt: skip

    task = json.dumps(task_document(load_scenario("reference")))
    operator = subprocess.run(
        [*hosts.desk, sys.executable, "-c", OPERATOR, ROBOT_ADDRESS, str(zenoh_port),
         PASSWORDS["operator"], ROBOT, task, str(START), str(SLOWDOWN), tls],
        cwd=REPO, capture_output=True, text=True, timeout=(START + 90) * SLOWDOWN,
    )  # fmt: skip
    assert operator.returncode == 0, f"{operator.stderr}\n{processes.outputs()}"
    seen = json.loads(operator.stdout)
    accepted = {"accepted": True, "reason": "none"}
    assert seen["replies"] == dict.fromkeys(("waypoints", "obstacle", "run"), accepted)
    assert seen["events"][0] == "run_started" and seen["events"][-1] == "run_finished", seen
    assert "collision" not in seen["events"]
    assert seen["tcp"] > 300  # the arm's path reached the other host at 100 Hz
    # in clear, the router and the bridge say what crosses the network so; over TLS, nothing
    for process in (secure, bridge):
        assert ("in clear" in process.output()) is (link == "tcp"), process.output()

    # and the robot's routers are out of the operator's reach without credentials, and over
    # TLS without the client certificate
    attempts = [("wrong", tls)] + ([(PASSWORDS["operator"], "")] if tls else [])
    for password_tried, tls_tried in attempts:
        refused = subprocess.run(
            [*hosts.desk, sys.executable, "-c", OPERATOR, ROBOT_ADDRESS, str(zenoh_port),
             password_tried, ROBOT, task, "3", str(SLOWDOWN), tls_tried],
            cwd=REPO, capture_output=True, text=True, timeout=60 * SLOWDOWN,
        )  # fmt: skip
        assert refused.returncode != 0 and "cannot open a session" in refused.stderr
