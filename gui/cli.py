"""``scara-gui``: the paper's GUI in a browser, on the robots of a Zenoh network or on a
recording (``scara-gui run.mcap``).

Live, it joins the router as a client with the user's credentials, as ``scara-monitor``
does (loopback by default, no scouting, ``bridge/session.py``). Its web server listens on
127.0.0.1 unless ``--host ADDRESS --allow-remote``, as the routers do, serves ``https`` with
``--https-cert``, and takes only requests that name a host it serves and come from its own
page (``gui/access.py``): whoever reaches the page may command the robot as the user it
joined as.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import can
import uvicorn
import zenoh

from bridge.session import add_zenoh_arguments, endpoint_from_args
from controller.task_rules import load_task
from gui.live import Fleet
from gui.recording import Recording
from gui.server import MAX_MESSAGE, Gui, build_app
from protocol.cli import (
    add_verbosity,
    configure_logging,
    interruptible,
    number,
    quiet_on_closed_pipe,
)
from protocol.errors import ScaraError
from protocol.keys import check_robot
from protocol.scenario import Scenario
from protocol.zenoh_can.config import (
    DEFAULT_HOST,
    check_host,
    close,
    is_loopback,
    served_hosts,
    warn_in_clear,
)
from recorder.mcap_can import RecordingError

DEFAULT_PORT = 17480
MAX_CONNECTIONS = 64
"""Connections (pages, requests) served at once: beyond, a new one is answered 503 at once,
so that a flood of them cannot starve the pages already open."""
READ_ONLY_USERS = ("monitor",)
"""Users the secure router lets read only (``config/zenoh/secure-router.json5``): their
page has no buttons to press, and this server sends no command for them."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-gui",
        description="Watch and command the SCARA robots of a Zenoh network in a browser, "
        "or play a recording (scara-gui run.mcap).",
    )
    parser.add_argument("recording", nargs="?", type=Path, help="an MCAP recording to play")
    parser.add_argument(
        "--host",
        default=DEFAULT_HOST,
        help="address the web server listens on (default %(default)s; another needs "
        "--allow-remote)",
    )
    parser.add_argument(
        "--port",
        type=number(1, 65535, integer=True),
        default=DEFAULT_PORT,
        help="web server port (default %(default)s)",
    )
    parser.add_argument(
        "--allow-host",
        action="append",
        default=[],
        metavar="NAME",
        help="a name the page is reached by, beside 127.0.0.1, localhost, ::1 and --host "
        "(repeatable); a request naming any other host is refused (DNS rebinding)",
    )
    parser.add_argument(
        "--https-cert",
        type=Path,
        metavar="PEM",
        help="serve https and wss with this certificate (scara-certs: server.pem)",
    )
    parser.add_argument("--https-key", type=Path, metavar="PEM", help="its private key")
    parser.add_argument(
        "--read-only",
        action="store_true",
        help=f"send no command (implied for the users {', '.join(READ_ONLY_USERS)})",
    )
    parser.add_argument(
        "--scenario",
        help="scenario file or name for the robot's geometry (default: the packaged one)",
    )
    add_zenoh_arguments(parser, robot_help="the robot a page shows first (the page lists all)")
    add_verbosity(parser)
    return parser


def check_https(certificate: Path | None, key: Path | None) -> bool:
    """Whether to serve https: both files given and there (``ValueError`` naming the flag
    otherwise), or neither."""
    if (certificate is None) != (key is None):
        raise ValueError("--https-cert and --https-key go together")
    for flag, path in (("--https-cert", certificate), ("--https-key", key)):
        if path is not None and not path.is_file():
            raise ValueError(f"{flag} {path}: no such file")
    return certificate is not None


@quiet_on_closed_pipe
def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose)
    interruptible()
    try:
        host = check_host(args.host, allow_remote=args.allow_remote, name="--host")
        https = check_https(args.https_cert, args.https_key)
        robot = check_robot(args.robot)
        base = load_task(args.scenario) if args.scenario else Scenario("gui", (), None)
        read_only = args.read_only or args.user in READ_ONLY_USERS
        if args.recording is not None:
            gui = Gui(robot, read_only=True, recording=Recording.read(args.recording))
        else:
            endpoint = endpoint_from_args(args, "scara-gui")
            gui = Gui(robot, read_only, user=args.user)
    except (can.CanInitializationError, ValueError, OSError, ScaraError, RecordingError) as error:
        print(f"scara-gui: {error}", file=sys.stderr)
        return 2
    if gui.recording is None:
        try:
            gui.session = endpoint.open()
        except zenoh.ZError as error:
            print(f"scara-gui: cannot join {endpoint}: {error}", file=sys.stderr)
            return 1
        gui.fleet = Fleet(gui.session, base)
    config = uvicorn.Config(
        build_app(gui, served_hosts(host, args.allow_host)),
        host=host,
        port=int(args.port),
        log_level="warning" if args.verbose < 2 else "info",
        ws_max_size=MAX_MESSAGE,
        limit_concurrency=MAX_CONNECTIONS,
        lifespan="off",
        ssl_certfile=args.https_cert,
        ssl_keyfile=args.https_key,
    )
    if not https and not is_loopback(host):
        warn_in_clear("scara-gui", "the page, its WebSocket and every command it sends")
    where = f"[{host}]" if ":" in host else host
    scheme = "https" if https else "http"
    print(
        f"scara-gui: {scheme}://{where}:{args.port}/ (Ctrl-C to stop)", file=sys.stderr, flush=True
    )
    try:
        uvicorn.Server(config).run()  # stops serving on SIGINT, then raises it again
    except KeyboardInterrupt:
        print("scara-gui: stopped", file=sys.stderr)
    finally:
        if gui.fleet is not None:
            gui.fleet.close()
        if gui.session is not None:
            close(gui.session)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
