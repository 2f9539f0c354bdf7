"""How the loop and its valve are used: utilization, saturation, MV travel and reversals."""

from __future__ import annotations

import numpy as np

SATURATION_BAND = 0.005  # within this share of the MV span of a limit counts as at the limit


def utilization(auto: np.ndarray) -> float:
    """Share of the samples in the normal (automatic) mode, 0–1.

    ``auto``: True where the loop was in automatic.
    """
    return float(np.mean(auto))


def saturation(mv: np.ndarray, auto: np.ndarray, limits: tuple[float, float]) -> float:
    """Share of the automatic samples with the MV at a limit (within 0.5 % of the span), 0–1 (0 when never in
    automatic).

    ``mv``: the MV record; ``auto``: True where the loop was in automatic; ``limits``: the MV's (low, high), MV
    units.
    """
    if not np.any(auto):
        return 0.0
    lo, hi = limits
    near = SATURATION_BAND * (hi - lo)
    at = (mv <= lo + near) | (mv >= hi - near)
    return float(np.mean(at[auto]))


def travel(mv: np.ndarray, hours: float) -> float:
    """The MV's total travel Σ|ΔMV| per hour, MV units/h.

    ``mv``: the MV record; ``hours``: its length, h.
    """
    return float(np.sum(np.abs(np.diff(mv))) / hours)


def reversals(mv: np.ndarray, deadzone: float, hours: float) -> float:
    """The MV's reversals of direction per hour, a reversal counting once the MV has moved back by more than
    ``deadzone`` MV units from its last extreme (so noise below it makes none).

    ``mv``: the MV record; ``hours``: its length, h.
    """
    count, direction = 0, 0  # direction: +1 rising, -1 falling, 0 not yet moved beyond the deadzone
    values = mv.tolist()
    extreme = values[0]
    for x in values[1:]:
        if direction * (x - extreme) > 0.0:
            extreme = x  # further the same way: a new extreme
        elif abs(x - extreme) > deadzone:
            count += direction != 0
            direction = 1 if x > extreme else -1
            extreme = x
    return count / hours
