"""The operations of :mod:`protocol.ops` on numpy arrays, one element per run: numpy,
``np.where`` and row subsets."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any, cast

import numpy as np
import numpy.typing as npt
from numpy import arccos as acos
from numpy import arctan2 as atan2
from numpy import copysign, cos, exp, rint, sin, sqrt, where

FloatArray = npt.NDArray[np.float64]
Rows = npt.NDArray[np.intp]

__all__ = [
    "acos",
    "any",
    "atan2",
    "branch",
    "clip",
    "converge",
    "copysign",
    "cos",
    "exp",
    "full",
    "max",
    "min",
    "not_",
    "rebuilt",
    "rint",
    "sin",
    "sqrt",
    "take",
    "tanh",
    "where",
]


def tanh(x: FloatArray) -> FloatArray:
    """``math.tanh`` of each element: numpy's differs from libm's in the last bit."""
    return np.fromiter(map(math.tanh, x.tolist()), np.float64, len(x))


def min(a: Any, b: Any) -> Any:
    """Python's ``min(a, b)`` elementwise: ``a`` on a tie (which shows with signed zeros)."""
    return np.minimum(b, a)


def max(a: Any, b: Any) -> Any:
    """Python's ``max(a, b)`` elementwise: ``a`` on a tie."""
    return np.maximum(b, a)


def clip(x: Any, low: Any, high: Any) -> Any:
    """``min(max(x, low), high)`` elementwise, ties as those give them."""
    return np.minimum(high, np.maximum(low, x))


def not_(condition: Any) -> Any:
    return ~condition


def any(condition: Any) -> bool:
    return bool(np.any(condition))


def full(like: Any, value: Any) -> Any:
    """``value`` for each run of ``like``."""
    return np.full(np.shape(like), value)


def branch(condition: Any, compute: Callable[..., Any], otherwise: Any, *arguments: Any) -> Any:
    """``compute(*arguments)`` of the runs where ``condition`` holds, ``otherwise`` for the
    others: ``compute`` sees only those runs' elements of the arguments that are arrays
    (indexed on their last axis) or tuples of them, and the others (``ops``, a
    configuration, a float) as they are, so a rare case costs only the runs that take it."""
    rows = np.flatnonzero(condition)
    count = np.size(condition)
    if len(rows) == count:
        return compute(*arguments)
    if not len(rows):
        return _filled(otherwise, count)
    part = compute(*(take(value, rows) for value in arguments))
    return _scattered(part, otherwise, rows, count)


def converge(
    step: Callable[..., tuple[Any, ...]], state: tuple[Any, ...], most: int, *constants: Any
) -> Any:
    """``state = step(*state, *constants)`` for every run until its first element (still
    going) is false, at most ``most`` times; once at most half the runs are still going, only
    those are stepped on (``constants`` are not per run)."""
    result = [np.array(value, copy=True) for value in state]
    active = np.arange(np.size(state[0]))
    for _ in range(most):
        state = step(*state, *constants)
        going = state[0]
        count = np.count_nonzero(going)
        if count == 0:
            break
        if count <= len(going) // 2:
            for whole, part in zip(result, state, strict=True):
                whole[active] = part
            active = active[going]
            state = tuple(value[going] for value in state)
    for whole, part in zip(result, state, strict=True):
        whole[active] = part
    return tuple(result)


def rebuilt(like: tuple[Any, ...], parts: Iterable[Any]) -> Any:
    """A tuple of ``parts`` of the same kind as ``like`` (a named tuple, or a plain one)."""
    return cast(Any, like)._make(parts) if hasattr(like, "_fields") else tuple(parts)


def take(value: Any, rows: Rows) -> Any:
    """``value``'s elements of the runs ``rows``: arrays on their last axis, tuples element by
    element, anything else (a float, a configuration) as it is."""
    if isinstance(value, np.ndarray):
        return value[..., rows]
    if isinstance(value, tuple):
        return rebuilt(value, [take(part, rows) for part in value])
    return value


def _filled(value: Any, count: int) -> Any:
    """``value`` (a float, a bool, an array of runs, or tuples of them) for ``count`` runs."""
    if isinstance(value, tuple):
        return rebuilt(value, [_filled(part, count) for part in value])
    return np.full(count, value)


def _scattered(part: Any, otherwise: Any, rows: Rows, count: int) -> Any:
    """Arrays of ``count`` runs holding ``part`` at ``rows`` and ``otherwise`` elsewhere."""
    if isinstance(part, tuple):
        parts = [
            _scattered(piece, other, rows, count)
            for piece, other in zip(part, otherwise, strict=True)
        ]
        return rebuilt(part, parts)
    whole = np.full(count, otherwise, dtype=np.asarray(part).dtype)
    whole[rows] = part
    return whole
