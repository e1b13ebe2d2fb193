"""The bridge's rate limit, on a clock the test drives."""

from __future__ import annotations

import pytest

from bridge.rate import RateLimit, StartOfMotion


def test_samples_faster_than_the_rate_go_out_at_the_rate_on_its_grid() -> None:
    limit: RateLimit[int] = RateLimit(128.0)  # a turn every 8 samples (times exact in binary)
    sent = []
    for tick in range(1024):  # 1 s of samples at 1024 Hz
        now = tick / 1024
        for sample in (limit.offer(now, tick), limit.due(now)):
            if sample is not None:
                sent.append(sample)
    assert sent == list(range(0, 1024, 8))  # 128 of them, each the newest at its turn


def test_the_last_sample_before_a_pause_goes_out_when_its_turn_comes() -> None:
    """What a monitor showed a step short of the end when it was dropped (CI)."""
    limit: RateLimit[str] = RateLimit(100.0)
    assert limit.offer(0.000, "second to last") == "second to last"
    assert limit.offer(0.005, "last") is None  # before its turn: it waits
    assert limit.due(0.009) is None
    assert limit.due(0.010) == "last"
    assert limit.due(0.030) is None  # once


def test_a_waiting_sample_is_replaced_by_a_newer_one() -> None:
    limit: RateLimit[int] = RateLimit(10.0)
    assert limit.offer(0.0, 1) == 1
    assert limit.offer(0.02, 2) is None
    assert limit.offer(0.05, 3) is None
    assert limit.due(0.1) == 3
    assert limit.due(0.2) is None


def test_after_a_pause_the_next_sample_goes_at_once_and_the_grid_restarts() -> None:
    limit: RateLimit[int] = RateLimit(100.0)
    assert limit.offer(0.0, 1) == 1
    assert limit.offer(1.0, 2) == 2
    assert limit.offer(1.005, 3) is None
    assert limit.due(1.0099) is None
    assert limit.due(1.010) == 3


def test_news_goes_out_at_once_and_the_grid_restarts_from_it() -> None:
    """The arm's first move, held up to a period on the grid before (a run pressed in a page
    waited for it)."""
    limit: RateLimit[str] = RateLimit(100.0)
    assert limit.offer(0.000, "at rest") == "at rest"
    assert limit.offer(0.004, "still at rest") is None  # waits for its turn at 0.010
    assert limit.offer(0.006, "moved", news=True) == "moved"  # not at 0.010
    assert limit.due(0.010) is None  # what waited is older than what went
    assert limit.offer(0.012, "on the way") is None  # the grid: from 0.006 on
    assert limit.due(0.0159) is None
    assert limit.due(0.016) == "on the way"


def test_the_first_move_after_standing_still_is_news_once() -> None:
    start = StartOfMotion(still=0.1)
    assert not start.moved(0.0, [0.0, 0.0])  # the first position heard: nothing to compare
    for tick in range(1, 60):  # 0.118 s standing still
        assert not start.moved(tick * 0.002, [0.0, 0.0])
    assert start.moved(0.120, [0.001, 0.0])
    assert not start.moved(0.122, [0.002, 0.0])  # moving on: no news


def test_a_pause_shorter_than_still_is_no_news() -> None:
    """A position that jitters, or an arm that turns back, would make every sample news."""
    start = StartOfMotion(still=0.1)
    start.moved(0.0, [0.0])
    start.moved(0.002, [0.1])
    for now in (0.004, 0.05, 0.099):
        assert not start.moved(now, [0.1])  # still since 0.004: not 0.1 s yet at 0.101
    assert not start.moved(0.101, [0.2])
    assert not start.moved(0.103, [0.3])


@pytest.mark.parametrize("rate", [0.0, -1.0, float("nan")])
def test_a_rate_that_is_not_positive_is_refused(rate: float) -> None:
    with pytest.raises(ValueError, match="rate must be > 0 Hz"):
        RateLimit(rate)
