"""The experiment's samples, kept in arrays that grow in amortized O(1).

A relay experiment appends one sample per step and analyses a few periods of
them at each switch. Kept as lists, every analysis converted the whole record
to arrays (O(record) per period); kept here, each column is an array with room
to grow (doubled when full: O(1) per sample, amortized), and an analysis reads
views of the stretch it needs without copying anything.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Samples:
    """A stretch of the record (views): sample times (s), PV, the MV held from each sample and when each
    MV reached the process (s). ``u`` and ``s`` may be one shorter than ``t`` and ``y`` (the latest
    sample's MV not decided yet)."""

    t: np.ndarray
    y: np.ndarray
    u: np.ndarray
    s: np.ndarray


class Record:
    """Samples of an experiment: time (s), PV, and the MV held from each sample with the time it reached
    the process (s, the sample's time unless a late write said otherwise); room for ``capacity`` samples at
    first."""

    def __init__(self, capacity: int = 256) -> None:
        self._columns = np.empty((4, capacity))  # t, y, u, s
        self._samples = 0
        self._held = 0

    def __len__(self) -> int:
        return self._samples

    @property
    def held(self) -> int:
        """How many samples have their MV."""
        return self._held

    def add(self, t: float, pv: float) -> None:
        """A new sample: time ``t`` (s) and its PV, ``pv``."""
        if self._samples == self._columns.shape[1]:
            grown = np.empty((4, 2 * self._samples))
            grown[:, : self._samples] = self._columns
            self._columns = grown
        self._columns[0, self._samples] = t
        self._columns[1, self._samples] = pv
        self._samples += 1

    def hold(self, mv: float) -> None:
        """The MV ``mv`` held from the latest sample on, reaching the process at the sample's time."""
        self._columns[2, self._held] = mv
        self._columns[3, self._held] = self._columns[0, self._held]
        self._held += 1

    def applied(self, at: float) -> None:
        """The latest MV reached the process at ``at`` (s; not before its sample)."""
        self._columns[3, self._held - 1] = max(at, self._columns[0, self._held - 1])

    def time(self, i: int) -> float:
        """The time of sample ``i`` (s; negative counts from the latest)."""
        return float(self._columns[0, i if i >= 0 else self._samples + i])

    def pv(self, i: int) -> float:
        """The PV of sample ``i`` (negative counts from the latest)."""
        return float(self._columns[1, i if i >= 0 else self._samples + i])

    def mv(self, i: int) -> float:
        """The MV held from sample ``i`` (negative counts from the latest held)."""
        return float(self._columns[2, i if i >= 0 else self._held + i])

    @property
    def t(self) -> np.ndarray:
        """Every sample's time (s), a view."""
        return self._columns[0, : self._samples]

    @property
    def y(self) -> np.ndarray:
        """Every sample's PV, a view."""
        return self._columns[1, : self._samples]

    def all(self) -> Samples:
        """The whole record (views)."""
        return self.since(-np.inf)

    def since(self, time: float) -> Samples:
        """The samples from the last one at or before ``time`` (s) on, or all of them (views)."""
        first = max(int(np.searchsorted(self.t, time, side="right")) - 1, 0)
        c, n, h = self._columns, self._samples, self._held
        return Samples(c[0, first:n], c[1, first:n], c[2, first:h], c[3, first:h])
