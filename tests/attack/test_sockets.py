"""The attack suite (marker ``attack``): every socket we serve, attacked from outside as a
hostile web page, a read-only user, a stranger, a forger on the CAN bus and a flood would.

Each attack is refused; the arm does not move (its joints on the robot's own key, read before
and after each test) and the controller stays as it was; every process is still up and every
server still answers afterwards (:func:`unmoved`)."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import http.client
import json
import os
import socket
import ssl
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import can
import pytest
import zenoh
from site_stack import PASSWORDS, ROBOT, Site, start_site
from support import (
    SLOWDOWN,
    Observer,
    Processes,
    free_port,
    listening_sockets,
    make_certificates,
    open_client,
    wait_until,
)
from websockets.asyncio.client import connect as connect_async
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect
from websockets.typing import Origin, Subprotocol

from bridge.foxglove_gate import MAX_CLIENT_MESSAGE, MAX_CLIENTS
from gui.server import MAX_MESSAGE
from protocol.codec import WIRE
from protocol.keys import COMMANDS
from protocol.messages import CONTROLLER_ANSWER, NODE_COMMAND, NodeId, Request

pytestmark = pytest.mark.attack

EVIL = "evil.example"
FOXGLOVE_APP = "https://app.foxglove.dev"
SUBPROTOCOL = Subprotocol("foxglove.sdk.v1")
AT_REST = ("ready", "hold")
"""The controller holding the arm: ready, or holding it through a stall of the machine (no
fresh joint state for 3 ticks), which is no attack's doing."""


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    processes = Processes(tmp_path_factory.mktemp("processes"))
    try:
        yield start_site(processes, make_certificates(tmp_path_factory.mktemp("certs")))
    finally:
        processes.close()


@pytest.fixture(autouse=True)
def unmoved(site: Site) -> Iterator[None]:
    """The arm where it was and the controller at rest after the attack; every process up;
    both pages, the Foxglove gate and the bridge answering."""
    joints = site.joints()
    assert site.controller_state() in AT_REST
    yield
    site.every_process_alive()
    assert site.joints() == pytest.approx(joints, abs=2e-6)
    assert site.controller_state() in AT_REST  # no run started, no fault
    for url in (site.operator_url, site.monitor_url):
        assert get(site, url, "/")[0] == 200
    with foxglove(site.foxglove_port) as client:
        assert json.loads(client.recv(timeout=10))["op"] == "serverInfo"


# --- as a browser would reach the pages -------------------------------------------------


def _context(site: Site) -> ssl.SSLContext:
    """The set's CA trusted; the name not checked: the Host header is the attack here."""
    context = ssl.create_default_context(cafile=site.ca)
    context.check_hostname = False
    return context


def get(site: Site, url: str, path: str, headers: dict[str, str] | None = None) -> tuple[int, str]:
    """A GET of ``path`` on the server at ``url``, with ``headers`` as given (Host too)."""
    parts = urlsplit(url)
    assert parts.hostname is not None and parts.port is not None
    connection: http.client.HTTPConnection
    if parts.scheme == "https":
        connection = http.client.HTTPSConnection(
            parts.hostname, parts.port, timeout=10, context=_context(site)
        )
    else:
        connection = http.client.HTTPConnection(parts.hostname, parts.port, timeout=10)
    try:
        connection.request("GET", path, headers=headers or {})
        response = connection.getresponse()
        return response.status, response.read().decode(errors="replace")
    finally:
        connection.close()


