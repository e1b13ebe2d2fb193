"""A soak's report: the disturbances of each kind and the time back to running after each,
the tasks, the faults raised and cleared, every invariant's violations (each with the seed and
the moment, to reproduce it) and the long-lived processes' health; text and JSON."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from soak.check import INVARIANTS, RECOVERY_BOUND, Verdict
from soak.disturb import Done
from soak.drive import Tally
from soak.health import Growth
from soak.schedule import Kind

MEMORY_BOUND = 10 * 2**20
"""bytes a long-lived process's resident memory may grow by within one start."""
FILES_BOUND = 4
"""open file handles a long-lived process may gain within one start (a reconnect's socket
may outlive the one it replaced for a while)."""
OBSERVED = 120.0
"""s past its warm-up a start must have been watched for its growth to be judged."""


def percentile(values: Sequence[float], share: float) -> float:
    """The nearest-rank percentile (``share`` in [0, 1]) of ``values`` (not empty)."""
    ordered = sorted(values)
    return ordered[max(0, math.ceil(share * len(ordered)) - 1)]


@dataclass
class Report:
    seed: int
    minutes: float
    wall: float
    """s the soak ran, start-up and shutdown included."""
    started_epoch: float
    """s since the epoch when the schedule's clock started (its moment 0)."""
    done: list[Done]
    back: list[float | None]
    """s from each disturbance's end until the system was up again (None: never)."""
    tally: Tally
    raised: dict[str, int]
    cleared: dict[str, int]
    verdict: Verdict
    growths: list[Growth]
    ended: list[str] = field(default_factory=list)
    """Processes that ended by themselves (a crash)."""
    interrupted: bool = False

    def reproduce(self) -> str:
        return f"scara-soak --minutes {self.minutes:g} --seed {self.seed}"

    def unrecovered(self) -> list[tuple[Done, float | None]]:
        return [
            (done, back)
            for done, back in zip(self.done, self.back, strict=True)
            if back is None or back > RECOVERY_BOUND
        ]

    def read_only_answered(self) -> list[str]:
        """Replies the read-only user got to its commands: the access control let one
        through."""
        return [
            reply
            for done in self.done
            if done.disturbance.kind is Kind.READ_ONLY
            for reply in done.replies
            if not reply.endswith(":no_reply")
        ]

    def too_much_growth(self) -> list[Growth]:
        return [
            g
            for g in self.growths
            if g.seconds >= OBSERVED and (g.rss_growth > MEMORY_BOUND or g.fds_growth > FILES_BOUND)
        ]

    @property
    def passed(self) -> bool:
        return self.tally.completed > 0 and not (
            self.verdict.violations
            or self.unrecovered()
            or self.ended
            or self.too_much_growth()
            or self.read_only_answered()
            or self.interrupted
        )

    def by_kind(self) -> dict[str, list[float | None]]:
        kinds: dict[str, list[float | None]] = {}
        for done, back in zip(self.done, self.back, strict=True):
            kinds.setdefault(done.disturbance.kind.value, []).append(back)
        return kinds

    def as_json(self) -> dict[str, Any]:
        return {
            "seed": self.seed,
            "minutes": self.minutes,
            "wall_s": round(self.wall, 1),
            "passed": self.passed,
            "interrupted": self.interrupted,
            "disturbances": [
                {
                    "at": round(done.disturbance.at, 3),
                    "what": done.disturbance.describe(),
                    "lasted_s": round(done.ended - done.began, 3) if done.ended else None,
                    "back_s": None if back is None else round(back, 3),
                    "replies": done.replies,
                    "error": done.error,
                }
                for done, back in zip(self.done, self.back, strict=True)
            ],
            "tasks": asdict(self.tally),
            "faults_raised": self.raised,
            "faults_cleared": self.cleared,
            "invariants": self.verdict.counts(),
            "violations": [
                {
                    "invariant": v.invariant,
                    "moment_s": round(v.t - self.started_epoch, 3),
                    "recording": v.recording,
                    "detail": v.detail,
                }
                for v in self.verdict.violations
            ],
            "checked": {
                "recordings": self.verdict.recordings,
                "frames": self.verdict.frames,
                "joint_states": self.verdict.states,
                "commands": self.verdict.commands,
                "states_unjudged": self.verdict.unjudged_states,
            },
            "health": [asdict(g) | {"rss_growth": g.rss_growth} for g in self.growths],
            "read_only_answered": self.read_only_answered(),
            "ended_by_themselves": self.ended,
        }


