"""Zenoh session settings of the CAN-over-Zenoh transport: one router, every bus its client.

Topology (measured in ``docs/transport.md``): a router process (``scara-router``) listens on
the well-known ``tcp/127.0.0.1:17447``; every bus is a Zenoh *client* of it and listens on
nothing. Frames go bus -> router -> bus over TCP, one path per sender, so each sender's
frames arrive in order; no bus depends on another bus or on gossip, so any bus may start,
die and restart at any time, and the router may restart too (clients reconnect to it).

Loopback only by default: ``host`` must be a loopback address unless ``allow_remote`` is
given, and never a wildcard or multicast address. Multicast scouting is always off and every
endpoint explicit. With :class:`Tls` the links are Zenoh's ``tls/`` ones (the router's
certificate checked by every client, and the clients' by the router where it asks for them):
what a session carries off the machine, passwords and commands among it, is then encrypted.
The settings are plain ``path -> JSON value`` dicts (pure, so tests can read them) turned
into a :class:`zenoh.Config` by :func:`build_zenoh_config`.
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import re
import socket
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import can
import zenoh

DEFAULT_CHANNEL: Final = "scara"
DEFAULT_HOST: Final = "127.0.0.1"
DEFAULT_PORT: Final = 17447
KEY_PREFIX: Final = "scara/can/"
FLUSH_PREFIX: Final = "scara/canflush/"  # the flush barrier's queryables, beside the frames

HANDSHAKE_MS: Final = 2000
"""Zenoh's is 10 s: a session whose handshake with a program that is not Zenoh is stuck
cannot close before it expires."""

_FORBIDDEN_IN_CHANNEL: Final = re.compile(r"[*$#?@\s\x00-\x1f\x7f]")
_HOSTNAME: Final = re.compile(r"^[A-Za-z0-9]([A-Za-z0-9-]*[A-Za-z0-9])?(\.[A-Za-z0-9-]+)*$")


def key_for_channel(channel: object) -> str:
    """The Zenoh key of a channel; raise CanInitializationError for a name that is not one."""
    if isinstance(channel, int) and not isinstance(channel, bool):
        channel = str(channel)  # python-can casts CAN_CHANNEL=1 to an int
    if not isinstance(channel, str) or not channel:
        raise can.CanInitializationError(
            f"zenoh channel must be a non-empty string, got {channel!r}"
        )
    bad = _FORBIDDEN_IN_CHANNEL.search(channel)
    if bad:
        raise can.CanInitializationError(
            f"zenoh channel {channel!r} contains {bad.group()!r}: "
            "wildcards, '$', '#', '?', '@', spaces and control characters are not allowed"
        )
    key = KEY_PREFIX + channel
    try:
        zenoh.KeyExpr(key)
    except zenoh.ZError as exc:
        raise can.CanInitializationError(
            f"zenoh channel {channel!r} does not make a valid key ({key!r}): {exc}"
        ) from None
    return key


def check_host(value: object, *, allow_remote: bool, name: str = "zenoh host") -> str:
    """Normalise an address; loopback only unless allow_remote, never a wildcard or group."""
    if not isinstance(value, str) or not value.strip():
        raise can.CanInitializationError(f"{name} must be an explicit address, got {value!r}")
    text = value.strip()
    bare = text[1:-1] if text.startswith("[") and text.endswith("]") else text
    if bare.lower() == "localhost":
        return DEFAULT_HOST
    try:
        address = ipaddress.ip_address(bare)
    except ValueError:
        address = None
    if address is not None:
        if address.is_unspecified or address.is_multicast:
            raise can.CanInitializationError(
                f"{name} {value!r} is not an explicit unicast address "
                "(wildcard and multicast addresses are refused)"
            )
        if address.is_loopback:
            return str(address)
    elif not _HOSTNAME.match(bare):
        raise can.CanInitializationError(f"{name} {value!r} is not an address or host name")
    if not allow_remote:
        raise can.CanInitializationError(
            f"{name} {value!r} is not a loopback address (127.x.x.x, ::1, localhost); "
            "use another address on purpose with --allow-remote (allow_remote=True in code)"
        )
    return bare


LOOPBACK_NAMES: Final = ("localhost", "127.0.0.1", "::1")
"""The names and addresses of this machine a local client uses."""


def served_hosts(listen: str, names: Sequence[str] = ()) -> list[str]:
    """The hosts a request to a server of ours may name (its ``Host``): loopback's, the
    address it listens on and ``names`` (``--allow-host``); lower case, IPv6 literals
    without brackets. A request naming another was meant for another site (DNS rebinding)."""
    hosts = [*LOOPBACK_NAMES, listen, *names]
    return list(dict.fromkeys(host.strip().strip("[]").lower() for host in hosts))


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or a name) is this machine's loopback."""
    bare = host.strip().removeprefix("[").removesuffix("]")
    try:
        return ipaddress.ip_address(bare).is_loopback
    except ValueError:
        return bare.lower() == "localhost"


