"""``scara-run``: start the plant and the controller as separate OS processes on one CAN
transport, run a scenario, stop both cleanly (Ctrl-C too) and print the report.

With ``--serve`` it runs nothing itself: the controller is a service holding the scenario as
its task, and ``scara-bridge`` publishes the robot on Zenoh and takes the commands, until
Ctrl-C. ``--secure`` puts the robot's keys on a second router of their own, with Zenoh's
authentication and access control (``config/zenoh/``), the bridge logged in as ``bridge``:
what ``docs/bridge.md`` otherwise has a user assemble by hand.

On the CAN-over-Zenoh transport it first makes sure a router runs on the transport's port:
if none answers it starts ``scara-router`` and stops it at the end, so the router outlives
either node (one may be restarted mid-run, and other tools may join) but not the launcher.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType
from typing import IO

import can
import zenoh
from tqdm import tqdm

from controller.task_rules import load_task
from protocol.bus import add_bus_arguments, parse_options, resolve_transport
from protocol.certs import CertificateSet
from protocol.cli import (
    add_comms_timeout_argument,
    add_verbosity,
    configure_logging,
    interruptible,
    number,
    quiet_on_closed_pipe,
)
from protocol.errors import ScaraError
from protocol.keys import DEFAULT_ROBOT, check_robot
from protocol.node import ClockMode, add_timing_arguments
from protocol.scenario import Mode
from protocol.zenoh_can.config import (
    DEFAULT_HOST,
    DEFAULT_PORT,
    Tls,
    router_reachable,
)
from sim.report import LOG_FILE, RECORDING, format_report, read_run

STOP_GRACE = 5.0
"""s a process gets to exit after SIGINT before it is killed."""
REALTIME_SLACK = 10.0
"""s a real-time controller may take beyond its run's timeout (start-up, a hold before the
run's first joint state)."""
ROUTER_START = 10.0
"""s the router gets to answer after it was started."""
SECURE_CONFIG = Path(__file__).resolve().parent.parent / "config" / "zenoh" / "secure-router.json5"
"""The access control of the robot's keys: who may read, who may command."""
CREDENTIALS = SECURE_CONFIG.parent / "credentials.txt"
"""The demo users, a ``user:password`` a line (change the passwords)."""
SECURE_PORT = 17448
DEFAULT_OUT = Path("out/run")
BRIDGE_USER = "bridge"
"""The user the bridge logs in as: the one ``SECURE_CONFIG`` lets publish and answer."""
ROLES = {"operator": "reads the state and sends commands", "monitor": "reads the state only"}
"""The users ``SECURE_CONFIG`` lets a monitor log in as, and what each may do there."""
PASSWORD_VARIABLE = "SCARA_ZENOH_PASSWORD"
"""Where the bridge takes its password from (bridge/session.py): never on a command line."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scara-run",
        description="Co-simulate a scenario: plant_sim and controller as two OS processes "
        "talking CAN frames only; prints the measures and loop statistics.",
    )
    parser.add_argument("scenario", nargs="?", default="reference", help="scenario file or name")
    parser.add_argument("--mode", choices=[m.value for m in Mode], help="coordination mode")
    parser.add_argument(
        "--clock",
        choices=[m.value for m in ClockMode],
        default=ClockMode.REALTIME.value,
        help="real time (each process on its own clock) or lockstep (deterministic)",
    )
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="results folder")
    parser.add_argument(
        "--controller-first", action="store_true", help="start the controller before the plant"
    )
    parser.add_argument(
        "--inject-faults",
        metavar="SPEC",
        help="drop/corrupt frames both nodes send, e.g. drop=0.05,corrupt=0.01 (tests)",
    )
    parser.add_argument(
        "--timeout",
        type=number(0.0, low_open=True),
        default=600.0,
        metavar="S",
        help="give up after this many seconds (default %(default)g)",
    )
    parser.add_argument(
        "--record",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="record the run to OUT/run.mcap with scara-record (default: on)",
    )
    parser.add_argument(
        "--serve",
        action="store_true",
        help="start the controller as a service and scara-bridge (keys on the CAN router), "
        "then wait for commands on Zenoh until Ctrl-C",
    )
    parser.add_argument(
        "--robot",
        help=f"with --serve: the robot's name on Zenoh (default {DEFAULT_ROBOT}); its CAN frames "
        "go on a channel of that name, so robots started so share the routers but not a bus",
    )
    secure = parser.add_argument_group("access control (with --serve)")
    secure.add_argument(
        "--secure",
        action="store_true",
        help="put the robot's keys on a second router with authentication and access control "
        "(config/zenoh/secure-router.json5), the bridge logged in as user bridge; monitors "
        "log in as operator (may command) or monitor (read-only)",
    )
    secure.add_argument(
        "--credentials",
        type=Path,
        metavar="FILE",
        help="the users of the secure router, user:password a line, bridge among them "
        "(default: config/zenoh/credentials.txt, the demo users: change their passwords)",
    )
    secure.add_argument(
        "--secure-port",
        type=number(1, 65535, integer=True),
        metavar="PORT",
        help=f"port of the secure router (default {SECURE_PORT}; its address is the bus's "
        "host option, 127.0.0.1 unless given)",
    )
    tls = parser.add_argument_group("TLS (every Zenoh link of the run encrypted)")
    tls.add_argument(
        "--tls",
        type=Path,
        metavar="DIR",
        help="the routers listen on tls/ links only, with DIR/server.pem, and every process "
        "joins them checking it against DIR/ca.pem (make DIR with scara-certs --out DIR)",
    )
    tls.add_argument(
        "--mtls",
        action="store_true",
        help="with --tls: the routers let in only processes showing DIR/client.pem (mutual TLS)",
    )
    add_comms_timeout_argument(parser, None, "default: the controller's, see controller --help")
    add_timing_arguments(parser)
    add_bus_arguments(parser)
    add_verbosity(parser)
    return parser


def node_commands(args: argparse.Namespace, time_limit: float) -> tuple[list[str], list[str]]:
    """The command lines of the plant and the controller for ``args``.

    In real time the controller gets the run's timeout ``time_limit`` (plus start-up) at most:
    a controller in another fault waits for a reset that nobody here will send.
    """
    interface, channel = resolve_transport(args.interface, args.channel)
    common = [args.scenario, "--clock", args.clock, "--interface", interface, "--channel", channel]
    for option in args.bus_option:
        common += ["--bus-option", option]
    common += ["--out", str(args.out)] + ["-v"] * args.verbose
    if args.rate:
        common += ["--rate", str(args.rate)]
    if args.realtime_priority:
        common += ["--realtime-priority", str(args.realtime_priority)]
    if args.plain_scheduling:
        common += ["--plain-scheduling"]
    plant = [sys.executable, "-m", "plant_sim.node", *common]
    controller = [sys.executable, "-m", "controller.cli", *common]
    if args.serve:
        controller.append("--service")  # serves until stopped: no wall-time limit
    else:
        wall_time = args.timeout
        if args.clock == ClockMode.REALTIME.value:
            wall_time = min(wall_time, time_limit + REALTIME_SLACK)
        controller += ["--max-wall-time", f"{wall_time:g}"]
    if args.mode:
        controller += ["--mode", args.mode]
    if args.comms_timeout:
        controller += ["--comms-timeout", str(args.comms_timeout)]
    if args.inject_faults:
        plant += ["--inject-faults", f"{args.inject_faults},seed=2"]
        controller += ["--inject-faults", f"{args.inject_faults},seed=1"]
    return plant, controller


def tls_of(args: argparse.Namespace, side: str) -> Tls | None:
    """The TLS files of ``--tls DIR`` for a ``client`` or a ``router`` (None without it)."""
    if args.tls is None:
        return None
    return CertificateSet(args.tls).tls(side, mutual=args.mtls)


def tls_flags(tls: Tls | None, flags: tuple[str, str, str]) -> list[str]:
    """``tls``'s files as the command-line flags ``flags`` (CA, certificate, key) name them."""
    return [] if tls is None else [part for pair in tls.named(flags) for part in pair]


