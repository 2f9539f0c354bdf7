"""A loop's record for the health assessment: time, set point, process value, controller output and mode.

The caller gives the samples with their times (the engine reads no clock). :meth:`LoopRecord.of` checks them
and names the first bad sample; :meth:`LoopRecord.last` cuts the assessment window; :meth:`LoopRecord.uniform`
puts the samples on an even grid (a historian's export is often uneven), which the indices assume.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# Spacings within 1 % of the sample time count as even (a historian's time stamps jitter): no resampling.
_EVEN = 0.01


def _array(name: str, values: Sequence[float] | np.ndarray, n: int | None) -> np.ndarray:
    x = np.asarray(values, dtype=float)
    if x.ndim != 1:
        raise ValueError(f"{name} must be a sequence of numbers")
    if n is not None and len(x) != n:
        raise ValueError(f"{name} has {len(x)} samples, t has {n}")
    bad = np.flatnonzero(~np.isfinite(x))
    if len(bad):
        raise ValueError(f"{name} is not a finite number at sample {bad[0]} ({x[bad[0]]})")
    return x


@dataclass(frozen=True)
class LoopRecord:
    """Samples of one loop: ``t`` seconds (strictly increasing), ``sp`` and ``pv`` PV units, ``mv`` MV units
    (the controller output), ``auto`` True where the loop was in its normal (automatic) mode."""

    t: np.ndarray
    sp: np.ndarray
    pv: np.ndarray
    mv: np.ndarray
    auto: np.ndarray

    @classmethod
    def of(cls, t: Sequence[float] | np.ndarray, sp: Sequence[float] | np.ndarray, pv: Sequence[float] | np.ndarray,
           mv: Sequence[float] | np.ndarray, auto: Sequence[bool] | np.ndarray | None = None) -> LoopRecord:
        """A checked record: ``t`` seconds, ``sp``/``pv`` PV units, ``mv`` MV units, ``auto`` the mode per sample
        (None: automatic throughout). ValueError names the first bad sample: a length that differs, a value that
        is not a finite number, a time that does not increase."""
        times = _array("t", t, None)
        if len(times) < 2:
            raise ValueError(f"a record needs at least 2 samples, got {len(times)}")
        back = np.flatnonzero(np.diff(times) <= 0.0)
        if len(back):
            k = back[0] + 1
            raise ValueError(f"t does not increase at sample {k}: {times[k]:g} s after {times[k - 1]:g} s")
        modes = np.ones(len(times), dtype=bool) if auto is None else np.asarray(auto, dtype=bool)
        if modes.shape != times.shape:
            raise ValueError(f"auto has {modes.size} samples, t has {len(times)}")
        n = len(times)
        return cls(times, _array("sp", sp, n), _array("pv", pv, n), _array("mv", mv, n), modes)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def duration(self) -> float:
        """From the first sample to the last, seconds."""
        return float(self.t[-1] - self.t[0])

    @property
    def ts(self) -> float:
        """The sample time, seconds: the median spacing of ``t``."""
        return float(np.median(np.diff(self.t)))

    def _take(self, keep: slice | np.ndarray) -> LoopRecord:
        return LoopRecord(self.t[keep], self.sp[keep], self.pv[keep], self.mv[keep], self.auto[keep])

    def last(self, window: float) -> LoopRecord:
        """The samples of the last ``window`` seconds (all of them for an infinite window)."""
        if not window > 0.0:
            raise ValueError(f"the window must be a positive number of seconds, got {window}")
        start = int(np.searchsorted(self.t, self.t[-1] - window, side="left"))
        return self._take(slice(start, None))

    def uniform(self, ts: float | None = None) -> LoopRecord:
        """The record on an even grid of ``ts`` seconds (None: its median spacing) from its first sample.

        Unchanged when already even at that spacing. PV and MV are interpolated linearly; the set point and the
        mode hold their last value (they change in steps).
        """
        step = self.ts if ts is None else float(ts)
        if not step > 0.0:
            raise ValueError(f"the sample time must be a positive number of seconds, got {ts}")
        spacing = np.diff(self.t)
        if np.all(np.abs(spacing - step) <= _EVEN * step):
            return self
        n = int(np.floor(self.duration / step * (1.0 + 1e-12))) + 1
        if n < 2:
            raise ValueError(f"a sample time of {step:g} s leaves fewer than 2 samples in {self.duration:g} s")
        grid = self.t[0] + step * np.arange(n)
        held = np.searchsorted(self.t, grid, side="right") - 1
        return LoopRecord(grid, self.sp[held], np.interp(grid, self.t, self.pv), np.interp(grid, self.t, self.mv),
                          self.auto[held])

    def longest_auto(self) -> LoopRecord | None:
        """The longest stretch of consecutive samples in automatic (None when the loop never was)."""
        edges = np.diff(np.concatenate(([False], self.auto, [False])).astype(np.int8))
        starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
        if not len(starts):
            return None
        k = int(np.argmax(ends - starts))
        return self._take(slice(starts[k], ends[k]))
