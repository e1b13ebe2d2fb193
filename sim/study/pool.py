"""Where the study's tasks run: a pool of worker processes, or the Dask cluster of a scheduler.

Both map a function over argument tuples and yield the results as they finish. The pool's
workers report the progress of a batch as it goes (:func:`progress_reporter`); a cluster's
progress is counted by finished tasks.
"""

from __future__ import annotations

import multiprocessing
import queue
import signal
from collections.abc import Callable, Iterator, Sequence
from typing import Any

_progress: Any = None
"""The worker's queue to the parent's progress bar (set by :func:`_start_worker`)."""


def _start_worker(progress: Any) -> None:
    global _progress
    _progress = progress


def progress_reporter() -> Callable[[int], None] | None:
    """In a worker of :class:`Processes`, what passes on the steps a batch has done (None
    elsewhere)."""
    if _progress is None:
        return None
    report: Callable[[int], None] = _progress.put
    return report


class Processes:
    """A pool of worker processes; batches report their progress as they go."""

    streams = True

    def __init__(self, workers: int, advance: Callable[[int], None]) -> None:
        context = multiprocessing.get_context("spawn")
        # Children start with Ctrl-C ignored, which they keep (the parent stops them; one
        # still importing would print a traceback). Blocked meanwhile, a Ctrl-C for the parent
        # stays pending (Linux keeps a blocked signal even while it is ignored) until after.
        self._pool: Any = None
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            try:
                self._progress = context.Queue()
                self._pool = context.Pool(
                    workers, initializer=_start_worker, initargs=(self._progress,)
                )
            finally:
                signal.signal(signal.SIGINT, handler)
                signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        except BaseException:
            self.close()
            raise
        self.advance = advance

    def map(self, function: Callable[..., Any], items: Sequence[Any]) -> Iterator[Any]:
        """``function(*item)`` for each item, in the order they finish."""
        pending = self._pool.imap_unordered(_star, [(function, item) for item in items])
        for _ in items:
            while True:
                try:
                    result = pending.next(timeout=0.2)
                except multiprocessing.TimeoutError:
                    continue
                finally:
                    self._drain()
                break
            yield result

    def _drain(self) -> None:
        """Pass on the progress the workers reported."""
        try:
            while True:
                self.advance(self._progress.get_nowait())
        except queue.Empty:
            pass

    def close(self) -> None:
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()


class Cluster:
    """The Dask cluster of a scheduler; progress by finished tasks."""

    streams = False

    def __init__(self, address: str) -> None:
        from distributed import Client  # only with --scheduler

        self._client = Client(address)

    def map(self, function: Callable[..., Any], items: Sequence[Any]) -> Iterator[Any]:
        from distributed import as_completed

        futures = [self._client.submit(function, *item, pure=False) for item in items]
        try:
            for future in as_completed(futures):
                yield future.result()
        finally:
            self._client.cancel(futures)

    def close(self) -> None:
        self._client.close()


def _star(task: tuple[Callable[..., Any], tuple[Any, ...]]) -> Any:
    function, arguments = task
    return function(*arguments)
