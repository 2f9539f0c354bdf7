"""What several indices read off a signal: its noise level and its half-cycles between zero crossings."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# The standard deviation of a normal variable per median absolute deviation.
_MAD_TO_STD = 1.4826


def noise_std(x: np.ndarray) -> float:
    """Standard deviation of the white noise on ``x`` (its units), from its second differences.

    Second differences of white noise of variance σ² have variance 6σ², while those of a slow signal are small;
    the median absolute deviation keeps the occasional step (a set-point change, a slip) out.
    """
    if len(x) < 3:
        return 0.0
    d2 = np.diff(x, 2)
    return float(_MAD_TO_STD * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))


@dataclass(frozen=True)
class HalfCycles:
    """The half-cycles of a signal between its zero crossings (sample indices and what lies between).

    ``start[i]``, ``end[i]``: the samples where half-cycle i begins and ends (``end[i] == start[i + 1]``);
    ``sign[i]``: +1 above zero, −1 below; ``iae[i]``: ∫|x|dt over it (signal units × seconds);
    ``duration[i]``: its length, seconds.
    """

    start: np.ndarray
    end: np.ndarray
    sign: np.ndarray
    iae: np.ndarray
    duration: np.ndarray

    def __len__(self) -> int:
        return len(self.start)

    @property
    def periods(self) -> np.ndarray:
        """Lengths of the full cycles, seconds: each pair of consecutive half-cycles."""
        return self.duration[:-1] + self.duration[1:]


def half_cycles(x: np.ndarray, ts: float, hysteresis: float) -> HalfCycles:
    """The complete half-cycles of ``x`` (sampled every ``ts`` seconds) about zero.

    A crossing counts once ``x`` has gone beyond ±``hysteresis`` on the other side (a Schmitt trigger, so noise
    about zero makes no crossings); the half-cycle then starts at the last sign change before that sample. The
    parts before the first and after the last crossing are incomplete and left out.
    """
    state = np.where(x > hysteresis, 1.0, np.where(x < -hysteresis, -1.0, np.nan))
    known = np.flatnonzero(~np.isnan(state))
    empty = np.zeros(0, dtype=int)
    if len(known) < 2:
        return HalfCycles(empty, empty, empty, np.zeros(0), np.zeros(0))
    flips = known[1:][np.diff(state[known]) != 0.0]  # the samples where the trigger changes side
    if len(flips) < 2:
        return HalfCycles(empty, empty, empty, np.zeros(0), np.zeros(0))
    # The last sign change at or before each flip: x changes sign between samples k-1 and k.
    changes = np.flatnonzero(np.signbit(x[1:]) != np.signbit(x[:-1])) + 1
    at = changes[np.maximum(np.searchsorted(changes, flips, side="right") - 1, 0)]
    bounds = np.where(at <= flips, at, flips)
    start, end = bounds[:-1], bounds[1:]
    cumulative = np.concatenate(([0.0], np.cumsum(np.abs(x)))) * ts
    return HalfCycles(start, end, state[flips[:-1]].astype(int), cumulative[end] - cumulative[start],
                      (end - start) * ts)