ROUTER_TLS_FLAGS = ("--tls-client-ca", "--tls-cert", "--tls-key")
CLIENT_TLS_FLAGS = ("--zenoh-tls-ca", "--zenoh-tls-cert", "--zenoh-tls-key")


def can_router(args: argparse.Namespace) -> tuple[str, int]:
    """The host and port of the CAN router the bus options name."""
    options = parse_options(args.bus_option)
    return str(options.get("host", DEFAULT_HOST)), int(options.get("port", DEFAULT_PORT))


def keys_router(args: argparse.Namespace) -> tuple[str, int]:
    """The host and port of the router where the robot's keys live: the secure one (at the
    bus's host), or the CAN router."""
    host, port = can_router(args)
    return (host, int(args.secure_port or SECURE_PORT)) if args.secure else (host, port)


def bridge_command(args: argparse.Namespace) -> list[str]:
    """``scara-bridge`` on the same transport, its keys on the CAN router, or on the secure
    one as :data:`BRIDGE_USER` (its password goes in the environment, see :func:`main`)."""
    interface, channel = resolve_transport(args.interface, args.channel)
    options = parse_options(args.bus_option)
    host, port = keys_router(args)
    command = [sys.executable, "-m", "bridge.node", args.scenario, "--interface", interface]
    command += ["--channel", channel, "--zenoh-host", host, "--zenoh-port", str(port)]
    command += tls_flags(tls_of(args, "client"), CLIENT_TLS_FLAGS)
    if args.secure:
        command += ["--user", BRIDGE_USER]
    if args.robot:
        command += ["--robot", args.robot]
    for option in args.bus_option:
        command += ["--bus-option", option]
    if options.get("allow_remote"):
        command.append("--allow-remote")
    return command + ["-v"] * args.verbose


