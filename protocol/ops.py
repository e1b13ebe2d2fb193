"""The operations the control law and the plant model are written over, once, for two kinds of
value: plain floats, one arm (the controller's tick), and numpy arrays, one element per run
(the batch study's thousands of runs at once).

A formula takes an ``ops`` first and uses ``+ - * / % abs`` and comparisons, which both kinds
of value have, and ``ops`` for everything else (:class:`Ops`): :data:`SCALAR`
(:mod:`protocol.scalar_ops`) is :mod:`math` and ``if``; :data:`ARRAY`
(:mod:`protocol.array_ops`) is numpy, ``np.where`` and row subsets. Numpy's per-call overhead
(microseconds) would dominate a tick of one arm, and a Python loop over the runs would be a
thousand times slower than numpy, hence two sets rather than numpy with one element.

Both give the same bits: ``+ - * / sqrt sin cos %`` are correctly rounded or libm's on both
sides; numpy's own ``arctan2``, ``arccos`` and ``exp`` are libm's on these machines and one
ulp off them on a CPU with AVX-512 (``tests/protocol/test_ops.py`` checks); ``tanh`` is libm's
on both; ``min``/``max`` break ties as Python does (the first argument), which shows only with
signed zeros. A formula must not compute a value it does not use where that would raise on
floats (a division by zero, ``acos`` beyond 1): guard the operand, or use ``branch``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, TypeAlias, TypeVar

from protocol import array_ops, scalar_ops

Real: TypeAlias = Any
"""A float (:data:`SCALAR`) or an array of float64, one element per run (:data:`ARRAY`).
Written ``Any``: mypy cannot follow one formula over both kinds without a type parameter on
every value."""
Mask: TypeAlias = Any
"""A bool (:data:`SCALAR`) or an array of bool, one element per run (:data:`ARRAY`)."""
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
    def clip(self, x: Real, low: Real, high: Real, /) -> Real:
        """``min(max(x, low), high)``, as those two would give it, ties and all."""
        ...

    def where(self, condition: Mask, if_true: Any, if_false: Any, /) -> Any: ...
    def not_(self, condition: Mask, /) -> Mask: ...
    def any(self, condition: Mask, /) -> bool: ...
    def full(self, like: Any, value: Any, /) -> Any: ...
    def branch(
        self, condition: Mask, compute: Callable[..., Result], otherwise: Result, /, *arguments: Any
    ) -> Result:
        """``compute(*arguments)`` where ``condition`` holds, ``otherwise`` elsewhere; on
        arrays, computed only for the runs that take it."""
        ...

    def converge(
        self,
        step: Callable[..., tuple[Any, ...]],
        state: tuple[Any, ...],
        most: int,
        /,
        *constants: Any,
    ) -> Any:
        """``state = step(*state, *constants)`` for each run until its first element (still
        going) is false, at most ``most`` times."""
        ...


SCALAR: Ops = scalar_ops
ARRAY: Ops = array_ops
