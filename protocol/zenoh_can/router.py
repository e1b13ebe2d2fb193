"""``scara-router``: the Zenoh router every CAN-over-Zenoh bus is a client of.

It listens on one explicit endpoint (``tcp/127.0.0.1:17447`` by default; with
``--tls-cert`` and ``--tls-key`` a ``tls/`` one only, and with ``--tls-client-ca`` it lets in
only clients whose certificate that CA signed), with multicast scouting off, and forwards
frames between the buses in Zenoh's own threads. It holds no state a bus needs: buses may
start before it (they wait up to their ``open_timeout``), and after it restarts they
reconnect by themselves. ``scara-run`` starts one when none answers.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from types import FrameType

import can
import zenoh

from protocol.cli import add_verbosity, configure_logging, number, quiet_on_closed_pipe
from protocol.realtime import tune_process
from protocol.zenoh_can.config import (
    DEFAULT_HOST,
    DEFAULT_PORT,
    Tls,
    build_zenoh_config,
    check_host,
    check_port,
    close,
    endpoint,
    is_loopback,
    router_config,
    warn_in_clear,
)

log = logging.getLogger("scara.router")


class Router:
    """A Zenoh router session on ``host:port``; :meth:`close` ends it."""

    def __init__(
        self,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        *,
        allow_remote: bool = False,
        config_file: str | None = None,
        tls: Tls | None = None,
    ) -> None:
        self.host = check_host(host, allow_remote=allow_remote)
        self.port = check_port(port)
        self.endpoint = endpoint(self.host, self.port, tls=tls is not None)
        settings = router_config(self.host, self.port, tls=tls)
        try:
            self.session = zenoh.open(build_zenoh_config(settings, config_file))
        except zenoh.ZError as error:
            raise can.CanInitializationError(
                f"cannot listen on {self.endpoint}: {error} (is a router already running "
                "there? choose another port with --port)"
            ) from None

    def close(self) -> None:
        close(self.session)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-router",
        description="The Zenoh router of the CAN-over-Zenoh transport: start it once, then "
        "start the nodes (and python-can's tools) in any order. Loopback only by default.",
    )
    parser.add_argument(
        "--host", default=DEFAULT_HOST, help="address to listen on (default %(default)s)"
    )
    parser.add_argument(
        "--port",
        type=number(1, 65535, integer=True),
        default=DEFAULT_PORT,
        help="TCP port to listen on (default %(default)s)",
    )
    parser.add_argument(
        "--allow-remote",
        action="store_true",
        help="accept a --host that is not a loopback address (to join other hosts on purpose)",
    )
    parser.add_argument(
        "--config",
        metavar="JSON5",
        help="a Zenoh configuration file under ours: authentication and access control, "
        "e.g. config/zenoh/secure-router.json5 (listen, mode and scouting stay ours)",
    )
    tls = parser.add_argument_group(
        "TLS (scara-certs makes a set): listen on a tls/ link only, never in clear"
    )
    tls.add_argument("--tls-cert", type=Path, metavar="PEM", help="the router's certificate")
    tls.add_argument("--tls-key", type=Path, metavar="PEM", help="its private key")
    tls.add_argument(
        "--tls-client-ca",
        type=Path,
        metavar="PEM",
        help="let in only clients with a certificate this CA signed (mutual TLS)",
    )
    add_verbosity(parser)
    return parser


@quiet_on_closed_pipe
def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose)
    tune_process()
    try:
        tls = Tls.of(args.tls_client_ca, args.tls_cert, args.tls_key, "router")
        router = Router(
            args.host, args.port, allow_remote=args.allow_remote, config_file=args.config, tls=tls
        )
    except can.CanInitializationError as error:
        log.error("%s", error)
        return 2
    if tls is None and args.allow_remote and not is_loopback(router.host):
        warn_in_clear("scara-router", "frames, state, user names, passwords and commands")
    stopped = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stopped.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    print(
        f"scara-router: routing on {router.endpoint} (Ctrl-C to stop)", file=sys.stderr, flush=True
    )
    stopped.wait()
    router.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