def read_credentials(path: Path) -> dict[str, str]:
    """The users of a Zenoh ``usrpwd`` dictionary file; ScaraError, before anything starts, if
    it cannot be read or has no :data:`BRIDGE_USER` (the bridge could not log in)."""
    try:
        text = path.read_text()
    except OSError as error:
        raise ScaraError(f"--credentials {path}: {error.strerror or error}") from None
    users: dict[str, str] = {}
    for line_number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        user, colon, password = line.partition(":")
        if not colon or not user or not password:
            raise ScaraError(f"--credentials {path}, line {line_number}: not user:password")
        users[user] = password
    if BRIDGE_USER not in users:
        raise ScaraError(
            f"--credentials {path} has no {BRIDGE_USER} user: the bridge logs in as "
            f"{BRIDGE_USER} (add a line {BRIDGE_USER}:PASSWORD)"
        )
    return users


def secure_router_command(args: argparse.Namespace, folder: Path) -> list[str]:
    """``scara-router`` on the secure port with :data:`SECURE_CONFIG`, its users taken from
    ``--credentials``: the access control stays the project's, the passwords are the user's.
    The configuration is written into ``folder``, which the router reads as it starts."""
    config = zenoh.Config.from_file(str(SECURE_CONFIG))
    credentials = (args.credentials or CREDENTIALS).resolve()
    config.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(credentials)))
    path = folder / SECURE_CONFIG.name
    path.write_text(str(config))
    host, port = keys_router(args)
    command = [sys.executable, "-m", "protocol.zenoh_can.router", "--host", host]
    command += ["--port", str(port), "--config", str(path)]
    command += tls_flags(tls_of(args, "router"), ROUTER_TLS_FLAGS)
    if parse_options(args.bus_option).get("allow_remote"):
        command.append("--allow-remote")
    return command + ["-v"] * args.verbose


def serving_hint(args: argparse.Namespace, users: dict[str, str]) -> str:
    """How to reach the robot being served: the monitor's command line, per user."""
    host, port = keys_router(args)
    where = (
        f"--zenoh-port {port}"
        if host == DEFAULT_HOST
        else f"--zenoh-host {host} --zenoh-port {port}"
    )
    if args.robot:
        where += f" --robot {args.robot}"
    where = " ".join([where, *tls_flags(tls_of(args, "client"), CLIENT_TLS_FLAGS)])
    if not args.secure:
        return f"scara-run: serving; watch and command it with: scara-monitor {where}"
    lines = [
        f"scara-run: serving behind access control on {host}:{port}, the users of "
        f"{args.credentials or CREDENTIALS}; connect with:"
    ]
    lines += [
        f"  scara-monitor {where} --user {user:<8}  ({what})"
        for user, what in ROLES.items()
        if user in users
    ]
    lines.append(f"  the user's password in --password-file FILE or in {PASSWORD_VARIABLE}")
    return "\n".join(lines)


def serve(processes: list[subprocess.Popen[bytes]], hint: str) -> int:
    """Print ``hint``; wait until Ctrl-C (0) or until one of ``processes`` ends by itself (1)."""
    print(f"{hint}\nscara-run: Ctrl-C to stop", file=sys.stderr, flush=True)
    try:
        while all(process.poll() is None for process in processes):
            time.sleep(0.2)
    except KeyboardInterrupt:
        return 0
    ended = [process.args for process in processes if process.poll() is not None]
    print(f"scara-run: a process ended on its own: {ended}", file=sys.stderr)
    return 1


