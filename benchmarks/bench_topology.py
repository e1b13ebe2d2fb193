"""The Zenoh topologies we considered for CAN over Zenoh, measured side by side on loopback.

For each topology, with raw Zenoh sessions (no project code in the data path):

- round trip at 500 Hz between two processes: one 8-byte put, answered with three puts from
  the far end's callback; p50, p99, p99.9, and the share answered within 2 ms;
- survival: four members, the first one killed, a fifth started: does every live member
  hear every other in the last second of the trial (the fifth joined 4 s before its end)?

Topologies:

- ``holder``: the first member listens on the well-known port, the others connect to it and
  listen on an ephemeral port; gossip links them (the transport before the router);
- ``peers+router``: a router on the port; members are peers connecting to it and listening
  on an ephemeral port, so gossip may link them directly;
- ``clients+router``: a router on the port; members are clients of it (the product's).

Run from the project root: ``python benchmarks/bench_topology.py [--seconds 8] [--trials 3]``.
Every endpoint is on 127.0.0.1 and multicast scouting is off.
"""

from __future__ import annotations

import argparse
import json
import os
import struct
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # the tests' helpers: tests.support
from tests.support import free_port  # noqa: E402

TOPOLOGIES = ("holder", "peers+router", "clients+router")
PERIOD = 0.002


def config(topology: str, port: int, first: bool) -> Any:
    """The session config of one member."""
    import zenoh

    endpoint = f"tcp/127.0.0.1:{port}"
    settings: dict[str, Any] = {"scouting/multicast/enabled": False}
    if topology == "clients+router":
        settings |= {"mode": "client", "listen/endpoints": [], "connect/endpoints": [endpoint]}
    elif topology == "holder" and first:
        settings |= {"mode": "peer", "listen/endpoints": [endpoint], "connect/endpoints": []}
    else:
        settings |= {
            "mode": "peer",
            "listen/endpoints": ["tcp/127.0.0.1:0"],
            "connect/endpoints": [endpoint],
        }
    built = zenoh.Config()
    for path, value in settings.items():
        built.insert_json5(path, json.dumps(value))
    return built


def router(port: int) -> None:
    import zenoh

    built = zenoh.Config()
    for path, value in {
        "mode": "router",
        "scouting/multicast/enabled": False,
        "listen/endpoints": [f"tcp/127.0.0.1:{port}"],
    }.items():
        built.insert_json5(path, json.dumps(value))
    session = zenoh.open(built)
    time.sleep(3600)
    session.close()


def pong(topology: str, port: int) -> None:
    import zenoh

    session = zenoh.open(config(topology, port, first=True))
    publisher = session.declare_publisher("bench/state")

    def answer(sample: Any) -> None:
        payload = sample.payload.to_bytes()
        for index in range(3):
            publisher.put(payload + bytes([index]))

    session.declare_subscriber("bench/cmd", answer)
    time.sleep(3600)


def ping(topology: str, port: int, seconds: float) -> dict[str, float]:
    import zenoh

    session = zenoh.open(config(topology, port, first=False))
    publisher = session.declare_publisher("bench/cmd")
    arrived: dict[int, float] = {}

    def on_state(sample: Any) -> None:
        payload = sample.payload.to_bytes()
        if payload[-1] == 2:
            arrived[struct.unpack_from("<I", payload)[0]] = time.monotonic()

    session.declare_subscriber("bench/state", on_state)
    while not publisher.matching_status.matching:
        time.sleep(0.01)
    time.sleep(1.0)
    sent: dict[int, float] = {}
    deadline = time.monotonic()
    for tick in range(int(seconds / PERIOD)):
        deadline += PERIOD
        remaining = deadline - time.monotonic()
        if remaining > 0:
            time.sleep(remaining)
        sent[tick] = time.monotonic()
        publisher.put(struct.pack("<I", tick))
    time.sleep(0.2)
    trips = np.array([arrived.get(tick, sent[tick] + 1.0) - sent[tick] for tick in sent]) * 1e6
    return {
        "p50_us": float(np.percentile(trips, 50)),
        "p99_us": float(np.percentile(trips, 99)),
        "p999_us": float(np.percentile(trips, 99.9)),
        "within_2ms": float(np.mean(trips <= 2000.0)),
    }


