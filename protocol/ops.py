"""The operations the control law and the plant model are written over, once, for two kinds of
value: plain floats, one arm (the controller's tick), and numpy arrays, one element per run
(the batch study's thousands of runs at once).

A formula takes an ``ops`` first and uses ``+ - * / % abs`` and comparisons, which both kinds
of value have, and ``ops`` for everything else: :data:`SCALAR` is :mod:`math`, ``min``/``max``
and ``if``; :data:`ARRAY` is numpy, ``np.where`` and row subsets. Numpy's per-call overhead
(microseconds) would dominate a tick of one arm, and a Python loop over the runs would be a
thousand times slower than numpy, hence two sets rather than numpy with one element.

Both give the same bits: ``+ - * / sqrt sin cos %`` are correctly rounded or libm's on both
sides; numpy's own ``arctan2``, ``arccos`` and ``exp`` are libm's on these machines and one
ulp off them on a CPU with AVX-512 (``tests/sim/test_batch.py`` checks); ``tanh`` is libm's
on both; ``min``/``max`` break ties as Python does (the first argument), which shows only with
signed zeros. A formula must not compute a value it does not use where that would raise on
floats (a division by zero, ``acos`` beyond 1): guard the operand, or use :meth:`branch`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any, Protocol, TypeAlias, TypeVar, cast

import numpy as np
import numpy.typing as npt

Real: TypeAlias = Any
"""A float (:data:`SCALAR`) or an array of float64, one element per run (:data:`ARRAY`).
Written ``Any``: mypy cannot follow one formula over both kinds without a type parameter on
every value."""
Mask: TypeAlias = Any
"""A bool (:data:`SCALAR`) or an array of bool, one element per run (:data:`ARRAY`)."""
FloatArray = npt.NDArray[np.float64]
Result = TypeVar("Result")


class Ops(Protocol):
    """What a formula may call besides arithmetic and comparisons."""

    def sqrt(self, x: Real, /) -> Real: ...
    def sin(self, x: Real, /) -> Real: ...
    def cos(self, x: Real, /) -> Real: ...
    def atan2(self, y: Real, x: Real, /) -> Real: ...
    def acos(self, x: Real, /) -> Real: ...
    def exp(self, x: Real, /) -> Real: ...
    def tanh(self, x: Real, /) -> Real: ...
    def copysign(self, x: Real, sign: Real, /) -> Real: ...
    def rint(self, x: Real, /) -> Real: ...
    def min(self, a: Real, b: Real, /) -> Real: ...
    def max(self, a: Real, b: Real, /) -> Real: ...
    def where(self, condition: Mask, if_true: Any, if_false: Any, /) -> Any: ...
    def not_(self, condition: Mask, /) -> Mask: ...
    def any(self, condition: Mask, /) -> bool: ...
    def full(self, like: Any, value: Any, /) -> Any: ...
    def branch(
        self, condition: Mask, compute: Callable[..., Result], otherwise: Result, /, *per_run: Any
    ) -> Result: ...
    def converge(
        self, step: Callable[..., tuple[Any, ...]], state: tuple[Any, ...], most: int, /
    ) -> Any: ...


class ScalarOps:
    """The operations on plain floats: :mod:`math`, Python's ``min``/``max`` and ``if``."""

    sqrt = staticmethod(math.sqrt)
    sin = staticmethod(math.sin)
    cos = staticmethod(math.cos)
    atan2 = staticmethod(math.atan2)
    acos = staticmethod(math.acos)
    exp = staticmethod(math.exp)
    tanh = staticmethod(math.tanh)
    copysign = staticmethod(math.copysign)
    rint = staticmethod(round)
    min = staticmethod(min)
    max = staticmethod(max)

    @staticmethod
    def where(condition: bool, if_true: Any, if_false: Any) -> Any:
        return if_true if condition else if_false

    @staticmethod
    def not_(condition: bool) -> bool:
        return not condition

    @staticmethod
    def any(condition: bool) -> bool:
        return condition

    @staticmethod
    def full(like: Any, value: Any) -> Any:
        """``value`` for each run of ``like``."""
        return value

    @staticmethod
    def branch(condition: bool, compute: Callable[..., Any], otherwise: Any, *per_run: Any) -> Any:
        """``compute(*per_run)`` where ``condition`` holds, else ``otherwise``."""
        return compute(*per_run) if condition else otherwise

    @staticmethod
    def converge(step: Callable[..., tuple[Any, ...]], state: tuple[Any, ...], most: int) -> Any:
        """``state = step(*state)`` until its first element (still going) is false, at most
        ``most`` times; the last state."""
        for _ in range(most):
            state = step(*state)
            if not state[0]:
                break
        return state


