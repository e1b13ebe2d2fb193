"""Instructions, not seconds: one control step and one fuzzy inference counted by callgrind.

On these shared machines wall times of the same code differ by 30 % from one run to the next;
``valgrind --tool=callgrind`` counts the instructions the interpreter executes, the same
whatever else the machine is doing. Each count is the difference between a child that
replays the work and one that only sets it up, divided by the work done: the instructions of
one ``ControlLaw.step`` over the reference scenario's ticks (each mode), and of one
``FuzzyInference.weights`` over 3000 inputs spread across its universes. The set-up (the
reference scenario simulated) is some 3.5 billion instructions, and its count moves by a few
million from one child to the next; the steps are replayed STEP_REPLAYS times, which divides
what that does to one step's count by as much. The counts of one tree still move by some
2,500 instructions a step (0.6 %) from one run to the next: compare the ratios of several
runs. ``--before REV`` counts REV's code too, beside this tree's. Needs valgrind (Debian's
``valgrind``); about a minute a count.

Run from the project root: ``python benchmarks/bench_instructions.py [--before REV]``.
"""

from __future__ import annotations

import argparse
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from against import ROOT, tree_at

FUZZY_INPUTS = 3000
STEP_REPLAYS = 3
"""The reference scenario's ticks stepped through this many times in the counted child."""


def child(what: str, repeats: int) -> None:
    """The work counted (in a child under valgrind): ``what`` ``repeats`` times over."""
    from controller.control_law import ControlLaw
    from controller.fuzzy import FuzzyInference, RuleBase
    from protocol.scenario import Mode, load_scenario
    from sim.simulation import simulate

    if what == "inference":
        inference = FuzzyInference(RuleBase.load())
        rng = random.Random(1)
        inputs = [(rng.uniform(0.0, 0.2), rng.uniform(-3.1, 3.1)) for _ in range(FUZZY_INPUTS)]
        for _ in range(repeats):
            for distance, beta in inputs:
                inference.weights(distance, beta)
        return
    scenario = load_scenario("reference").with_mode(Mode(what))
    log = simulate(scenario).log
    ticks = [
        (float(t), (float(a), float(b), float(c)))
        for t, a, b, c in log.columns("t", "theta1", "theta2", "d3")
    ]
    for _ in range(repeats):
        law = ControlLaw.for_scenario(scenario)
        for t, joints in ticks:
            law.step(t, joints)


def count(tree: Path, what: str, repeats: int) -> int:
    """Instructions of a child running ``what`` ``repeats`` times on ``tree``'s code."""
    done = subprocess.run(
        [
            "valgrind",
            "--tool=callgrind",
            "--callgrind-out-file=/dev/null",
            sys.executable,
            str(Path(__file__).resolve()),
            "--child",
            what,
            str(repeats),
        ],
        cwd=tree,
        env=dict(os.environ, PYTHONPATH=str(tree)),
        capture_output=True,
        text=True,
        check=True,
    )
    found = re.search(r"Collected : (\d+)", done.stderr)
    if found is None:
        raise RuntimeError(f"no count from callgrind:\n{done.stderr[-2000:]}")
    return int(found.group(1))


def per_unit(tree: Path, what: str) -> float:
    """Instructions of one inference, or of one step of the reference scenario in mode
    ``what``."""
    if what == "inference":
        units, repeats = FUZZY_INPUTS * 2, 2
    else:
        from protocol.scenario import load_scenario

        scenario = load_scenario("reference")
        ticks = round(scenario.duration / scenario.controller.period) + 1
        units, repeats = ticks * STEP_REPLAYS, STEP_REPLAYS
    return (count(tree, what, repeats) - count(tree, what, 0)) / units


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Count the instructions of one control step and one fuzzy inference "
        "with callgrind (this tree, and --before REV's beside it)."
    )
    parser.add_argument("--before", metavar="REV", help="also count git revision REV's code")
    parser.add_argument("--child", nargs=2, metavar=("WHAT", "REPEATS"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        child(args.child[0], int(args.child[1]))
        return 0
    if shutil.which("valgrind") is None:
        parser.error("valgrind is not installed (apt-get install valgrind)")
    works = (
        ("inference", "FuzzyInference.weights"),
        ("fuzzy", "ControlLaw.step, fuzzy"),
        ("conventional", "ControlLaw.step, conventional"),
    )
    with tempfile.TemporaryDirectory() as scratch:
        trees = {"this tree": ROOT}
        if args.before:
            trees = {args.before: tree_at(args.before, Path(scratch)), **trees}
        print("| instructions per call | " + " | ".join(trees) + " |")
        print("|---|" + "---:|" * len(trees))
        for what, label in works:
            counts = []
            for name, tree in trees.items():
                print(f"counting {label} on {name}", file=sys.stderr, flush=True)
                counts.append(per_unit(tree, what))
            cells = [f"{value:,.0f}" for value in counts]
            if len(counts) == 2:
                cells[1] += f" ({counts[1] / counts[0]:.2f}x)"
            print(f"| {label} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
