"""Argument checks shared by the controller, the data loaders and the adapters.

Each names the argument and the value it got, so a bad input fails with a message that says what
to fix. ``bool`` is refused where a number is expected (``True`` is an ``int`` to Python, never
a count or a rate to us)."""

from __future__ import annotations

import math
from typing import Optional

__all__ = ["check_int", "check_float", "is_int"]


def is_int(value) -> bool:
    """True for a Python int that is not a bool."""
    return isinstance(value, int) and not isinstance(value, bool)


def check_int(name: str, value, lo: int, hi: Optional[int] = None) -> int:
    """``value`` as an int in ``lo..hi`` (``hi`` None: no upper bound), else ValueError."""
    if not is_int(value) or value < lo or (hi is not None and value > hi):
        what = f"an int in {lo}..{hi}" if hi is not None else "a positive int" if lo == 1 else f"an int >= {lo}"
        raise ValueError(f"{name} must be {what}, got {value!r}")
    return value


def check_float(name: str, value, positive: bool = False) -> float:
    """``value`` as a finite float >= 0 (> 0 with ``positive``), else ValueError."""
    if isinstance(value, bool):
        raise ValueError(f"{name} must be a number, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v < 0 or (positive and v == 0):
        raise ValueError(f"{name} must be a finite number {'> 0' if positive else '>= 0'}, got {value!r}")
    return v