class ArrayOps:
    """The operations on arrays of runs: numpy, ``np.where`` and row subsets."""

    sqrt = staticmethod(np.sqrt)
    sin = staticmethod(np.sin)
    cos = staticmethod(np.cos)
    atan2 = staticmethod(np.arctan2)
    acos = staticmethod(np.arccos)
    exp = staticmethod(np.exp)
    copysign = staticmethod(np.copysign)
    rint = staticmethod(np.rint)
    where = staticmethod(np.where)

    @staticmethod
    def tanh(x: FloatArray) -> FloatArray:
        """``math.tanh`` of each element: numpy's differs from libm's in the last bit."""
        return np.fromiter(map(math.tanh, x.tolist()), np.float64, len(x))

    @staticmethod
    def min(a: Real, b: Real) -> Real:
        """Python's ``min(a, b)``: ``a`` on a tie."""
        return np.minimum(b, a)

    @staticmethod
    def max(a: Real, b: Real) -> Real:
        """Python's ``max(a, b)``: ``a`` on a tie."""
        return np.maximum(b, a)

    @staticmethod
    def not_(condition: Mask) -> Mask:
        return ~condition

    @staticmethod
    def any(condition: Mask) -> bool:
        return bool(np.any(condition))

    @staticmethod
    def full(like: Real, value: Any) -> Any:
        """``value`` for each run of ``like``."""
        return np.full(np.shape(like), value)

    @staticmethod
    def branch(condition: Mask, compute: Callable[..., Any], otherwise: Any, *per_run: Any) -> Any:
        """``compute`` of the runs where ``condition`` holds, ``otherwise`` for the others:
        ``compute`` sees only those runs' elements of ``per_run`` (arrays, indexed on their
        last axis, or tuples of them), so a rare case costs only the runs that take it."""
        rows = np.flatnonzero(condition)
        count = np.size(condition)
        if len(rows) == count:
            return compute(*per_run)
        if not len(rows):
            return _filled(otherwise, count)
        part = compute(*(take(value, rows) for value in per_run))
        return _scattered(part, otherwise, rows, count)

    @staticmethod
    def converge(step: Callable[..., tuple[Any, ...]], state: tuple[Any, ...], most: int) -> Any:
        """``state = step(*state)`` for every run until its first element (still going) is
        false, at most ``most`` times; once at most half the runs are still going, only those
        are stepped on."""
        result = [np.array(value, copy=True) for value in state]
        active = np.arange(np.size(state[0]))
        for _ in range(most):
            state = step(*state)
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


def take(value: Any, rows: npt.NDArray[np.intp]) -> Any:
    """``value``'s elements of the runs ``rows``: arrays on their last axis, tuples element by
    element, anything else (a float, a configuration) as it is."""
    if isinstance(value, np.ndarray):
        return value[..., rows]
    if isinstance(value, tuple):
        parts = [take(part, rows) for part in value]
        return rebuilt(value, parts)
    return value


def _filled(value: Any, count: int) -> Any:
    """``value`` (a float, a bool, or tuples of them) as arrays of ``count`` runs."""
    if isinstance(value, tuple):
        return rebuilt(value, [_filled(part, count) for part in value])
    return np.full(count, value)


def _scattered(part: Any, otherwise: Any, rows: npt.NDArray[np.intp], count: int) -> Any:
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


SCALAR: Ops = ScalarOps()
ARRAY: Ops = ArrayOps()
