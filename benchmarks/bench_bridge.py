"""Bridge benchmark: what ``scara-bridge`` costs and how quickly it delivers.

1. **CAN to Zenoh**: plant, controller (service) and bridge as processes on CAN-over-Zenoh;
   a Zenoh subscriber here takes ``joints`` and ``tcp`` at the default 100 Hz during
   reference runs started by commands. The latency of a sample is its arrival here minus
   its ``t``, the receive time of the CAN frame behind it at the bridge (one host, one clock).
2. **Task upload over ISO-TP**: the ``waypoints`` command from the Zenoh query to the
   controller's answer, which includes checking, the ISO-TP transfer and the answer frame.
3. **The controller with and without the bridge**: the reference run at 500 Hz, the bridge
   (and a subscriber) present in every other run, side by side; tick lateness p99 of each.

Run from the project root: ``python benchmarks/bench_bridge.py [--runs 6] [--json PATH]``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from tqdm import tqdm

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from bench_link import background, router  # noqa: E402

from bridge.session import ZenohEndpoint  # noqa: E402
from protocol.keys import command_key, state_key  # noqa: E402
from protocol.scenario import encode_task, load_scenario, task_document  # noqa: E402

ROBOT = "arm1"
TARGET_P99_MS = 2.0
TARGET_RATIO = 1.10
UPLOADS = 40


def bus_args(port: int) -> list[str]:
    return ["--interface", "zenoh", "--channel", f"bench{port}", "--bus-option", f"port={port}"]


def node(module: str, *args: str) -> list[str]:
    return [sys.executable, "-m", module, *args]


def query(session: zenoh.Session, key: str, body: Any = None, timeout: float = 5.0) -> Any:
    payload = None if body is None else json.dumps(body)
    for reply in session.get(key, payload=payload, timeout=timeout):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return None


def wait_for(condition: Any, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise SystemExit(f"timed out waiting for {what}")
        time.sleep(0.05)


def delivery(port: int, runs: int) -> dict[str, Any]:
    """Parts 1 and 2 on one stack."""
    stack = [
        node("plant_sim.node", *bus_args(port)),
        node("controller.cli", *bus_args(port)),
        node("bridge.node", "--zenoh-port", str(port), *bus_args(port)),
    ]
    task = task_document(load_scenario("reference"))
    latencies: dict[str, list[float]] = {"joints": [], "tcp": []}
    events: list[str] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        received = time.time()
        name = str(sample.key_expr).rsplit("/", 1)[1]
        payload = json.loads(sample.payload.to_bytes())
        with lock:
            if name == "events":
                events.append(payload["event"])
            else:
                latencies[name].append(received - payload["t"])

    with background(stack):
        session = ZenohEndpoint("127.0.0.1", port).open()
        subscribers = [
            session.declare_subscriber(state_key(ROBOT, name), on_sample)
            for name in ("joints", "tcp", "events")
        ]

        def ready() -> bool:
            status = query(session, state_key(ROBOT, "status"), timeout=1.0)
            return bool(status and status["controller"]["state"] == "ready")

        wait_for(ready, 30.0, "the stack to come up")
        uploads = []
        for index in tqdm(range(UPLOADS), desc="[1/3] task uploads", file=sys.stderr):
            waypoints = [dict(w) for w in task["waypoints"]]
            waypoints[-1]["z"] += 0.001 * (index % 2)  # a change each time
            start = time.perf_counter()
            reply = query(session, command_key(ROBOT, "waypoints"), {"waypoints": waypoints})
            uploads.append(time.perf_counter() - start)
            if not (reply and reply["accepted"]):
                raise SystemExit(f"waypoints refused: {reply}")
        for name in ("obstacle", "mode"):
            body = {"obstacle": task["obstacle"]} if name == "obstacle" else {"mode": "fuzzy"}
            if not query(session, command_key(ROBOT, name), body)["accepted"]:
                raise SystemExit(f"{name} refused")
        with lock:
            for samples in latencies.values():
                samples.clear()
        for _ in tqdm(range(runs), desc="[2/3] runs through the bridge", file=sys.stderr):
            with lock:
                finished = events.count("run_finished")
            if not query(session, command_key(ROBOT, "run"))["accepted"]:
                raise SystemExit("run refused")
            wait_for(lambda f=finished: events.count("run_finished") > f, 60.0, "the run's end")
            time.sleep(0.5)
        status = query(session, state_key(ROBOT, "status"))
        for subscriber in subscribers:
            subscriber.undeclare()
        session.close()  # type: ignore[no-untyped-call]
    size = len(encode_task(load_scenario("reference"), 1))
    result: dict[str, Any] = {
        "upload_p50_ms": 1e3 * float(np.percentile(uploads, 50)),
        "upload_p99_ms": 1e3 * float(np.percentile(uploads, 99)),
        "task_bytes": size,
        "task_frames": 1 + -(-(size - 6) // 7),  # ISO-TP: a first frame, then 7 bytes each
        "dropped": sum(status["bridge"]["dropped"].values()),
    }
    for name, samples in latencies.items():
        values = np.asarray(samples) * 1e3
        result[name] = {
            "samples": len(samples),
            "p50_ms": float(np.percentile(values, 50)),
            "p99_ms": float(np.percentile(values, 99)),
            "max_ms": float(values.max()),
        }
    return result


def reference_run(port: int, out: Path, with_bridge: bool) -> float:
    """One launcher run at 500 Hz (with a bridge and a subscriber beside it, or not):
    the controller's tick lateness p99 in microseconds."""
    extra = []
    if with_bridge:
        extra = [node("bridge.node", "--zenoh-port", str(port), *bus_args(port))]
    with background(extra):
        session = ZenohEndpoint("127.0.0.1", port).open() if with_bridge else None
        subscriber = None
        if session is not None:
            subscriber = session.declare_subscriber(state_key(ROBOT, "joints"), lambda s: None)
            wait_for(
                lambda: query(session, state_key(ROBOT, "status"), timeout=0.5) is not None,
                30.0,
                "the bridge",
            )
        command = node(
            "sim.launch", "reference", "--clock", "realtime", "--rate", "500",
            "--out", str(out), *bus_args(port),
        )  # fmt: skip
        subprocess.run(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        if subscriber is not None and session is not None:
            subscriber.undeclare()
            session.close()  # type: ignore[no-untyped-call]
    result = json.loads((out / "controller.json").read_text())
    if not result["completed"]:
        raise SystemExit(f"a reference run did not complete: {result['faults']}")
    lateness: float = result["loop"]["lateness_p99_us"]
    return lateness


def verdict(passed: bool) -> str:
    return "PASS" if passed else "FAIL"


def table(delivered: dict[str, Any], without: list[float], with_: list[float]) -> str:
    lines = [
        "| measure | result | target | |",
        "|---|---|---|---|",
    ]
    for name in ("joints", "tcp"):
        d = delivered[name]
        lines.append(
            f"| CAN to Zenoh, `{name}` at 100 Hz, p50 / p99 / max ({d['samples']} samples) "
            f"| {d['p50_ms']:.2f} / {d['p99_ms']:.2f} / {d['max_ms']:.2f} ms "
            f"| p99 <= {TARGET_P99_MS:g} ms | {verdict(d['p99_ms'] <= TARGET_P99_MS)} |"
        )
    lines += [
        f"| samples dropped by the bridge | {delivered['dropped']} | 0 "
        f"| {verdict(delivered['dropped'] == 0)} |",
        f"| task upload (`waypoints`: query to answer, ISO-TP {delivered['task_bytes']} B "
        f"in {delivered['task_frames']} frames), p50 / p99 "
        f"| {delivered['upload_p50_ms']:.1f} / {delivered['upload_p99_ms']:.1f} ms "
        "| reported | |",
    ]
    lines += lateness_rows(without, with_, "the bridge", "the bridge and a subscriber")
    return "\n".join(lines)


def lateness_rows(without: list[float], with_: list[float], absent: str, beside: str) -> list[str]:
    """The rows of the controller's tick lateness p99 (us, one per run) without ``absent`` and
    with ``beside``, and the ratio of their medians against :data:`TARGET_RATIO`."""
    ratio = statistics.median(with_) / statistics.median(without)
    return [
        f"| controller tick lateness p99 without {absent}, median of "
        f"{len(without)} runs | {statistics.median(without):.0f} us "
        f"({', '.join(f'{v:.0f}' for v in without)}) | reported | |",
        f"| ... with {beside}, median of {len(with_)} runs "
        f"| {statistics.median(with_):.0f} us ({', '.join(f'{v:.0f}' for v in with_)}) "
        "| reported | |",
        f"| with / without | {ratio:.2f} | <= {TARGET_RATIO:.2f} "
        f"| {verdict(ratio <= TARGET_RATIO)} |",
    ]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument(
        "--runs", type=int, default=6, help="runs of each kind (default %(default)s)"
    )
    parser.add_argument("--json", type=Path, help="also write the numbers as JSON here")
    args = parser.parse_args(argv)
    with router() as port, tempfile.TemporaryDirectory() as folder:
        delivered = delivery(port, args.runs)
        without: list[float] = []
        with_: list[float] = []
        for index in tqdm(range(2 * args.runs), desc="[3/3] with / without", file=sys.stderr):
            bridged = index % 2 == 1
            lateness = reference_run(port, Path(folder) / str(index), bridged)
            (with_ if bridged else without).append(lateness)
    print(table(delivered, without, with_))
    if args.json:
        numbers = {"delivery": delivered, "lateness_without_us": without, "with_us": with_}
        args.json.write_text(json.dumps(numbers, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
