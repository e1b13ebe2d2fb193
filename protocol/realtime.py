"""How a node process keeps time on a shared, non-real-time Linux machine.

Measured on our 2-core VMs (``docs/timing.md``): a fixed-rate loop that *spins* for the last
part of each period loses the CPU to any other busy process for whole scheduler slices (ms),
while a loop that *sleeps* to its deadline is woken on time. Two things make a sleep precise
without privileges, and :func:`tune_process` asks for both (threads started later, such as the
transport's, inherit them):

- timer slack of 1 ns (``prctl(PR_SET_TIMERSLACK)``): the default 50 us slack makes every
  timed wait, ``time.sleep(0)`` included, wake up to 50 us late;
- a short scheduler slice (``sched_setattr`` with ``sched_runtime``, EEVDF, Linux >= 6.12):
  still normal priority (SCHED_OTHER, nice 0), but the task is picked first when it wakes.

``--realtime-priority N`` switches to SCHED_FIFO instead, where permitted.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import logging
import os
import struct
import sys

_PR_SET_TIMERSLACK = 29
_SYS_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274}
SLICE_NS = 100_000
"""The scheduler slice asked for: 0.1 ms, the shortest the kernel accepts."""

log = logging.getLogger("scara.realtime")


def tune_process(priority: int | None = None, *, plain: bool = False) -> list[str]:
    """Ask for precise wake-ups (see the module docstring); return what was applied.

    ``priority`` (1-99) selects SCHED_FIFO; ``plain`` leaves the scheduling as it is (to
    measure what the tuning brings). Whatever the kernel refuses is logged and skipped.
    """
    applied: list[str] = []
    if priority is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            applied.append(f"SCHED_FIFO {priority}")
        except (AttributeError, OSError, ValueError) as error:
            log.warning("real-time priority %d not applied: %s", priority, error)
    if plain or not sys.platform.startswith("linux"):
        return applied
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(_PR_SET_TIMERSLACK, 1, 0, 0, 0) == 0:
        applied.append("timer slack 1 ns")
    else:
        log.info("timer slack not set: %s", os.strerror(ctypes.get_errno()))
    if priority is None and _set_slice(libc, SLICE_NS):
        applied.append(f"slice {SLICE_NS // 1000} us")
    return applied


def _set_slice(libc: ctypes.CDLL, nanoseconds: int) -> bool:
    """``sched_setattr(0, {SCHED_OTHER, runtime=nanoseconds})``; False where unsupported."""
    number = _SYS_SCHED_SETATTR.get(os.uname().machine)
    if number is None:
        return False
    # struct sched_attr: size, policy, flags, nice, priority, runtime, deadline, period,
    # util_min, util_max (the size the kernel is told is the struct's own).
    layout = struct.Struct("IIQiIQQQII")
    attr = ctypes.create_string_buffer(
        layout.pack(layout.size, 0, 0, 0, 0, nanoseconds, 0, 0, 0, 0)
    )
    if libc.syscall(number, 0, attr, 0) != 0:
        log.info("scheduler slice not set: %s", os.strerror(ctypes.get_errno()))
        return False
    return True


OBSERVER_NICENESS = 5
"""Processes that only watch the bus (the bridge, the recorder) run this much below the
nodes: on a 2-core machine they must not win the controller's core when both wake
(``benchmarks/bench_bridge.py`` measures it)."""


def yield_to_the_nodes() -> None:
    """Lower this process's priority; no precise wake-ups (it is not real time)."""
    with contextlib.suppress(OSError):
        os.nice(OBSERVER_NICENESS)


def settle_memory() -> None:
    """Collect once, then freeze what start-up allocated, so that later garbage collections
    scan only the objects the loop makes (a full collection over every module took
    milliseconds here)."""
    gc.collect()
    gc.freeze()
