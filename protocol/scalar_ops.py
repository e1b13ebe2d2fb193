"""The operations of :mod:`protocol.ops` on plain floats: :mod:`math` and ``if``.

A module rather than a class: its functions are found as a module's attributes, the quickest
lookup Python has, and a control tick makes a few hundred such calls.
"""

from __future__ import annotations

from collections.abc import Callable
from math import acos, atan2, copysign, cos, exp, sin, sqrt, tanh
from typing import Any, TypeVar

Result = TypeVar("Result")

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
    "rint",
    "sin",
    "sqrt",
    "tanh",
    "where",
]

rint = round


def min(a: float, b: float) -> float:
    """Python's ``min(a, b)`` (``a`` on a tie), at half the builtin's cost for two values."""
    return b if b < a else a


def max(a: float, b: float) -> float:
    """Python's ``max(a, b)`` (``a`` on a tie), at half the builtin's cost for two values."""
    return b if b > a else a


def clip(x: float, low: float, high: float) -> float:
    """``min(max(x, low), high)`` in one call: smoothsteps and joint boxes make a few dozen a
    tick."""
    if low > x:
        x = low
    return high if high < x else x


def where(condition: bool, if_true: Any, if_false: Any) -> Any:
    return if_true if condition else if_false


def not_(condition: bool) -> bool:
    return not condition


def any(condition: bool) -> bool:
    return condition


def full(like: Any, value: Any) -> Any:
    """``value`` for each run of ``like``: one."""
    return value


def branch(
    condition: bool, compute: Callable[..., Result], otherwise: Result, *arguments: Any
) -> Result:
    """``compute(*arguments)`` where ``condition`` holds, else ``otherwise``."""
    return compute(*arguments) if condition else otherwise


def converge(
    step: Callable[..., tuple[Any, ...]], state: tuple[Any, ...], most: int, *constants: Any
) -> Any:
    """``state = step(*state, *constants)`` until its first element (still going) is false,
    at most ``most`` times; the last state."""
    for _ in range(most):
        state = step(*state, *constants)
        if not state[0]:
            break
    return state
