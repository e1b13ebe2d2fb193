"""The report of a run (``scara-report``, and ``scara-run`` at its end) says what each clock
mode measured: a lockstep run has no periods, so no loop count, deadline or hold to report."""

from __future__ import annotations

from typing import Any

from controller.loop_stats import LoopStats
from controller.runlog import RunLog
from sim.report import RunReport, format_report

E2E = {"ok": 9808, "lost": 0, "repeated": 0, "stale": 0, "corrupt": 0, "unknown": 0}
PLANT = {"e2e": E2E | {"ok": 6552}, "stats": {"collisions": 0}, "state": "RUNNING"}


def report_of(clock: str, stats: LoopStats) -> str:
    """The report of a run whose controller wrote ``stats`` (the shape of controller.json)."""
    controller: dict[str, Any] = {
        "scenario": "reference", "mode": "fuzzy", "clock": clock, "rate_hz": 500.0,
        "completed": True, "state": "READY", "faults": [], "e2e": E2E,
        "loop": stats.summary(), "realtime_factor": 1.4, "wall_time_s": 4.55,
    }  # fmt: skip
    return format_report(RunReport(controller, PLANT, RunLog(), None))


def test_a_lockstep_run_reports_its_ticks_and_retries_and_no_periods() -> None:
    stats = LoopStats(0.002, ticks=3251, lockstep_retries=1)  # what run_lockstep counts
    text = report_of("lockstep", stats)
    assert "3251 control ticks in lockstep" in text, text
    assert "of 0" not in text and "0 periods" not in text, text
    for meaningless in ("lateness", "deadline misses", "overruns", "holds"):
        assert meaningless not in text, text
    assert text.splitlines()[2].endswith("an answer): 1"), text


def test_a_realtime_run_reports_its_ticks_among_its_periods_and_its_deadlines() -> None:
    stats = LoopStats(0.002, loops=3300, ticks=3251, deadline_misses=10, overruns=9, holds=2)
    stats.lateness.add(34e-6)
    stats.add_answer(831e-6)
    text = report_of("realtime", stats)
    assert "3251 control ticks in 3300 periods; lateness p50 34 us" in text, text
    assert "deadline misses 10 (0.30 %), overruns 9" in text, text
    assert "holds (no fresh joint state for 3 ticks): 2" in text, text
    assert "answer to a command within one tick" in text, text
    assert "retries" not in text, text


def test_what_each_side_received_lines_up() -> None:
    lines = report_of("lockstep", LoopStats(0.002, ticks=3251)).splitlines()
    controller, plant = lines[-2], lines[-1]
    assert controller.startswith("controller received: 9808 ok"), controller
    assert plant.startswith("plant received:") and plant[15:].lstrip().startswith("6552 ok"), plant
    assert plant.index("6552 ok") == controller.index("9808 ok"), (controller, plant)
