"""Who may reach ``scara-gui``: the checks in front of every route and the WebSocket.

A browser is the operator's, and any site it has open may send requests to 127.0.0.1. Two
checks stop such a site from reaching the robot through the operator's browser:

- **Host** (Starlette's :class:`~starlette.middleware.trustedhost.TrustedHostMiddleware`):
  the name the browser asked for must be one this server serves
  (:func:`~protocol.zenoh_can.config.served_hosts`). A
  site whose name was rebound to 127.0.0.1 (DNS rebinding) asks for its own name: refused
  with 400 before any route or WebSocket sees it.
- **Origin** (:class:`SameOrigin`): the page a request comes from, where the browser says
  so, must be this server's own: its scheme, a host it serves, its port. A WebSocket must
  say so (every browser does; a WebSocket without an Origin is not this page's): refused
  with 403 otherwise.

What is left to the operator: the credentials the server joined Zenoh with are its own, so
whoever reaches the page may do what that user may (``--read-only`` for a page to watch).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from urllib.parse import urlsplit

from starlette.datastructures import Headers
from starlette.middleware import Middleware
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.responses import PlainTextResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

log = logging.getLogger("scara.gui")

DEFAULT_PORTS = {"http": 80, "https": 443}
REFUSED = (400, 403)
"""The answers of the two checks: a Host not served, an Origin not ours."""


def _bracketed(host: str) -> str:
    """A host as a ``Host`` header carries it (IPv6 literals in brackets)."""
    return f"[{host}]" if ":" in host else host


class SameOrigin:
    """ASGI middleware: a request whose ``Origin`` is not this server's own is refused with
    403, as is a WebSocket without one; the rest goes on to ``app``."""

    def __init__(self, app: ASGIApp, hosts: Sequence[str]) -> None:
        self.app = app
        self.hosts = frozenset(hosts)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] in ("http", "websocket"):
            refusal = self.refusal(scope, Headers(scope=scope).get("origin"))
            if refusal is not None:
                await PlainTextResponse(refusal, status_code=403)(scope, receive, send)
                return
        await self.app(scope, receive, send)

    def refusal(self, scope: Scope, origin: str | None) -> str | None:
        """Why a request from ``origin`` is refused, or None."""
        if origin is None:
            return "a WebSocket needs an Origin" if scope["type"] == "websocket" else None
        scheme = "https" if scope["scheme"] in ("https", "wss") else "http"
        server = scope.get("server")
        try:
            parts = urlsplit(origin)
            port = parts.port or DEFAULT_PORTS.get(parts.scheme)
        except ValueError:
            return f"Origin {origin!r} is not a URL"
        own = (
            parts.scheme == scheme
            and (parts.hostname or "") in self.hosts
            and (server is None or port == server[1])
        )
        return None if own else f"Origin {origin!r} is not this server's"


class LogRefusals:
    """ASGI middleware: every request refused (400, 403) logged with its Host and Origin."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        async def sending(message: Message) -> None:
            if message["type"].endswith("http.response.start") and message["status"] in REFUSED:
                headers = Headers(scope=scope)
                log.warning(
                    "refused %s %s (%d): Host %r, Origin %r",
                    scope["type"],
                    scope.get("path"),
                    message["status"],
                    headers.get("host"),
                    headers.get("origin"),
                )
            await send(message)

        await self.app(scope, receive, sending)


def guards(hosts: Sequence[str]) -> list[Middleware]:
    """The checks of every request, outermost first: its Host, then its Origin; a refusal
    by either logged."""
    return [
        Middleware(LogRefusals),
        Middleware(
            TrustedHostMiddleware,
            allowed_hosts=[_bracketed(host) for host in hosts],
            www_redirect=False,
        ),
        Middleware(SameOrigin, hosts=hosts),
    ]
