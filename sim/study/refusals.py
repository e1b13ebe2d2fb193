"""The tasks the controller refuses for want of a way round the obstacle: counted, and a
sample of them searched by brute force (:mod:`sim.passability`) for a way the check missed."""

from __future__ import annotations

import random
import re
from collections import Counter
from collections.abc import Sequence

from protocol.errors import NoWayRoundError
from protocol.scenario import Scenario
from sim.passability import Verdict, way_round

DEFAULT_CHECKED = 20
"""Refused tasks searched by brute force by default (a search takes about 0.1 s)."""
_SEGMENT = re.compile(r"waypoints\[(\d+)\.\.")


def refused_segment(error: NoWayRoundError) -> int:
    """The segment a refusal names (``waypoints[i..i+1]``)."""
    found = _SEGMENT.match(error.field)
    if found is None:
        raise ValueError(f"a refusal that names no segment: {error}")
    return int(found.group(1))


def check_refused(
    refused: Sequence[tuple[Scenario, NoWayRoundError]], count: int, seed: int = 0
) -> list[tuple[Scenario, Verdict]]:
    """The brute force's verdict on the refused segment of ``count`` of the ``refused``
    tasks, drawn at random (``seed``)."""
    sample = random.Random(seed).sample(list(refused), min(count, len(refused)))
    return [(scenario, way_round(scenario, refused_segment(error))) for scenario, error in sample]


def refusal_report(
    offered: int, refused: Sequence[tuple[Scenario, NoWayRoundError]], checked: int
) -> str:
    """How many tasks were refused, and what the brute force found on a sample of them; a
    refused task for which it found a way is named (the check was stricter than it must)."""
    lines = [
        f"tasks offered: {offered}, accepted: {offered - len(refused)}, refused (no way round "
        f"the obstacle inside the joint limits): {len(refused)}"
    ]
    if refused and checked > 0:
        verdicts = check_refused(refused, checked)
        counts = Counter(verdict for _, verdict in verdicts)
        lines.append(
            f"refusals searched by brute force: {len(verdicts)}: "
            + ", ".join(f"{counts[verdict]} {verdict.value}" for verdict in Verdict)
        )
        lines += [
            f"  refused though a way exists: {scenario.name}"
            for scenario, verdict in verdicts
            if verdict is Verdict.WAY
        ]
    return "\n".join(lines)