def warn_in_clear(program: str, what: str) -> None:
    """Say on stderr that ``what`` leaves this machine unencrypted (an address off loopback
    without TLS), and what to do about it."""
    print(
        f"{program}: warning: {what} cross the network in clear (no TLS); anyone on the way "
        "can read them: use TLS (scara-certs makes a set; docs/bridge.md, 'Remote operators')",
        file=sys.stderr,
        flush=True,
    )


def check_port(port: object) -> int:
    """A TCP port number, 1..65535."""
    if isinstance(port, bool) or not isinstance(port, int) or not 0 < port < 65536:
        raise can.CanInitializationError(f"zenoh port must be in 1..65535, got {port!r}")
    return port


TLS_SETTINGS: Final = "transport/link/tls/"


@dataclass(frozen=True, slots=True)
class Tls:
    """The files of one side of Zenoh's ``tls/`` links (PEM; ``scara-certs`` makes a set).

    A client: ``ca`` is the authority that signed the router's certificate (required), and
    ``certificate`` with ``key`` its own, for a router that asks for one (mutual TLS). A
    router: ``certificate`` and ``key`` are its own (required), and ``ca``, if given, the
    authority every client's certificate must be signed by (mutual TLS).
    """

    ca: Path | None = None
    certificate: Path | None = None
    key: Path | None = None

    @classmethod
    def of(cls, ca: object, certificate: object, key: object, side: str) -> Tls | None:
        """The files given (paths, or None), checked for ``side`` (:meth:`check`); None
        where none is: a plain ``tcp/`` link."""
        files = [None if name is None else Path(str(name)) for name in (ca, certificate, key)]
        if all(name is None for name in files):
            return None
        return cls(*files).check(side)

    def named(self, names: tuple[str, str, str]) -> list[tuple[str, str]]:
        """Its files, each with the name ``names`` gives it (CA, certificate, key): a
        command's flags, a bus's options."""
        given = zip(names, (self.ca, self.certificate, self.key), strict=True)
        return [(name, str(path)) for name, path in given if path is not None]

    @property
    def mutual(self) -> bool:
        """A client that shows a certificate, or a router that asks for one."""
        return self.certificate is not None and self.ca is not None

    def check(self, side: str) -> Tls:
        """Itself, once every file it names can be read and ``side`` (``client`` or
        ``router``) has what it needs; ``can.CanInitializationError`` naming the file."""
        if (self.certificate is None) != (self.key is None):
            raise can.CanInitializationError(
                "TLS: a certificate goes with its private key: give both, or neither"
            )
        if side == "client" and self.ca is None:
            raise can.CanInitializationError(
                "TLS: a client needs the CA that signed the router's certificate"
            )
        if side == "router" and self.certificate is None:
            raise can.CanInitializationError("TLS: a router needs its certificate and key")
        for path in (self.ca, self.certificate, self.key):
            if path is not None and not Path(path).is_file():
                raise can.CanInitializationError(f"TLS: no such file: {path}")
        return self

    def client_settings(self) -> dict[str, Any]:
        """Zenoh's settings of a client's TLS link."""
        settings: dict[str, Any] = {TLS_SETTINGS + "root_ca_certificate": str(self.ca)}
        if self.mutual:
            settings |= {
                TLS_SETTINGS + "enable_mtls": True,
                TLS_SETTINGS + "connect_certificate": str(self.certificate),
                TLS_SETTINGS + "connect_private_key": str(self.key),
            }
        return settings

    def router_settings(self) -> dict[str, Any]:
        """Zenoh's settings of a router's TLS listener."""
        settings: dict[str, Any] = {
            TLS_SETTINGS + "listen_certificate": str(self.certificate),
            TLS_SETTINGS + "listen_private_key": str(self.key),
        }
        if self.mutual:
            settings |= {
                TLS_SETTINGS + "enable_mtls": True,
                TLS_SETTINGS + "root_ca_certificate": str(self.ca),
            }
        return settings