def talk(
    site: Site, url: str, sent: Sequence[str | bytes] = (), wanted: int = 0
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Open the page's WebSocket as its own page does (its own origin), send ``sent`` and
    return the hello and the next ``wanted`` replies or errors (state updates skipped).

    websockets' asyncio client, one thread: its threaded client reads and writes one TLS
    socket from two threads, which OpenSSL does not allow (one opening in a few hundred
    then waits for an answer the server sent)."""
    parts = urlsplit(url)
    secure = parts.scheme == "https"

    async def exchange() -> tuple[dict[str, Any], list[dict[str, Any]]]:
        async with (
            asyncio.timeout(30 * SLOWDOWN),
            connect_async(
                f"{'wss' if secure else 'ws'}://{parts.netloc}/ws",
                ssl=_context(site) if secure else None,
                origin=Origin(own_origin(url)),
                open_timeout=10,
            ) as ws,
        ):
            hello = json.loads(await ws.recv())
            for message in sent:
                await ws.send(message)
            found: list[dict[str, Any]] = []
            while len(found) < wanted:
                message = json.loads(await ws.recv())
                if message["type"] in ("reply", "error"):
                    found.append(message)
            return hello, found

    return asyncio.run(exchange())


def own_origin(url: str) -> str:
    parts = urlsplit(url)
    return f"{parts.scheme}://{parts.netloc}"


def upgrade(
    site: Site, url: str, origin: str | None, host: str | None = None, path: str = "/ws"
) -> int:
    """The HTTP status a WebSocket's opening request gets (101: let in), from ``origin``
    (None: no Origin) naming ``host``: the request as a browser sends it, written out, so
    that a refusal is the server's answer and nothing of a client library's."""
    parts = urlsplit(url)
    headers = {
        "Host": host or parts.netloc,
        "Connection": "Upgrade",
        "Upgrade": "websocket",
        "Sec-WebSocket-Version": "13",
        "Sec-WebSocket-Key": base64.b64encode(os.urandom(16)).decode(),
        "Sec-WebSocket-Protocol": SUBPROTOCOL,
    }
    if origin is not None:
        headers["Origin"] = origin
    return get(site, url, path, headers)[0]


def foxglove(port: int) -> ClientConnection:
    """A Foxglove connection through the gate, from the Foxglove app's origin."""
    return connect(
        f"ws://127.0.0.1:{port}",
        subprotocols=[SUBPROTOCOL],
        origin=Origin(FOXGLOVE_APP),
        open_timeout=10,
    )


def urls(site: Site) -> dict[str, str]:
    return {"operator": site.operator_url, "monitor": site.monitor_url}


# --- the attacks ----------------------------------------------------------------------------


@pytest.mark.parametrize("page", ["operator", "monitor"])
def test_a_site_rebound_to_loopback_reaches_no_route_and_no_socket(site: Site, page: str) -> None:
    url = urls(site)[page]
    port = urlsplit(url).port
    foreign = f"{EVIL}:{port}"
    for path in ("/", "/static/app.js", "/static/vendor/three.min.js", "/ws"):
        status, body = get(site, url, path, {"Host": foreign})
        assert (status, body) == (400, "Invalid host header"), path
    # the rebound page's own WebSocket: its own name as Host, its own origin
    scheme = urlsplit(url).scheme
    assert upgrade(site, url, f"{scheme}://{foreign}", host=foreign) == 400
    # the same requests naming a host the server serves go through
    assert get(site, url, "/", {"Host": f"localhost:{port}"})[0] == 200
    hello, _ = talk(site, url)
    assert hello["type"] == "hello" and hello["read_only"] is (page == "monitor")


@pytest.mark.parametrize("page", ["operator", "monitor"])
def test_a_websocket_from_another_site_or_from_none_is_refused(site: Site, page: str) -> None:
    url = urls(site)[page]
    parts = urlsplit(url)
    other_scheme = "http" if parts.scheme == "https" else "https"
    for origin in (
        f"http://{EVIL}",
        "null",
        f"{parts.scheme}://127.0.0.1:{parts.port + 1}",  # another port of this machine
        f"{other_scheme}://{parts.netloc}",
        None,
    ):
        assert upgrade(site, url, origin) == 403, origin
    status, body = get(site, url, "/static/app.js", {"Origin": f"http://{EVIL}"})
    assert status == 403 and EVIL in body


def test_a_read_only_user_commands_nothing_on_any_path(site: Site) -> None:
    bodies = {
        "waypoints": {"waypoints": []},
        "obstacle": {"obstacle": None},
        "mode": {"mode": "fuzzy"},
    }
    # the monitor's page: the server refuses every command before any query
    commands = [
        json.dumps({"type": "command", "name": name, "body": bodies.get(name), "id": number})
        for number, name in enumerate(COMMANDS)
    ]
    _, answers = talk(site, site.monitor_url, commands, len(COMMANDS))
    assert [a["name"] for a in answers] == list(COMMANDS)
    assert all(a["error"]["error"] == "read_only" for a in answers), answers
    # the monitor's own Zenoh session: the router lets no command query through
    monitor = open_client(site.secure_port, "monitor", PASSWORDS["monitor"], ca=site.ca)
    try:
        for name in COMMANDS:
            payload = json.dumps(bodies[name]) if name in bodies else None
            got = list(monitor.get(f"scara/{ROBOT}/cmd/{name}", payload=payload, timeout=2.0))
            assert got == [], name
    finally:
        monitor.close()  # type: ignore[no-untyped-call]
    # a read-only Foxglove server: no service advertised, and a call to any ID fails
    from foxglove_client import FoxgloveClient

    client = FoxgloveClient(site.watch_foxglove_port)
    try:
        wait_until(lambda: bool(client.channels), 10.0, "the read-only server's channels")
        assert client.services == {}
        assert "services" not in client.server_info["capabilities"]
        for service in range(1, len(COMMANDS) + 1):
            ok, _ = client.call_raw(service, b"{}", what=f"service {service}")
            assert not ok, service
    finally:
        client.close()


def test_foxglove_takes_only_the_allowed_origins_and_its_own_server_no_browser(
    site: Site,
) -> None:
    port = site.foxglove_port
    gate = f"http://127.0.0.1:{port}"
    for origin in (f"http://{EVIL}", "null", "http://127.0.0.1:8080", None):
        assert upgrade(site, gate, origin, path="/") == 403, origin
    host = f"{EVIL}:{port}"  # rebound, with the app's origin
    assert upgrade(site, gate, FOXGLOVE_APP, host=host, path="/") == 400
    from foxglove_client import FoxgloveClient

    client = FoxgloveClient(port)  # the app's origin: let in, with the commands
    try:
        wait_until(lambda: len(client.services) == len(COMMANDS), 10.0, "the services")
    finally:
        client.close()
    # the SDK's own server, behind the gate: TLS with a certificate no browser trusts
    assert site.stack.bridge is not None
    listening = listening_sockets(site.stack.bridge.pid)
    assert listening is not None
    inner = [p for host, p in listening if p != port]
    assert len(inner) == 1 and {host for host, _ in listening} == {"127.0.0.1"}, listening
    with pytest.raises((http.client.HTTPException, OSError)):  # in clear, as a page tries
        upgrade(site, f"http://127.0.0.1:{inner[0]}", FOXGLOVE_APP, path="/")
    untrusting = http.client.HTTPSConnection("127.0.0.1", inner[0], timeout=10)
    with pytest.raises(ssl.SSLCertVerificationError):  # TLS, trusting what a browser trusts
        untrusting.request("GET", "/")
    untrusting.close()


def test_wrong_or_missing_credentials_open_no_session(site: Site, tmp_path: Path) -> None:
    for user, password in (("operator", "guess"), ("root", "root"), (None, None)):
        with pytest.raises(zenoh.ZError):
            open_client(site.secure_port, user, password, ca=site.ca).close()  # type: ignore[no-untyped-call]
    wrong = tmp_path / "wrong.password"
    wrong.write_text("guess")
    gui = site.processes.start(
        "gui.cli", "--zenoh-port", str(site.secure_port), "--zenoh-tls-ca", str(site.ca),
        "--user", "operator", "--password-file", str(wrong), "--port", str(free_port()),
        name="gui-wrong",
    )  # fmt: skip
    assert gui.wait(30.0) == 1
    assert "cannot join" in gui.output() and "Traceback" not in gui.output()
    site.processes.started.remove(gui)  # ended as it should: not one of the site's


def test_replayed_and_reordered_command_frames_are_not_acted_on(site: Site) -> None:
    bus = can.Bus(
        interface="zenoh", channel=f"robot{site.stack.can_port}", port=site.stack.can_port
    )
    observer = Observer(bus)
    try:
        bad_before = site.status()["controller"]["bad_frames"]

        def node_command(request: Any, counter: int, ticket: int) -> bytes:
            record = NODE_COMMAND.Record(
                Command=request, Target=NodeId.CONTROLLER, Source=NodeId.OPERATOR, Ticket=ticket
            )
            return bytes(NODE_COMMAND.encode(record, counter))

        def answered(ticket: int) -> list[Any]:
            found = []
            for frame in observer.frames():
                if frame.arbitration_id == CONTROLLER_ANSWER.frame_id:
                    record = WIRE.decode(frame.arbitration_id, frame.data)[2]
                    if record.Ticket == ticket:
                        found.append(record)
            return found

        stop = node_command(Request.STOP, 9, 201)
        observer.send(NODE_COMMAND.frame_id, stop)  # the first after a silence: taken
        wait_until(lambda: bool(answered(201)), 5.0, "the controller's answer to stop")
        observer.send(NODE_COMMAND.frame_id, node_command(Request.RUN, 9, 202))  # repeated
        observer.send(NODE_COMMAND.frame_id, node_command(Request.RUN, 8, 203))  # late, older
        observer.send(NODE_COMMAND.frame_id, stop)  # replayed as it was
        wait_until(
            lambda: site.status()["controller"]["bad_frames"] >= bad_before + 3,
            10.0,
            "the controller to count the three frames it did not act on",
        )
        time.sleep(0.5)
        assert len(answered(201)) == 1 and answered(202) == answered(203) == []
    finally:
        observer.close()


def test_oversized_and_malformed_messages_are_refused_and_the_socket_goes_on(
    site: Site,
) -> None:
    url = site.operator_url
    bad_body = {"waypoints": "x"}
    sent: list[str | bytes] = ["{not json", "[1, 2]", b"\x00binary"]
    sent.append(json.dumps({"type": "command", "name": "waypoints", "id": 1, "body": bad_body}))
    sent.append(json.dumps({"type": "command", "name": "launch", "id": 2}))
    _, answers = talk(site, url, sent, 5)
    errors = [a for a in answers if a["type"] == "error"]
    answered = {a["id"]: a["error"] for a in answers if a["type"] == "reply"}
    assert len(errors) == 3 and set(answered) == {1, 2}, answers
    assert answered[1]["error"] == "malformed" and "waypoints" in answered[1]["field"]
    assert answered[2]["error"] == "malformed" and "launch" in answered[2]["message"]
    assert urlsplit(url).scheme == "http"  # the threaded client, in clear (see talk)
    with connect(f"ws://{urlsplit(url).netloc}/ws", origin=Origin(own_origin(url))) as ws:
        ws.send("x" * (MAX_MESSAGE + 1))
        assert closing_code(ws) == 1009

    from foxglove_client import FoxgloveClient

    client = FoxgloveClient(site.foxglove_port)
    try:
        wait_until(lambda: len(client.services) == len(COMMANDS), 10.0, "the services")
        ok, failure = client.call_raw(client.services["cmd/run"]["id"], b"{not json")
        assert not ok and failure, failure
        ok, failure = client.call_raw(client.services["cmd/waypoints"]["id"], b'{"waypoints": 7}')
        assert not ok and "waypoints" in failure, failure
        ok, failure = client.call_raw(9999, b"{}", what="a service never advertised")
        assert not ok, failure
    finally:
        client.close()
    for message in (b"\x02", "not json"):  # cut short, not JSON: dropped by the SDK
        with (
            foxglove(site.foxglove_port) as ws,
            contextlib.suppress(ConnectionClosed),
        ):
            ws.send(message)
            ws.recv(timeout=2)
    with foxglove(site.foxglove_port) as ws:
        ws.send("x" * (MAX_CLIENT_MESSAGE + 1))
        assert closing_code(ws) == 1009


def closing_code(ws: ClientConnection, within: float = 10.0) -> int | None:
    """The code ``ws`` was closed with by the server within ``within`` s (None: still open)."""
    deadline = time.monotonic() + within * SLOWDOWN
    try:
        while (left := deadline - time.monotonic()) > 0:
            ws.recv(timeout=left)
    except TimeoutError:
        return None
    except ConnectionClosed as closed:
        return None if closed.rcvd is None else closed.rcvd.code
    return None


def test_a_flood_of_connections_is_bounded_and_the_servers_still_answer(site: Site) -> None:
    flood: list[socket.socket] = []
    deadline = time.monotonic() + 20 * SLOWDOWN
    targets = [
        urlsplit(site.operator_url).port,
        urlsplit(site.monitor_url).port,
        site.foxglove_port,
    ]
    try:
        for port in targets:
            for number in range(150):
                assert time.monotonic() < deadline, "the flood took too long to open"
                connection = socket.create_connection(("127.0.0.1", port), timeout=5)
                if number % 2:  # half of them start a request and never finish it
                    connection.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n")
                flood.append(connection)
        # WebSockets to the gate beyond its bound are closed at once
        with contextlib.ExitStack() as opened:
            clients = [
                opened.enter_context(foxglove(site.foxglove_port)) for _ in range(MAX_CLIENTS + 4)
            ]
            codes = [closing_code(ws, within=2.0) for ws in clients]
        assert codes.count(1013) >= 4 and codes.count(None) <= MAX_CLIENTS, codes
    finally:
        for connection in flood:
            connection.close()
    time.sleep(1.0)
