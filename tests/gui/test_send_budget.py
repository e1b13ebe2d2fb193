"""The pace of a page's updates (``gui.server.SendBudget``): at once after a pause, at the
rate over a run."""

from __future__ import annotations

from itertools import pairwise

import pytest

from gui.server import SendBudget

RATE = 40.0
PERIOD = 1.0 / RATE


def test_after_a_pause_a_burst_goes_at_once_then_one_a_period() -> None:
    budget = SendBudget(RATE, burst=2, now=0.0)
    for _ in range(2):  # say the status changed, then the arm first moved
        assert budget.wait(10.0) == 0.0
        budget.spend(10.0)
    assert budget.wait(10.0) == pytest.approx(PERIOD)
    assert budget.wait(10.0 + PERIOD / 2) == pytest.approx(PERIOD / 2)
    assert budget.wait(10.0 + PERIOD) == 0.0


def test_over_a_run_no_more_than_the_rate_and_the_burst() -> None:
    """Updates offered every 10 ms for 5 s, sent whenever the budget allows."""
    budget = SendBudget(RATE, burst=2, now=0.0)
    sent = []
    for tick in range(500):
        now = tick * 0.01
        if budget.wait(now) == 0.0:
            budget.spend(now)
            sent.append(now)
    assert len(sent) <= 5.0 * RATE + 2
    assert len(sent) >= 5.0 * RATE - 1  # the rate is kept, not only bounded
    gaps = [later - earlier for earlier, later in pairwise(sent[2:])]
    assert min(gaps) >= PERIOD - 0.01 - 1e-9  # once the burst is spent: a period apart


def test_a_budget_saved_up_is_never_more_than_the_burst() -> None:
    budget = SendBudget(RATE, burst=2, now=0.0)
    sent = 0
    while budget.wait(3600.0) == 0.0:
        budget.spend(3600.0)
        sent += 1
    assert sent == 2