def _seconds(values: Sequence[float]) -> str:
    if not values:
        return "-"
    return " / ".join(f"{percentile(values, q):.2f}" for q in (0.5, 0.99, 1.0))


def format_report(report: Report) -> str:
    """The report as text."""
    lines = [
        f"scara-soak: seed {report.seed}, {report.minutes:g} min"
        f" ({report.wall:.0f} s wall{', interrupted' if report.interrupted else ''})",
        "",
        f"disturbances: {len(report.done)}; time back to ready or running after each, "
        "s p50 / p99 / max:",
    ]
    for kind, backs in sorted(report.by_kind().items()):
        known = [b for b in backs if b is not None]
        lines.append(f"  {kind:<16} {len(backs):>4}   {_seconds(known)}")
    everything = [b for b in report.back if b is not None]
    lines.append(f"  {'all':<16} {len(report.back):>4}   {_seconds(everything)}")
    for done, back in report.unrecovered():
        moment = done.disturbance.at
        when = "never" if back is None else f"after {back:.1f} s"
        lines.append(f"  NOT RECOVERED: {done.disturbance.describe()} at {moment:.1f} s: {when}")
    errors = [done for done in report.done if done.error]
    for done in errors:
        lines.append(f"  (could not do {done.disturbance.describe()}: {done.error})")
    tally = report.tally
    lines += [
        "",
        f"tasks: {tally.completed} completed, {tally.started} runs started, "
        f"{tally.ended_otherwise} ended otherwise than done, {tally.skipped} skipped, "
        f"{tally.resets} resets sent",
    ]
    if tally.refusals:
        refusals = ", ".join(f"{k} {v}" for k, v in sorted(tally.refusals.items()))
        lines.append(f"  refused or unanswered: {refusals}")
    raised = ", ".join(f"{k} {v}" for k, v in sorted(report.raised.items())) or "none"
    cleared = ", ".join(f"{k} {v}" for k, v in sorted(report.cleared.items())) or "none"
    lines += [f"faults raised: {raised}", f"faults cleared: {cleared}", ""]
    verdict = report.verdict
    lines.append(
        f"invariants, from {verdict.recordings} recordings ({verdict.frames} frames, "
        f"{verdict.states} joint states, {verdict.commands} commands; "
        f"{verdict.unjudged_states} states of an unrecorded world not judged):"
    )
    counts = verdict.counts()
    lines += [f"  {name:<16} {counts[name]} violations" for name in INVARIANTS]
    for v in verdict.violations:
        lines.append(
            f"  VIOLATION {v.invariant} at {v.t - report.started_epoch:.3f} s ({v.recording}): "
            f"{v.detail}; reproduce: {report.reproduce()}"
        )
    lines += ["", "health (each start watched past its warm-up, longest first):"]
    shown: set[str] = set()
    for g in report.growths:
        if g.process in shown:
            continue
        shown.add(g.process)
        lines.append(
            f"  {g.process:<12} start {g.start}: {g.seconds:.0f} s, RSS "
            f"{g.rss_first / 2**20:.1f} -> max {g.rss_max / 2**20:.1f} MB "
            f"(+{g.rss_growth / 2**20:.1f}), files {g.fds_first} -> max {g.fds_max}"
        )
    for g in report.too_much_growth():
        lines.append(f"  GROWS: {g.process} start {g.start}")
    for reply in report.read_only_answered():
        lines.append(f"READ-ONLY USER ANSWERED: {reply}")
    if report.ended:
        lines.append(f"ended by themselves: {', '.join(report.ended)}")
    lines += ["", "PASSED" if report.passed else f"FAILED; reproduce: {report.reproduce()}"]
    return "\n".join(lines)
