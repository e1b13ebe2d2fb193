"""``scara-run --serve --secure``: the CAN router, a second router with authentication and
access control whose users are those of ``--credentials``, plant, controller service and the
bridge logged in as ``bridge``, all from one command; an operator commands the robot through
it, a read-only monitor and a wildcard over the commands are refused; Ctrl-C stops it all.

The sessions here are written from Zenoh's own configuration keys (no project code), as a
client in any language would open them: multicast scouting off, one explicit
``tcp/127.0.0.1`` endpoint.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh
from support import (
    ROOT,
    SIGINT_IGNORED,
    SLOWDOWN,
    Process,
    Processes,
    free_port,
    make_certificates,
    open_client,
    wait_until,
)

from protocol.zenoh_can.config import router_reachable

ROBOT = "arm1"
START = 30.0
"""s the stack may take to come up on a loaded 2-core machine (imports, joins)."""
USERS = {"bridge": "b-3f9c", "operator": "o-71ad", "monitor": "m-0e42"}
"""Not the demo passwords: the router must take its users from ``--credentials``."""
DEMO = dict(
    line.split(":", 1) for line in (ROOT / "config/zenoh/credentials.txt").read_text().split()
)

pytestmark = pytest.mark.timeout(240)


def logs_in(port: int, user: str, password: str) -> bool:
    try:
        session = open_client(port, user, password)
    except zenoh.ZError:
        return False
    session.close()  # type: ignore[no-untyped-call]
    return True


def latest(session: zenoh.Session, name: str, timeout: float = 2.0) -> dict[str, Any] | None:
    """A state key's latest value from the bridge's queryable; None without an answer within
    ``timeout`` s (times SLOWDOWN)."""
    for reply in session.get(f"scara/{ROBOT}/{name}", timeout=timeout * SLOWDOWN):
        if reply.ok is not None:
            loaded: dict[str, Any] = json.loads(reply.ok.payload.to_bytes())
            return loaded
    return None


def ask(session: zenoh.Session, selector: str, body: Any, timeout: float = 5.0) -> list[Any]:
    """Every reply to a query (a command), waited for ``timeout`` s (times SLOWDOWN)."""
    payload = None if body is None else json.dumps(body)
    return list(session.get(selector, payload=payload, timeout=timeout * SLOWDOWN))


class Samples:
    """Counts the samples a subscriber receives, per key."""

    def __init__(self, session: zenoh.Session, selector: str) -> None:
        self.keys: list[str] = []
        self._lock = threading.Lock()
        self.subscriber = session.declare_subscriber(selector, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.keys.append(str(sample.key_expr))

    def count(self) -> int:
        with self._lock:
            return len(self.keys)


@pytest.fixture
def credentials(tmp_path: Path) -> Path:
    path = tmp_path / "users.txt"
    path.write_text("".join(f"{user}:{password}\n" for user, password in USERS.items()))
    path.chmod(0o600)
    return path


@dataclass
class Served:
    """``scara-run --serve --secure`` running, its robot ready behind its secure router."""

    launcher: Process
    can_port: int
    secure_port: int

    def session(self, user: str) -> zenoh.Session:
        return open_client(self.secure_port, user, USERS[user])


@pytest.fixture
def served(processes: Processes, credentials: Path, tmp_path: Path) -> Iterator[Served]:
    can_port, secure_port = free_port(), free_port()
    assert can_port != secure_port
    launcher = processes.start(  # as a script's `scara-run ... &` starts it: SIGINT ignored
        "sim.launch", "reference", "--serve", "--secure", "--credentials", str(credentials),
        "--secure-port", str(secure_port), "--comms-timeout", "0.5", "--out", str(tmp_path),
        "--interface", "zenoh", "--channel", f"secure{can_port}",
        "--bus-option", f"port={can_port}", name="scara-run", prefix=SIGINT_IGNORED,
    )  # fmt: skip

    def operator_in() -> bool:
        assert launcher.poll() is None, processes.outputs()
        return logs_in(secure_port, "operator", USERS["operator"])

    wait_until(operator_in, START, "the secure router to let the operator in")
    served = Served(launcher, can_port, secure_port)
    watcher = served.session("operator")
    try:

        def ready() -> bool:
            assert launcher.poll() is None, processes.outputs()
            status = latest(watcher, "status", timeout=1.0)
            scenario = latest(watcher, "scenario", timeout=1.0)
            return bool(status and status["controller"]["state"] == "ready" and scenario)

        wait_until(ready, START, "a ready controller and its task behind the bridge")
    finally:
        watcher.close()  # type: ignore[no-untyped-call]
    yield served


def test_serve_secure_lets_an_operator_command_refuses_a_monitor_and_stops_on_ctrl_c(
    served: Served,
) -> None:
    output = served.launcher.output()
    hint = f"--zenoh-port {served.secure_port} --user"
    assert f"{hint} operator" in output and f"{hint} monitor" in output, output
    for user in ("operator", "monitor", "bridge"):  # the demo users are not this router's
        assert not logs_in(served.secure_port, user, DEMO[user])
    assert not logs_in(served.secure_port, "operator", USERS["monitor"])
    operator, monitor = served.session("operator"), served.session("monitor")
    try:
        assert latest(operator, "scenario") == latest(monitor, "scenario")  # both may read
        assert (latest(operator, "scenario") or {})["mode"] == "fuzzy"

        replies = ask(operator, f"scara/{ROBOT}/cmd/mode", {"mode": "conventional"})
        assert len(replies) == 1 and replies[0].ok is not None, replies
        assert json.loads(replies[0].ok.payload.to_bytes()) == {"accepted": True, "reason": "none"}
        wait_until(
            lambda: (latest(operator, "scenario") or {}).get("mode") == "conventional",
            5.0,
            "the bridge to publish the task with the new mode",
        )

        # The read-only user's command reaches nothing (the bridge, given the query, would
        # have applied it before the reply's time ran out) and gets no reply.
        assert ask(monitor, f"scara/{ROBOT}/cmd/mode", {"mode": "fuzzy"}, timeout=2.0) == []
        assert ask(monitor, f"scara/{ROBOT}/cmd/estop", None, timeout=2.0) == []
        assert (latest(operator, "scenario") or {})["mode"] == "conventional"
        status = latest(operator, "status")
        assert status is not None and status["controller"]["state"] == "ready", status
    finally:
        operator.close()  # type: ignore[no-untyped-call]
        monitor.close()  # type: ignore[no-untyped-call]

    served.launcher.signal(signal.SIGINT)
    assert served.launcher.wait(30.0) == 0, served.launcher.output()
    wait_until(
        lambda: (
            not router_reachable("127.0.0.1", served.can_port)
            and not logs_in(served.secure_port, "operator", USERS["operator"])
        ),
        5.0,
        "both of the launcher's routers to go",
    )


def test_the_access_control_lets_no_wildcard_reach_the_commands_nor_the_keys(
    served: Served,
) -> None:
    """What docs/bridge.md says the rules grant, against the real secure router."""
    operator, alone = served.session("operator"), served.session("monitor")
    try:
        # A query reaches every queryable it matches: a wildcard over the commands would be
        # estop, run, reset and stop at once. The operator names one command per query.
        for selector in (f"scara/{ROBOT}/cmd/**", f"scara/{ROBOT}/cmd/*", f"scara/{ROBOT}/**"):
            assert ask(operator, selector, None, timeout=2.0) == [], selector
        status = latest(operator, "status")
        assert status is not None and status["controller"]["state"] == "ready", status
        assert status["plant"]["state"] != "estop", status

        # The router refuses a wildcard subscription: alone in its session it gets nothing.
        # Beside an allowed one it gets that one's samples: a session hands each sample it
        # receives to every subscriber of its own that matches.
        wide_alone = Samples(alone, f"scara/{ROBOT}/**")
        exact = Samples(operator, f"scara/{ROBOT}/joints")
        wide_beside = Samples(operator, f"scara/{ROBOT}/**")
        wait_until(lambda: min(exact.count(), wide_beside.count()) >= 20, 10.0, "joint samples")
        assert wide_alone.count() == 0
        assert set(wide_beside.keys) == {f"scara/{ROBOT}/joints"}
    finally:
        operator.close()  # type: ignore[no-untyped-call]
        alone.close()  # type: ignore[no-untyped-call]


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["--serve", "--credentials", "no-such-file"], "--credentials no-such-file: No such file"),
        (["--serve", "--credentials", "{operator_only}"], "has no bridge user"),
        (["--serve", "--credentials", "{not_pairs}"], "line 2: not user:password"),
        ([], "--secure goes with --serve"),
    ],
    ids=["missing", "no-bridge-user", "not-user-password", "without-serve"],
)
def test_serve_secure_refuses_credentials_it_cannot_use_before_starting_anything(
    tmp_path: Path, port: int, args: list[str], said: str
) -> None:
    operator_only = tmp_path / "operator_only.txt"
    operator_only.write_text("operator:o\nmonitor:m\n")
    not_pairs = tmp_path / "not_pairs.txt"
    not_pairs.write_text("bridge:b\noperator\n")
    args = [arg.format(operator_only=operator_only, not_pairs=not_pairs) for arg in args]
    done = subprocess.run(
        [sys.executable, "-m", "sim.launch", "--secure", *args, "--out", str(tmp_path),
         "--interface", "zenoh", "--bus-option", f"port={port}"],
        cwd=ROOT, capture_output=True, text=True, timeout=60 * SLOWDOWN,
    )  # fmt: skip
    assert done.returncode == 2, (done.stdout, done.stderr)
    assert said in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert not router_reachable("127.0.0.1", port)  # nothing was started


def test_serve_secure_over_mutual_tls_lets_in_only_clients_of_the_set(
    processes: Processes, credentials: Path, tmp_path: Path
) -> None:
    """``--tls DIR --mtls``: both routers on TLS links only, every process of the launcher
    joining with the set's client certificate; a monitor process and an operator's session
    that show it read and command, nothing joins in clear or without it."""
    certs = make_certificates(tmp_path / "certs")
    can_port, secure_port = free_port(), free_port()
    launcher = processes.start(
        "sim.launch", "reference", "--serve", "--secure", "--credentials", str(credentials),
        "--secure-port", str(secure_port), "--comms-timeout", "0.5", "--out", str(tmp_path),
        "--interface", "zenoh", "--channel", f"tls{can_port}", "--bus-option", f"port={can_port}",
        "--tls", str(certs), "--mtls", name="scara-run",
    )  # fmt: skip
    shown = {
        "ca": certs / "ca.pem",
        "certificate": certs / "client.pem",
        "key": certs / "client-key.pem",
    }

    def operator() -> zenoh.Session:
        return open_client(secure_port, "operator", USERS["operator"], **shown)

    def ready() -> bool:
        assert launcher.poll() is None, processes.outputs()
        try:
            session = operator()
        except zenoh.ZError:
            return False
        try:
            status = latest(session, "status", timeout=1.0)
            return bool(status and status["controller"]["state"] == "ready")
        finally:
            session.close()  # type: ignore[no-untyped-call]

    wait_until(ready, START, "a ready controller behind the TLS router")
    assert f"--zenoh-tls-ca {certs / 'ca.pem'}" in launcher.output()
    monitor = subprocess.run(
        [sys.executable, "-m", "bridge.monitor", "--zenoh-port", str(secure_port),
         "--zenoh-tls-ca", str(certs / "ca.pem"), "--zenoh-tls-cert", str(certs / "client.pem"),
         "--zenoh-tls-key", str(certs / "client-key.pem"), "--user", "monitor",
         "--json", "--count", "3"],
        env={**os.environ, "SCARA_ZENOH_PASSWORD": USERS["monitor"]},
        capture_output=True, text=True, timeout=60 * SLOWDOWN, cwd=ROOT,
    )  # fmt: skip
    assert monitor.returncode == 0, monitor.stderr
    assert len(monitor.stdout.splitlines()) == 3 and "in clear" not in monitor.stderr
    session = operator()
    try:
        replies = ask(session, f"scara/{ROBOT}/cmd/mode", {"mode": "conventional"})
        assert [json.loads(r.ok.payload.to_bytes()) for r in replies] == [
            {"accepted": True, "reason": "none"}
        ]
    finally:
        session.close()  # type: ignore[no-untyped-call]
    for port in (can_port, secure_port):  # in clear, or without the client's certificate
        assert not logs_in(port, "operator", USERS["operator"])
        with pytest.raises(zenoh.ZError):
            open_client(port, "operator", USERS["operator"], ca=certs / "ca.pem")
    launcher.signal(signal.SIGINT)
    assert launcher.wait(30.0) == 0, launcher.output()
