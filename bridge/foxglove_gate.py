"""The gate in front of the bridge's Foxglove server: who may reach it, checked for every
connection before foxglove-sdk's server sees it.

foxglove-sdk's WebSocket server checks neither the ``Host`` nor the ``Origin`` of a
connection, and any web page the operator opens may open a WebSocket to 127.0.0.1. So the
SDK's server listens on 127.0.0.1 at a port of the system's choosing, over TLS with a
certificate made for this process alone (:func:`protocol.certs.self_signed`), which only
this gate trusts: a browser cannot open it (it trusts no such certificate and gives a page
no way round that). The gate listens where the user asked, and relays a connection to it
only when

- its ``Host`` names a host this server serves (:func:`~protocol.zenoh_can.config.served_hosts`:
  a site rebound to 127.0.0.1 names its own): else 400;
- its ``Origin`` is on the allow-list (``--foxglove-allow-origin``; by default the Foxglove
  app's, :data:`FOXGLOVE_APP_ORIGINS`): else 403, a connection without one included
  (websockets' own ``origins`` check);
- fewer than :data:`MAX_CLIENTS` are connected: else it is closed at once (1013).

A client's message over :data:`MAX_CLIENT_MESSAGE` bytes closes its connection (1009).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import ssl
import threading
from collections.abc import Sequence
from http import HTTPStatus
from urllib.parse import urlsplit

from websockets.asyncio.client import ClientConnection, connect
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed, WebSocketException
from websockets.http11 import Request, Response
from websockets.typing import Origin, Subprotocol

log = logging.getLogger("scara.bridge.foxglove")

FOXGLOVE_APP_ORIGINS = ("https://app.foxglove.dev",)
"""The Foxglove app's origin in a browser: the only one a Foxglove server takes by default."""
SUBPROTOCOL = Subprotocol("foxglove.sdk.v1")
"""The one foxglove-sdk's server speaks (it refuses the older ``foxglove.websocket.v1``)."""
MAX_CLIENTS = 16
"""Foxglove connections at once; a flood of them gets no further than the gate."""
MAX_CLIENT_MESSAGE = 64 * 1024
"""Bytes a client's message may take: subscriptions and service calls are small (the
bridge refuses a command over 64 KiB itself)."""
OPEN_TIMEOUT = 10.0
"""s a connection may take to finish its opening handshake before it is dropped."""


def check_origin(origin: str) -> str:
    """A web origin as a browser sends it (``scheme://host[:port]``, nothing after), or
    ``ValueError`` naming it."""
    try:
        parts = urlsplit(origin)
        parts.port  # noqa: B018 - a port that is not a number raises here
    except ValueError:
        parts = None
    if (
        parts is None
        or parts.scheme not in ("http", "https")
        or not parts.hostname
        or parts.path
        or parts.query
        or parts.fragment
    ):
        raise ValueError(
            f"--foxglove-allow-origin {origin!r} is not an origin: scheme://host[:port], "
            f"e.g. {FOXGLOVE_APP_ORIGINS[0]}"
        )
    return origin


class FoxgloveGate:
    """A WebSocket server on ``host:port`` that relays each connection it lets in to the
    SDK's server at ``127.0.0.1:inner_port`` over TLS (``inner_certificate``, pinned); its
    own thread and event loop. Raises ``OSError`` if ``host:port`` cannot be listened on."""

    def __init__(
        self,
        host: str,
        port: int,
        inner_port: int,
        inner_certificate: bytes,
        origins: Sequence[str],
        hosts: Sequence[str],
    ) -> None:
        self._inner_url = f"wss://127.0.0.1:{inner_port}"
        self._inner_ssl = ssl.create_default_context(cadata=inner_certificate.decode())
        self._origins = [Origin(origin) for origin in origins]
        self._hosts = frozenset(hosts)
        self._clients: set[ServerConnection] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: Server | None = None
        started = threading.Event()
        failed: list[OSError] = []
        self._thread = threading.Thread(
            target=self._run, args=(host, port, started, failed), name="foxglove-gate", daemon=True
        )
        self._thread.start()
        started.wait()
        if failed:
            raise failed[0]

    @property
    def port(self) -> int:
        assert self._server is not None
        return int(next(iter(self._server.sockets)).getsockname()[1])

    def _run(self, host: str, port: int, started: threading.Event, failed: list[OSError]) -> None:
        asyncio.run(self._serve(host, port, started, failed))

    async def _serve(
        self, host: str, port: int, started: threading.Event, failed: list[OSError]
    ) -> None:
        self._loop = asyncio.get_running_loop()
        try:
            self._server = await serve(
                self._relay,
                host,
                port,
                origins=self._origins,
                process_request=self._check_host,
                process_response=self._log_refusal,
                subprotocols=[SUBPROTOCOL],
                max_size=MAX_CLIENT_MESSAGE,
                open_timeout=OPEN_TIMEOUT,
            )
        except OSError as error:
            failed.append(error)
            return
        finally:
            started.set()
        await self._server.wait_closed()

    def _check_host(self, connection: ServerConnection, request: Request) -> Response | None:
        """400 for a request that names a host this server does not serve (DNS rebinding)."""
        host = request.headers.get("Host", "")
        with contextlib.suppress(ValueError):
            if (urlsplit(f"//{host}").hostname or "") in self._hosts:
                return None
        return connection.respond(HTTPStatus.BAD_REQUEST, f"Host {host!r} is not served here\n")

    def _log_refusal(
        self, connection: ServerConnection, request: Request, response: Response
    ) -> None:
        """Say who was refused, and why (websockets' ``origins`` check answers 403)."""
        if response.status_code >= 400:
            log.warning(
                "refused a Foxglove client (%d %s): Host %r, Origin %r",
                response.status_code,
                response.reason_phrase,
                request.headers.get("Host"),
                request.headers.get("Origin"),
            )

    async def _relay(self, client: ServerConnection) -> None:
        if len(self._clients) >= MAX_CLIENTS:
            await client.close(1013, "too many Foxglove clients: try again later")
            return
        self._clients.add(client)
        try:
            async with connect(
                self._inner_url,
                ssl=self._inner_ssl,
                subprotocols=[SUBPROTOCOL],
                max_size=None,
                compression=None,
                open_timeout=OPEN_TIMEOUT,
            ) as inner:
                await _both_ways(client, inner)
        except (OSError, WebSocketException) as error:
            log.warning("a Foxglove client could not be relayed: %s", error)
        finally:
            self._clients.discard(client)

    def stop(self) -> None:
        """Close every connection and stop listening."""
        if self._loop is not None and self._server is not None:
            self._loop.call_soon_threadsafe(self._server.close)
        self._thread.join(5.0)


async def _both_ways(client: ServerConnection, inner: ClientConnection) -> None:
    """Relay messages each way until either side closes; then close the other."""
    pumps = [
        asyncio.create_task(_pump(client, inner)),
        asyncio.create_task(_pump(inner, client)),
    ]
    await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
    for pump in pumps:
        pump.cancel()
    with contextlib.suppress(ConnectionClosed):
        await client.close()
    await inner.close()


async def _pump(
    source: ServerConnection | ClientConnection, sink: ServerConnection | ClientConnection
) -> None:
    with contextlib.suppress(ConnectionClosed):
        async for message in source:
            await sink.send(message)
