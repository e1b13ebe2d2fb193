"""TLS benchmark: the controller's loop over CAN-over-Zenoh with every link on TLS against the
same in clear, side by side.

Runs ``scara-run reference`` at 500 Hz in real time, alternately without and with ``--tls``
(a ``scara-certs`` set; with ``--mtls`` the routers ask for the client certificate too),
each run with a router of its own, and compares the controller's tick lateness p99 and the
command-to-state round trip, pair by pair (one run of each, back to back, so both see the
same machine).

Prints a Markdown table and the ratio TLS / clear of the median lateness p99 (target: within
1.10). Run from the project root: ``python benchmarks/bench_tls.py [--pairs 5] [--mtls]
[--json PATH]``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bench_link import RATE_HZ, ROOT, summarise
from tqdm import tqdm

from tests.support import free_port, make_certificates

TARGET_RATIO = 1.10


def run_once(out: Path, tls: list[str]) -> dict[str, Any]:
    """One reference run through a router of its own (``scara-run`` starts it, on TLS with
    ``tls``); its summary."""
    port = free_port()
    command = [
        sys.executable, "-m", "sim.launch", "reference", "--clock", "realtime",
        "--rate", f"{RATE_HZ:g}", "--out", str(out), "--no-record", "--interface", "zenoh",
        "--channel", f"tls{port}", "--bus-option", f"port={port}", *tls,
    ]  # fmt: skip
    subprocess.run(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return summarise(json.loads((out / "controller.json").read_text()))


def table(pairs: list[tuple[dict[str, Any], dict[str, Any]]], link: str) -> str:
    lines = [
        f"| pair | lateness p99 clear / {link} (us) | ratio | round trip p50 clear / {link} "
        "(us) | completed |",
        "|---|---:|---:|---:|---|",
    ]
    for index, (clear, tls) in enumerate(pairs, 1):
        ratio = tls["lateness_p99_us"] / clear["lateness_p99_us"]
        both = "yes" if clear["completed"] and tls["completed"] else "NO"
        lines.append(
            f"| {index} | {clear['lateness_p99_us']:.0f} / {tls['lateness_p99_us']:.0f} "
            f"| {ratio:.2f} | {clear['rtt_p50_us']:.0f} / {tls['rtt_p50_us']:.0f} | {both} |"
        )
    clear_p99 = statistics.median(clear["lateness_p99_us"] for clear, _ in pairs)
    tls_p99 = statistics.median(tls["lateness_p99_us"] for _, tls in pairs)
    ratio = tls_p99 / clear_p99
    verdict = "PASS" if ratio <= TARGET_RATIO else "FAIL"
    clear_trip = statistics.median(clear["rtt_p50_us"] for clear, _ in pairs)
    tls_trip = statistics.median(tls["rtt_p50_us"] for _, tls in pairs)
    lines += [
        "",
        f"median lateness p99: clear {clear_p99:.0f} us, {link} {tls_p99:.0f} us; "
        f"ratio {ratio:.2f} (target <= {TARGET_RATIO:.2f}: {verdict})",
        f"median round trip p50: clear {clear_trip:.0f} us, {link} {tls_trip:.0f} us",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n", 1)[0])
    parser.add_argument("--pairs", type=int, default=5, help="runs of each (default 5)")
    parser.add_argument("--mtls", action="store_true", help="mutual TLS: client certificates")
    parser.add_argument("--json", type=Path, help="also write the numbers as JSON here")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as folder:
        certs = make_certificates(Path(folder) / "certs")
        tls = ["--tls", str(certs), *(["--mtls"] if args.mtls else [])]
        pairs = []
        for index in tqdm(range(args.pairs), desc="pairs (clear, TLS)", file=sys.stderr):
            clear = run_once(Path(folder) / f"clear{index}", [])
            secured = run_once(Path(folder) / f"tls{index}", tls)
            pairs.append((clear, secured))
    print(table(pairs, "mTLS" if args.mtls else "TLS"))
    if args.json:
        numbers = [{"clear": clear, "tls": tls} for clear, tls in pairs]
        args.json.write_text(json.dumps({"mtls": args.mtls, "pairs": numbers}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
