"""One point of a frequency response: the experiment's result and the design's input."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Point:
    """One point of the process frequency response: ``value`` = ``F(j·omega)``, ``omega`` in rad/s."""

    omega: float
    value: complex

    @property
    def gain(self) -> float:
        """``|F(jω)|`` (PV units per MV unit)."""
        return abs(self.value)

    @property
    def phase_deg(self) -> float:
        """``arg F(jω)`` in degrees, negative for lag, in (−360, 0]."""
        lag = math.degrees(-math.atan2(self.value.imag, self.value.real)) % 360.0
        return -lag
