"""How late the sessions' samples are: histograms the field fills and hands to the loop manager in batches.

Each sample of a session reports two wall-second figures
(:attr:`~autotuner.service.link_session.SessionHooks.on_timing`): how late
its PV read completed behind its due time (the link's round trip included:
what the experiment sees as jitter), and how late the session itself started
the read (its process's own part: a starved CPU, a busy event loop).
:class:`Timings` gathers them per field and hands a :class:`TimingBatch` to
the manager every :data:`FLUSH_PERIOD` seconds — one message, not one per
sample, from a sampler process. The manager keeps the running totals (the
daemon's metrics, the load benchmark's percentiles) and refuses new TUNEs
while samples are late by the daemon's own fault.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from autotuner.service.daemon.capacity import Cost

# Bucket bounds: 20 per decade from 10 µs to 1000 s (a percentile read from them is within 6 % of the sample's).
PER_DECADE = 20
BOUNDS = 10.0 ** (np.arange(-5 * PER_DECADE, 3 * PER_DECADE + 1) / PER_DECADE)
# A field hands its timings to the manager this often, wall seconds.
FLUSH_PERIOD = 0.5


@dataclass
class Histogram:
    """Counts of wall-second values by :data:`BOUNDS` (the last bucket: beyond them), their sum and largest."""

    counts: np.ndarray = field(default_factory=lambda: np.zeros(len(BOUNDS) + 1, dtype=np.int64))
    total: float = 0.0
    largest: float = 0.0

    @property
    def count(self) -> int:
        """How many values."""
        return int(self.counts.sum())

    def add(self, value: float) -> None:
        """One value, seconds."""
        self.counts[int(np.searchsorted(BOUNDS, value))] += 1
        self.total += value
        self.largest = max(self.largest, value)

    def merge(self, other: Histogram) -> None:
        """Add ``other``'s values."""
        self.counts += other.counts
        self.total += other.total
        self.largest = max(self.largest, other.largest)

    def quantile(self, q: float) -> float:
        """The ``q`` quantile (0–1), seconds, interpolated within its bucket on a log scale (nan: no values)."""
        n = self.count
        if n == 0:
            return math.nan
        rank = q * n
        cumulative = np.cumsum(self.counts)
        i = int(np.searchsorted(cumulative, rank, side="left"))
        if i >= len(BOUNDS):
            return self.largest
        low = BOUNDS[i - 1] if i > 0 else BOUNDS[0] / 10.0 ** (1.0 / PER_DECADE)
        before = cumulative[i - 1] if i > 0 else 0
        share = (rank - before) / max(self.counts[i], 1)
        return float(min(low * (BOUNDS[i] / low) ** share, self.largest))

    def cumulative(self, bounds: list[float]) -> list[int]:
        """How many values are at most each of ``bounds`` (seconds; each one of :data:`BOUNDS`, or +inf)."""
        running = np.cumsum(self.counts)
        return [int(running[-1]) if math.isinf(b) else int(running[int(np.searchsorted(BOUNDS, b * (1 + 1e-9)) - 1)])
                for b in bounds]


@dataclass
class TimingBatch:
    """The timings of the samples since the last batch: ``late`` and ``own`` (wall seconds, see the module), the
    samples late enough by the field's own fault to hurt an experiment (``overloaded``) and per loop the worst
    of them (``worst``, seconds); ``analysis``: the CPU seconds of each period's analysis; ``readings``: the
    monitor's readings; ``cpu``: the CPU seconds the field's process (and its analyses) spent meanwhile; ``cost``: the field's
    estimate of its CPU seconds per sample and per reading (:mod:`~autotuner.service.daemon.capacity`; None: not
    yet)."""

    late: Histogram = field(default_factory=Histogram)
    own: Histogram = field(default_factory=Histogram)
    analysis: Histogram = field(default_factory=Histogram)
    overloaded: int = 0
    worst: dict[str, float] = field(default_factory=dict)
    readings: int = 0
    cpu: float = 0.0
    cost: Cost | None = None


class Timings:
    """What a field's sessions report, gathered until the next :meth:`take`."""

    def __init__(self) -> None:
        self._batch = TimingBatch()
        self._cpu = time.process_time()
        self._elsewhere = 0.0  # CPU seconds of analyses in other processes since the last take

    def add(self, loop_id: str, late: float, own: float, tolerance: float) -> None:
        """A sample of ``loop_id``: ``late`` and ``own`` seconds; ``tolerance``: the own lateness (seconds) past
        which a sample hurts the experiment."""
        batch = self._batch
        batch.late.add(late)
        batch.own.add(own)
        if own > tolerance:
            batch.overloaded += 1
            batch.worst[loop_id] = max(own, batch.worst.get(loop_id, 0.0))

    def analysed(self, cpu: float, elsewhere: bool) -> None:
        """A period's analysis took ``cpu`` CPU seconds; ``elsewhere``: in another process (a worker), whose CPU
        is then added to the batch's: it is the field's work."""
        self._batch.analysis.add(cpu)
        if elsewhere:
            self._elsewhere += cpu

    def read(self) -> None:
        """The monitor read a loop."""
        self._batch.readings += 1

    def take(self) -> TimingBatch:
        """The batch since the last take, with the process's CPU seconds since."""
        batch, self._batch = self._batch, TimingBatch()
        now = time.process_time()
        batch.cpu, self._cpu, self._elsewhere = now - self._cpu + self._elsewhere, now, 0.0
        return batch