def recorder_command(args: argparse.Namespace) -> list[str]:
    """``scara-record`` on the same transport, into ``OUT/run.mcap``."""
    interface, channel = resolve_transport(args.interface, args.channel)
    command = [sys.executable, "-m", "recorder.node", "--out", str(args.out / RECORDING)]
    command += ["--scenario", args.scenario, "--run", str(args.out)]
    command += ["--interface", interface, "--channel", channel]
    for option in args.bus_option:
        command += ["--bus-option", option]
    return command + ["-v"] * args.verbose


def start_recorder(args: argparse.Namespace) -> subprocess.Popen[bytes] | None:
    """The recorder, once it listens (it says so on stderr); None if it failed."""
    recorder = subprocess.Popen(recorder_command(args), stderr=subprocess.PIPE)
    assert recorder.stderr is not None
    said: list[str] = []
    for raw in recorder.stderr:  # with -v, log lines may come first
        said.append(raw.decode())
        sys.stderr.write(said[-1])
        if "recording to" in said[-1]:
            break
    else:
        recorder.wait()
        print(f"scara-run: the recorder did not start: {''.join(said).strip()}", file=sys.stderr)
        return None
    threading.Thread(target=_echo, args=(recorder.stderr,), daemon=True).start()
    return recorder


def _echo(stream: IO[bytes]) -> None:
    for line in stream:
        sys.stderr.write(line.decode())


def router_command(args: argparse.Namespace) -> list[str] | None:
    """The router to start for ``args``: None if the transport is not Zenoh or one answers."""
    interface, _ = resolve_transport(args.interface, args.channel)
    if interface != "zenoh":
        return None
    host, port = can_router(args)
    if router_reachable(host, port, tls=tls_of(args, "client")):
        return None
    command = [sys.executable, "-m", "protocol.zenoh_can.router", "--host", host]
    command += ["--port", str(port), *tls_flags(tls_of(args, "router"), ROUTER_TLS_FLAGS)]
    if parse_options(args.bus_option).get("allow_remote"):
        command.append("--allow-remote")
    return command


def wait_for_router(router: subprocess.Popen[bytes], answers: Callable[[], bool]) -> bool:
    """True once ``answers()`` does, within ROUTER_START; False if ``router`` ends first."""
    deadline = time.monotonic() + ROUTER_START
    while time.monotonic() < deadline and router.poll() is None:
        if answers():
            return True
        time.sleep(0.05)
    return False