def endpoint(host: str, port: int, tls: bool = False) -> str:
    """A Zenoh TCP (or, with ``tls``, TLS) locator; IPv6 literals go in brackets."""
    scheme = "tls" if tls else "tcp"
    if ":" in host:
        return f"{scheme}/[{host}]:{port}"
    return f"{scheme}/{host}:{port}"


def _common(mode: str) -> dict[str, Any]:
    return {
        "mode": mode,
        "scouting/multicast/enabled": False,
        "transport/unicast/open_timeout": HANDSHAKE_MS,
    }


def client_config(
    host: str,
    port: int,
    user: str | None = None,
    password: str | None = None,
    tls: Tls | None = None,
) -> dict[str, Any]:
    """A bus (or a bridge, a monitor): client of the router at ``host:port``, listening on
    nothing; ``user`` and ``password`` for a router that authenticates its clients; ``tls``
    for a router that listens on a ``tls/`` link."""
    host = check_host(host, allow_remote=True)  # a guard: never a wildcard or a group
    settings = _common("client") | {
        "listen/endpoints": [],
        "connect/endpoints": [endpoint(host, port, tls=tls is not None)],
    }
    if user is not None:
        settings |= {"transport/auth/usrpwd/user": user, "transport/auth/usrpwd/password": password}
    if tls is not None:
        settings |= tls.client_settings()
    return settings


def router_config(
    host: str, port: int, connect: list[str] | None = None, tls: Tls | None = None
) -> dict[str, Any]:
    """The router: listens on ``host:port`` only (on a ``tls/`` link only, with ``tls``);
    ``connect`` links it to other routers."""
    host = check_host(host, allow_remote=True)
    settings = _common("router") | {
        "scouting/gossip/enabled": False,
        "listen/endpoints": [endpoint(host, port, tls=tls is not None)],
        "listen/exit_on_failure": True,
        "connect/endpoints": list(connect or []),
    }
    if tls is not None:
        settings |= tls.router_settings()
    return settings


def build_zenoh_config(settings: dict[str, Any], base: str | None = None) -> zenoh.Config:
    """A :class:`zenoh.Config` with every setting inserted, over the JSON5 file ``base`` if
    given (authentication and access control, ``config/zenoh/``): ours win."""
    config = zenoh.Config.from_file(base) if base else zenoh.Config()
    if base:
        settings = _files_beside(config, Path(base).parent) | settings
    for path, value in settings.items():
        config.insert_json5(path, json.dumps(value))
    return config


def free_port(host: str = DEFAULT_HOST) -> int:
    """A TCP port nobody holds on ``host`` right now: for a router of one's own (the tests',
    ``scara-soak``'s) beside any other on the machine."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return int(probe.getsockname()[1])


def router_reachable(
    host: str = DEFAULT_HOST,
    port: int = DEFAULT_PORT,
    user: str | None = None,
    password: str | None = None,
    tls: Tls | None = None,
) -> bool:
    """True if a Zenoh router answers at ``host:port`` now (opens and closes a client), and
    lets ``user`` in if one is given (a secure router refuses a session without one), over a
    ``tls/`` link with ``tls``."""
    try:
        settings = client_config(host, port, user, password, tls)
        session = zenoh.open(build_zenoh_config(settings))
    except zenoh.ZError:
        return False
    try:
        return bool(session.info.routers_zid())
    finally:
        close(session)


AUTH_FILES = ("transport/auth/usrpwd/dictionary_file",)
"""Settings that name a file: relative to the configuration file that holds them."""


def _files_beside(config: zenoh.Config, folder: Path) -> dict[str, Any]:
    found: dict[str, Any] = {}
    for path in AUTH_FILES:
        with contextlib.suppress(zenoh.ZError, ValueError):
            value = json.loads(config.get_json(path))
            if isinstance(value, str) and not Path(value).is_absolute():
                found[path] = str(folder / value)
    return found


def close(session: Any) -> None:
    """``Session.close`` (zenoh's stub leaves it unannotated, which strict mypy refuses)."""
    session.close()
