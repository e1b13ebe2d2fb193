"""Where a bridge or a monitor meets the others: a Zenoh client session to one router, with
a user and password when that router authenticates (``config/zenoh/secure-router.json5``),
over a ``tls/`` link when it listens on one (``--zenoh-tls-ca``).

Loopback only unless ``--allow-remote``; never a scouted or default-configured session; a
router off loopback joined without TLS is warned of (the password crosses in clear).
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from pathlib import Path

import can
import zenoh

from protocol.cli import number
from protocol.keys import DEFAULT_ROBOT
from protocol.zenoh_can.config import (
    DEFAULT_HOST,
    DEFAULT_PORT,
    Tls,
    build_zenoh_config,
    check_host,
    client_config,
    is_loopback,
    warn_in_clear,
)

PASSWORD_VARIABLE = "SCARA_ZENOH_PASSWORD"


@dataclass(frozen=True, slots=True)
class ZenohEndpoint:
    """A router to join, and who joins it."""

    host: str
    port: int
    user: str | None = None
    password: str | None = None
    tls: Tls | None = None

    def open(self) -> zenoh.Session:
        """A client session of this router (raises ``zenoh.ZError`` if it cannot)."""
        settings = client_config(self.host, self.port, self.user, self.password, self.tls)
        return zenoh.open(build_zenoh_config(settings))

    def __str__(self) -> str:
        who = f"{self.user}@" if self.user else ""
        scheme = "tls/" if self.tls is not None else ""
        return f"{scheme}{who}{self.host}:{self.port}"


def add_zenoh_arguments(
    parser: argparse.ArgumentParser,
    *,
    default_port: int = DEFAULT_PORT,
    robot_help: str = "robot name",
) -> None:
    """``--robot`` (``robot_help`` says what it is to this command), ``--zenoh-host``,
    ``--zenoh-port``, ``--allow-remote``, ``--user``, ``--password-file``."""
    parser.add_argument(
        "--robot", default=DEFAULT_ROBOT, help=f"{robot_help} (default %(default)s)"
    )
    group = parser.add_argument_group("Zenoh (the router where the robot's keys live)")
    group.add_argument(
        "--zenoh-host", default=DEFAULT_HOST, help="router address (default %(default)s)"
    )
    group.add_argument(
        "--zenoh-port",
        type=number(1, 65535, integer=True),
        default=default_port,
        help="router port (default %(default)s)",
    )
    group.add_argument(
        "--allow-remote", action="store_true", help="accept a router that is not on loopback"
    )
    group.add_argument("--user", help="user name for a router that authenticates")
    group.add_argument(
        "--password-file",
        type=Path,
        help=f"file holding the password (or set {PASSWORD_VARIABLE})",
    )
    group.add_argument(
        "--zenoh-tls-ca",
        type=Path,
        metavar="PEM",
        help="join the router on a tls/ link, its certificate signed by this CA (scara-certs)",
    )
    group.add_argument(
        "--zenoh-tls-cert",
        type=Path,
        metavar="PEM",
        help="this client's certificate, for a router that asks for one (mutual TLS)",
    )
    group.add_argument("--zenoh-tls-key", type=Path, metavar="PEM", help="its private key")


def endpoint_from_args(args: argparse.Namespace, program: str) -> ZenohEndpoint:
    """The endpoint the arguments name; ``ValueError``/``OSError`` if they are wrong.
    ``program`` warns, off loopback without TLS, that what it sends crosses in clear."""
    try:
        host = check_host(args.zenoh_host, allow_remote=args.allow_remote, name="--zenoh-host")
        tls = Tls.of(args.zenoh_tls_ca, args.zenoh_tls_cert, args.zenoh_tls_key, "client")
    except can.CanInitializationError as error:
        raise ValueError(str(error)) from None
    password = None
    if args.password_file is not None:
        password = args.password_file.read_text().strip()
    elif args.user is not None:
        password = os.environ.get(PASSWORD_VARIABLE)
    if args.user is not None and not password:
        raise ValueError(f"--user {args.user} needs --password-file or {PASSWORD_VARIABLE}")
    if tls is None and not is_loopback(host):
        warn_in_clear(program, "the user's password, the state and the commands")
    return ZenohEndpoint(host, args.zenoh_port, args.user, password, tls)
