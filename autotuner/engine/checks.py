"""Validation of numbers at the boundary of the engine, with errors that name the value."""

from __future__ import annotations

import math
from typing import Any


def _number(name: str, value: Any) -> float:
    # bool is an int subclass; a True gain or input is almost certainly a wiring mistake.
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    return float(value)


def real(name: str, value: Any) -> float:
    """``value`` as a float; ValueError naming ``name`` for a non-number, a bool or NaN (infinities pass)."""
    x = _number(name, value)
    if math.isnan(x):
        raise ValueError(f"{name} must be a number, got {value!r}")
    return x


def finite(name: str, value: Any) -> float:
    """``value`` as a finite float; ValueError naming ``name`` otherwise."""
    if type(value) is float and math.isfinite(value):  # the common case, at once (a PID unit's every sample)
        return value
    x = _number(name, value)
    if not math.isfinite(x):
        raise ValueError(f"{name} must be finite, got {x}")
    return x