def member(topology: str, port: int, name: str, first: bool, end: float) -> None:
    """Puts its name every 20 ms until the wall-clock time ``end``; prints the names it heard
    in the last second before it."""
    import zenoh

    session = zenoh.open(config(topology, port, first))
    publisher = session.declare_publisher("bench/members")
    heard: dict[str, float] = {}
    session.declare_subscriber(
        "bench/members",
        lambda sample: heard.__setitem__(sample.payload.to_bytes().decode(), time.time()),
    )
    while time.time() < end:
        publisher.put(name.encode())
        time.sleep(0.02)
    recent = sorted(who for who, when in heard.items() if when > end - 1.0 and who != name)
    print(json.dumps(recent), flush=True)
    os._exit(0)  # zenoh's callbacks may hold a session open at interpreter exit


def spawn(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, str(Path(__file__)), *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )


def with_router(topology: str, port: int) -> subprocess.Popen[str] | None:
    if topology == "holder":
        return None
    started = spawn("--router", str(port))
    time.sleep(1.0)
    return started


def round_trip(topology: str, seconds: float) -> dict[str, float]:
    port = free_port()
    helper = with_router(topology, port)
    far = spawn("--pong", topology, str(port))
    time.sleep(1.0)
    try:
        done = spawn("--ping", topology, str(port), str(seconds))
        out, _ = done.communicate(timeout=seconds + 60)
        result: dict[str, float] = json.loads(out)
        return result
    finally:
        for process in (far, helper):
            if process is not None:
                process.kill()
                process.wait()


def survival(topology: str) -> bool:
    """Four members, the first killed after 3 s, a fifth joins: all live ones hear all."""
    port = free_port()
    helper = with_router(topology, port)
    names = ["a", "b", "c", "d"]
    end = f"{time.time() + 8.0:.3f}"  # the fifth has 2 s after joining, then 1 s is checked
    members = {
        name: spawn("--member", topology, str(port), name, str(int(index == 0)), end)
        for index, name in enumerate(names)
    }
    try:
        time.sleep(3.0)
        members.pop("a").kill()
        members["e"] = spawn("--member", topology, str(port), "e", "0", end)
        live = set(members)
        ok = True
        for name, process in members.items():
            out, _ = process.communicate(timeout=30)
            ok &= set(json.loads(out or "[]")) == live - {name}
        return ok
    finally:
        for process in members.values():
            if process.poll() is None:
                process.kill()
        if helper is not None:
            helper.kill()
            helper.wait()


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument("--seconds", type=float, default=8.0, help="round-trip measurement")
    parser.add_argument("--trials", type=int, default=3, help="survival trials per topology")
    parser.add_argument("--router", help=argparse.SUPPRESS)
    parser.add_argument("--pong", nargs=2, help=argparse.SUPPRESS)
    parser.add_argument("--ping", nargs=3, help=argparse.SUPPRESS)
    parser.add_argument("--member", nargs=5, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.router:
        router(int(args.router))
    elif args.pong:
        pong(args.pong[0], int(args.pong[1]))
    elif args.ping:
        print(json.dumps(ping(args.ping[0], int(args.ping[1]), float(args.ping[2]))))
        os._exit(0)
    elif args.member:
        topology, port, name, first, end = args.member
        member(topology, int(port), name, first == "1", float(end))
    else:
        print("| topology | round trip p50 / p99 / p99.9 (us) | within 2 ms | "
              "first member killed, a fifth joins: all hear all |")  # fmt: skip
        print("|---|---:|---:|---:|")
        for topology in TOPOLOGIES:
            trip = round_trip(topology, args.seconds)
            survived = sum(survival(topology) for _ in range(args.trials))
            print(
                f"| {topology} | {trip['p50_us']:.0f} / {trip['p99_us']:.0f} / "
                f"{trip['p999_us']:.0f} | {100 * trip['within_2ms']:.2f} % "
                f"| {survived} of {args.trials} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
