"""The CAN-over-Zenoh link between OS processes: any participant may start, die and restart,
in any order, at any time, and every live participant hears every other (each sender's
frames complete and in order) within 1 s of joining."""

from __future__ import annotations

import random
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from support import ROOT, SLOWDOWN, Process, Processes

PEER = ROOT / "tests" / "peer.py"
MEMBERS = 5
ROUNDS = 20
PERIOD = 0.01
"""s between two frames of one member."""
JOIN_GRACE = 1.0 * SLOWDOWN
"""s after a member has joined from which every other live member must hear it."""
KILL_MARGIN = 0.2 * SLOWDOWN
"""s before a kill in which a frame may still have been in flight (lost with its process)."""


@dataclass
class Life:
    """One run of one member: its process, when it started and when it was killed."""

    index: int
    run: int
    process: Process
    log: Path
    killed: float = float("inf")
    joined: float = field(default=float("nan"))


def start(processes: Processes, router: int, index: int, folder: Path, run: int) -> Life:
    log = folder / f"member{index}-{run}.log"
    process = Process(
        f"member{index}-{run}",
        [
            sys.executable, str(PEER), "member", "--port", str(router), "--channel", "link",
            "--index", str(index), "--run", str(run), "--period", str(PERIOD), "--log", str(log),
        ],
        folder / f"member{index}-{run}.out",
    )  # fmt: skip
    processes.started.append(process)
    return Life(index, run, process, log)


Received = dict[tuple[int, int], list[int]]


def read(life: Life) -> tuple[float, list[tuple[float, int]], Received]:
    """(joined, [(time, seq) sent], {(index, run) of a sender: [seq received]}) from its log
    (a line cut off by the kill is skipped). No log: the life was killed before its process
    got going (on a loaded machine start-up can outlast a life): it never joined."""
    joined = float("nan")
    sent: list[tuple[float, int]] = []
    got: Received = {}
    if not life.log.exists():
        return joined, sent, got
    for line in life.log.read_text().splitlines():
        words = line.split()
        if words and words[0] == "joined" and len(words) == 2:
            joined = float(words[1])
        elif words and words[0] == "sent" and len(words) == 3:
            sent.append((float(words[1]), int(words[2])))
        elif words and words[0] == "got" and len(words) == 5:
            got.setdefault((int(words[2]), int(words[3])), []).append(int(words[4]))
    return joined, sent, got


@pytest.mark.slow
@pytest.mark.timeout(180)
def test_five_buses_killed_and_restarted_at_random_lose_no_frame_between_live_members(
    router: int, processes: Processes, tmp_path: Path
) -> None:
    rng = random.Random(20261124)
    lives: list[Life] = []
    runs = [0] * MEMBERS
    order = list(range(MEMBERS))
    rng.shuffle(order)
    live: dict[int, Life] = {}
    for index in order:  # random start order, staggered
        live[index] = start(processes, router, index, tmp_path, runs[index])
        lives.append(live[index])
        time.sleep(rng.uniform(0.0, 0.3) * SLOWDOWN)
    for _ in range(ROUNDS):
        time.sleep(rng.uniform(0.4, 1.2) * SLOWDOWN)  # lives last as long, in ticks
        dead = [i for i in range(MEMBERS) if i not in live]
        if dead and (len(live) <= 2 or rng.random() < 0.5):
            index = rng.choice(dead)
            runs[index] += 1
            live[index] = start(processes, router, index, tmp_path, runs[index])
            lives.append(live[index])
        else:
            index = rng.choice(sorted(live))
            life = live.pop(index)
            life.killed = time.time()
            life.process.popen.send_signal(signal.SIGKILL)
            life.process.popen.wait(10 * SLOWDOWN)
    time.sleep(JOIN_GRACE + 0.5 * SLOWDOWN)
    ended = time.time()
    for life in live.values():
        life.killed = ended
        life.process.popen.send_signal(signal.SIGKILL)
        life.process.popen.wait(10 * SLOWDOWN)

    logs = {id(life): read(life) for life in lives}
    checked = 0
    problems: list[str] = []
    for receiver in lives:
        r_joined, _, r_got = logs[id(receiver)]
        for sender in lives:
            if sender.index == receiver.index:
                continue
            s_joined, s_sent, _ = logs[id(sender)]
            start_at = max(r_joined, s_joined) + JOIN_GRACE
            end_at = min(receiver.killed, sender.killed) - KILL_MARGIN
            due = [seq for sent_at, seq in s_sent if start_at <= sent_at <= end_at]
            if not due:
                continue
            got = r_got.get((sender.index, sender.run), [])
            window = [seq for seq in got if due[0] <= seq <= due[-1]]
            checked += len(due)
            if window != due:
                missing = sorted(set(due) - set(window))
                problems.append(
                    f"member {receiver.index} from member {sender.index}: {len(due)} due, "
                    f"{len(missing)} missing (first {missing[:5]}), in order: "
                    f"{window == sorted(window)}"
                )
            if got != sorted(got):
                problems.append(f"member {receiver.index}: {sender.index} out of order")
    assert checked > 2000, f"only {checked} frames were due: the test did not exercise the link"
    assert not problems, "\n".join(problems)