def stop(process: subprocess.Popen[bytes]) -> int:
    """SIGINT, then SIGKILL if it does not exit within STOP_GRACE."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(STOP_GRACE)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    return process.returncode


def _interrupt(signum: int, frame: FrameType | None) -> None:
    raise KeyboardInterrupt


def name_the_robot(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """``--robot NAME``: its frames on a CAN-over-Zenoh channel of its own (unless one is
    given) and its results in ``OUT/NAME``, so that a second robot served beside the first
    shares its routers (each launcher starts one only where none answers) and nothing else."""
    if args.robot is None:
        return
    if not args.serve:
        parser.error("--robot goes with --serve: only a served robot has a name on Zenoh")
    try:
        check_robot(args.robot)
    except ValueError as error:
        parser.error(f"--robot: {error}")
    interface, _ = resolve_transport(args.interface, args.channel)
    if interface == "zenoh" and args.channel is None:
        args.channel = args.robot
    if args.out == DEFAULT_OUT:
        args.out = DEFAULT_OUT / args.robot


def check_tls(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """``--tls DIR``: its files there (ScaraError naming the missing one), and the buses
    told to join over TLS; ``--mtls`` only with it."""
    if args.tls is None:
        if args.mtls:
            parser.error("--mtls goes with --tls DIR")
        return
    for side in ("client", "router"):
        tls = tls_of(args, side)
        assert tls is not None
        try:
            tls.check(side)
        except can.CanInitializationError as error:
            raise ScaraError(f"--tls {args.tls}: {error} (make a set with scara-certs)") from None
    client = tls_of(args, "client")
    assert client is not None
    args.bus_option += [
        f"{o}={path}" for o, path in client.named(("tls_ca", "tls_cert", "tls_key"))
    ]


def check_secure(parser: argparse.ArgumentParser, args: argparse.Namespace) -> dict[str, str]:
    """The users of ``--credentials`` when ``--secure`` (none otherwise); exits 2 on flags that
    do not go together (ScaraError from :func:`read_credentials`)."""
    if not args.secure:
        for flag, value in (
            ("--credentials", args.credentials),
            ("--secure-port", args.secure_port),
        ):
            if value is not None:
                parser.error(f"{flag} goes with --secure")
        return {}
    if not args.serve:
        parser.error("--secure goes with --serve: only a served robot has keys to protect")
    if keys_router(args) == can_router(args):
        parser.error(f"--secure-port {args.secure_port} is the CAN router's: choose another")
    if not SECURE_CONFIG.exists():
        raise ScaraError(f"{SECURE_CONFIG} is missing: --secure needs the repository's config/")
    return read_credentials(args.credentials or CREDENTIALS)


@quiet_on_closed_pipe
def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.verbose)
    interruptible()
    signal.signal(signal.SIGTERM, _interrupt)  # stop the nodes on SIGTERM as on Ctrl-C
    try:
        scenario = load_task(args.scenario)
        parse_options(args.bus_option)
        name_the_robot(parser, args)
        check_tls(parser, args)
        users = check_secure(parser, args)
    except (ScaraError, argparse.ArgumentTypeError) as error:
        print(f"scara-run: {error}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    for stale in ("controller.json", "plant_sim.json", LOG_FILE, RECORDING):
        (args.out / stale).unlink(missing_ok=True)
    plant_command, controller_command = node_commands(args, scenario.time_limit)
    order = (
        [controller_command, plant_command]
        if args.controller_first
        else [plant_command, controller_command]
    )
    processes: list[subprocess.Popen[bytes]] = []
    router: subprocess.Popen[bytes] | None = None
    secure_router: subprocess.Popen[bytes] | None = None
    recorder: subprocess.Popen[bytes] | None = None
    interrupted = False
    bridge_environment = None
    try:
        command = router_command(args)
        if command is not None:
            router = subprocess.Popen(command)
            client = tls_of(args, "client")
            if not wait_for_router(router, lambda: router_reachable(*can_router(args), tls=client)):
                print("scara-run: the Zenoh router did not come up", file=sys.stderr)
                return 1
        if args.secure:
            password = users[BRIDGE_USER]
            host, port = keys_router(args)
            client = tls_of(args, "client")
            if router_reachable(host, port, BRIDGE_USER, password, client):  # another's: share it
                print(f"scara-run: joining the secure router on {host}:{port}", file=sys.stderr)
            else:
                with tempfile.TemporaryDirectory(prefix="scara-run-") as folder:  # read at start
                    secure_router = subprocess.Popen(secure_router_command(args, Path(folder)))
                    if not wait_for_router(
                        secure_router,
                        lambda: router_reachable(host, port, BRIDGE_USER, password, client),
                    ):
                        print(
                            f"scara-run: the secure router did not let {BRIDGE_USER} in on "
                            f"{host}:{port} (is the port taken? see its output above)",
                            file=sys.stderr,
                        )
                        return 1
            bridge_environment = os.environ | {PASSWORD_VARIABLE: password}
        if args.record and not args.serve:
            recorder = start_recorder(args)
            if recorder is None:
                return 1
        processes += [subprocess.Popen(command) for command in order]
        if args.serve:
            processes.append(subprocess.Popen(bridge_command(args), env=bridge_environment))
            watched = processes + ([secure_router] if secure_router is not None else [])
            return serve(watched, serving_hint(args, users))
        controller = processes[0] if args.controller_first else processes[1]
        started = time.monotonic()
        with tqdm(
            total=round(scenario.duration, 1),
            unit="s",
            desc=f"{scenario.name} ({args.clock})",
            disable=None,
            bar_format="{l_bar}{bar}| {n:.1f}/{total} s wall",
        ) as progress:
            while controller.poll() is None:
                time.sleep(0.1)
                progress.n = min(time.monotonic() - started, progress.total)
                progress.refresh()
    except KeyboardInterrupt:
        interrupted = True
        print("\nscara-run: interrupted, stopping the nodes", file=sys.stderr)
    finally:
        codes = [stop(process) for process in reversed(processes)]
        if recorder is not None and stop(recorder) == 0:
            (args.out / LOG_FILE).unlink(missing_ok=True)  # its copy in the recording is kept
        for a_router in (secure_router, router):
            if a_router is not None:
                stop(a_router)
    if interrupted:
        return 130
    if not (args.out / "controller.json").exists():
        print(f"scara-run: the controller wrote no result (exit codes {codes})", file=sys.stderr)
        return 1
    print(format_report(read_run(args.out)))
    return controller.returncode or 0


if __name__ == "__main__":
    raise SystemExit(main())
