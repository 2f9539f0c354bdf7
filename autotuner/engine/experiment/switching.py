"""The relay's switching: the filtered error against the hysteresis, sub-sample crossings, the cycle's times.

The relay switches when the filtered control error crosses ``∓hysteresis``.
The crossing happened between the last two samples; switching one sample
period after it, with the interval's MV averaged to keep the area, makes the
limit cycle periodic in continuous time instead of jittering by a sample at
every switch (the frequency-response estimate depends on that periodicity).
Rising crossings bound the periods the estimates use; falling ones the
half-period check. The oscillation's watch ends an experiment whose cycle
died out.
"""

from __future__ import annotations

import numpy as np

from autotuner.engine.outcome import Code
from autotuner.engine.experiment import endings
from autotuner.engine.experiment.loop import Loop
from autotuner.engine.experiment.phase_filter import PhaseFilter


class Switching:
    """The relay's state (+1 high, −1 low) and the samples and times of its switches in the ``loop``'s record."""

    def __init__(self, loop: Loop) -> None:
        self.loop = loop
        self.relay = 0
        self.filtered = 0.0  # the filtered control error, PV units
        self.peak_error = 0.0  # its largest size so far
        self.crossing = 0.0  # the latest crossing's sub-sample time, s
        self.start = 0  # the sample the relay started at
        self.switches: list[int] = []  # the sample of each switch
        self.rising: list[int] = []  # ... of each rising one
        # Sub-sample times of the rising crossings: the period they give is
        # free of the sampling jitter of the switch instants.
        self.crossings: list[float] = []
        self.falls: list[float] = []  # the same at the falling switches
        self.longest_half = 0.0  # the longest time between two switches so far, s (watch)
        self.react = 0.0  # seconds from the relay's start to its first switch

    def begin(self) -> None:
        """The relay starts at the high level at the latest sample."""
        self.relay = 1
        self.start = len(self.loop.record) - 1
        self.filtered = 0.0
        self.crossing = self.loop.record.time(-1)

    @property
    def periods(self) -> int:
        """Whole periods so far."""
        return len(self.rising) - 1

    def period(self) -> float:
        """The latest whole period between rising switches, s (there must be one)."""
        time = self.loop.record.time
        return time(self.rising[-1]) - time(self.rising[-2])

    def step(self, e: float, dt: float, phase_filter: PhaseFilter, hysteresis: float) -> int:
        """Filter the control error ``e`` (PV units) taken ``dt`` s after the previous sample through
        ``phase_filter``; the switch it
        makes at the latest sample: +1 rising, −1 falling, 0 none. ``hysteresis``: PV units."""
        before = self.filtered
        self.filtered = phase_filter.step(e, dt)
        self.peak_error = max(self.peak_error, abs(self.filtered))
        if self.relay > 0 and self.filtered < -hysteresis:
            self._switch(-1, -hysteresis, before, dt)
            return -1
        if self.relay < 0 and self.filtered > hysteresis:
            self._switch(1, hysteresis, before, dt)
            return 1
        return 0

    def _switch(self, relay: int, threshold: float, before: float, dt: float) -> None:
        time, k = self.loop.record.time, len(self.loop.record) - 1
        frac = (threshold - before) / (self.filtered - before)
        self.crossing = time(k - 1) + frac * dt
        self.relay = relay
        if self.switches:
            self.longest_half = max(self.longest_half, time(k) - time(self.switches[-1]))
        self.switches.append(k)
        if len(self.switches) == 1:
            # At least a sample: a process without dead time answers within one (noise-free, no hysteresis).
            self.react = self.crossing - time(self.start)
        if relay > 0:
            self.rising.append(k)
            self.crossings.append(self.crossing)
        else:
            self.falls.append(self.crossing)

    def blend(self, old: float, new: float, dt: float) -> float:
        """The MV over the sample interval of a switch from ``old`` to ``new`` (MV units) at the crossing,
        ``dt`` s after the previous sample: the area of a switch at the crossing itself."""
        late = (self.crossing - self.loop.record.time(-2)) / dt
        return old * late + new * (1.0 - late)

    def watch(self, hysteresis: float) -> str | None:
        """End the experiment (endings.Ended) when the cycle died out (``hysteresis``: PV units); after
        ``max_periods``, say when the estimates did not settle."""
        if self.periods >= self.loop.config.max_periods:
            return f"after {self.periods} periods"
        if len(self.switches) < 3:
            return None
        time = self.loop.record.time
        if time(-1) - time(self.switches[-1]) > 5.0 * self.longest_half:
            if self._pushed_away(hysteresis):
                raise endings.Ended(Code.DISTURBANCE, endings.PUSHED_AWAY)
            raise endings.Ended(Code.NO_OSCILLATION, endings.DIED_OUT)
        return None

    def _pushed_away(self, hysteresis: float) -> bool:
        """True when, since the last switch, the PV moved away from the set point by more than the cycle's swing
        and the hysteresis (PV units).

        A relay held at one level with the error growing is a relay without
        the authority to bring the PV back: something larger than amp pushes it.
        """
        loop = self.loop
        last = self.switches[-1]
        before = loop.record.y[self.switches[-3]:last]
        swing = 0.5 * float(np.max(before) - np.min(before)) if len(before) else 0.0
        error = loop.sign * (loop.sp - loop.record.pv(-1))
        pushing = error * self.relay > 0.0  # the relay pushes against an error that keeps growing
        return pushing and abs(error) > swing + hysteresis
