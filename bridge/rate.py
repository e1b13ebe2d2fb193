"""At most so many samples a second of a key, and never the latest one held back for good.

A plain limiter that drops what comes before its turn loses the last state before the arm
stops (or before a recording ends) whenever that state came within a period of the one
before: monitors would show the arm a step short of where it is, for ever. Here a sample
that comes early waits (a newer one replaces it) and goes out when its turn comes.

The other way round, the first state of an arm that starts to move is news a user waits for
(a run pressed in a page, to the arm's first move there): it goes out at once, not up to a
period later on the grid (:class:`StartOfMotion` tells it).
"""

from __future__ import annotations

from typing import Generic, TypeVar

Sample = TypeVar("Sample")


class RateLimit(Generic[Sample]):
    """The samples of one key to send, at most ``rate`` a second; the clock is the caller's."""

    def __init__(self, rate: float) -> None:
        if not rate > 0:
            raise ValueError(f"rate must be > 0 Hz, not {rate}")
        self.period = 1.0 / rate
        self._due = -float("inf")
        self._waiting: Sample | None = None

    def offer(self, now: float, sample: Sample, news: bool = False) -> Sample | None:
        """``sample`` if it may go now, or at once if it is ``news`` (the grid starts again
        from it); else ``None``, and it waits for :meth:`due`."""
        if now < self._due and not news:
            self._waiting = sample
            return None
        if news:
            self._due = -float("inf")
        self._waiting = None
        self._advance(now)
        return sample

    def due(self, now: float) -> Sample | None:
        """The waiting sample once its turn has come (once), else ``None``."""
        if self._waiting is None or now < self._due:
            return None
        sample, self._waiting = self._waiting, None
        self._advance(now)
        return sample

    def _advance(self, now: float) -> None:
        # on a grid of the period, so the mean rate is the rate even when the samples come
        # at a rate that is not a multiple of it; after a pause the grid starts again at now
        late = now - self._due >= self.period
        self._due = now + self.period if late else self._due + self.period


class StartOfMotion:
    """Tells the first position that differs after the arm stood still for at least
    ``still`` s: the news of :meth:`RateLimit.offer`. Standing still that long first keeps
    a position that jitters from making every sample news."""

    def __init__(self, still: float) -> None:
        self.still = still
        self._position: object = None
        self._still_since = float("inf")

    def moved(self, now: float, position: object) -> bool:
        """Whether ``position``, at ``now``, is the arm's first move after standing still."""
        if position == self._position:
            self._still_since = min(self._still_since, now)
            return False
        started = now - self._still_since >= self.still
        self._position = position
        self._still_since = float("inf")
        return started
