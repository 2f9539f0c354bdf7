"""The runaway tests: a PV that keeps moving away from the set point, faster and faster, under the relay.

Long after the relay turned against it (over three windows of
``RUNAWAY_WINDOW`` reaction time after the process had time to answer, or,
below full amp, over four windows that split the whole time since), such a
PV is an open-loop unstable process the level cannot hold: the weaker level
of the biased relay has less authority than the overshoot the dead time
gave. The experiment then rescues it with the full amp (levels.py). If the
PV runs away from a level at full amp, no relay holds the process: the
experiment ends (endings.runaway_at_full_amp).
"""

from __future__ import annotations

import math

import numpy as np

from autotuner.engine.experiment import endings
from autotuner.engine.experiment.estimates import GAP, longest_gap
from autotuner.engine.experiment.levels import Levels
from autotuner.engine.experiment.loop import Loop
from autotuner.engine.experiment.switching import Switching

# A runaway from a full-amp level within this fraction of its growth time constant after the relay's answer
# arrived is faster than one unstable pole with dead time runs from it (D/T ≥ 0.5 for that).
REACH_ONE_POLE = 0.25
# A first switch within this many samples of the relay's start tells nothing of the process's reaction time
# (see Runaway.reaction).
REACT_SAMPLES = 3
# Windows of the runaway test, as a share of the process's reaction time.
RUNAWAY_WINDOW = 0.15
# The runaway test's steps must grow this close to geometrically (s0·s2 ≥ GEOMETRIC·s1², less the noise).
GEOMETRIC = 0.97
# ... and by more than this share of the distance from the set point: the rounding of the windows' means
# (running sums since the switch: about 1e-13 of it) is no growth.
ROUNDING = 1e-9


class Runaway:
    """The runaway test's state: running sums of the PV's distance from the set point since the latest switch or
    rescue, the process's reaction time and when the level was last strengthened (``loop``, ``switching``,
    ``levels``: the loop under test, the relay's switches and its levels)."""

    def __init__(self, loop: Loop, switching: Switching, levels: Levels) -> None:
        self.loop = loop
        self.switching = switching
        self.levels = levels
        self.rescued_at = 0  # the sample the level was last strengthened at
        self._turn = 0.0  # seconds from the first switch to the PV's first turn (see reaction)
        # Running sums of the PV's distance from the set point over the samples after _sums_from: the long
        # windows' means at O(1) per sample.
        self._sums_from = -1
        self._sums = [0.0]

    def check(self, lags: list[float]) -> bool:
        """True when the level must be strengthened now (the latest sample ran away from a weak level); ends the
        experiment (endings.Ended) when it ran away from a level at full amp (``lags``: the process's lag over
        each period measured, radians)."""
        loop, switching = self.loop, self.switching
        k = len(loop.record) - 1
        react = self.reaction(k)
        if not switching.switches:
            return False
        # Since the last switch, or since the level was strengthened (its effect takes as long to arrive).
        last = max(switching.switches[-1], self.rescued_at)
        self._sum_distance(last, k)
        if react <= 0.0:
            return False
        m = max(int(round(RUNAWAY_WINDOW * react / loop.dt)), 2)  # samples per window
        # The dead time after the switch has passed, and three windows since (the PV accelerates
        # away during the dead time whatever the process).
        elapsed = loop.record.time(k) - loop.record.time(last) - react
        if elapsed < 3 * m * loop.dt:
            return False
        full = self.levels.at_full_amp(switching.relay)
        growth = self._runaway(k, m, samples=True)
        if growth is None and not full and elapsed >= 4 * m * loop.dt:
            # Windows that grow with the time since, and the PV's mean over each: a runaway much slower
            # than the reaction time (D/T 0.275 near a weak level's equilibrium) grows by less than the
            # noise from window to window, and the short windows' samples saw it only once it was beyond
            # the full amp's reach (exp(-0.55*s)/(2*s-1) with 1 % noise: 10 s late, refused with 17).
            # (Not at full amp: there the short windows' growth rate tells one unstable pole from two.)
            m = int(elapsed / (4.0 * loop.dt))
            growth = self._runaway(k, m, samples=False)
        if growth is None:
            return False
        away, steps = growth
        if len(switching.switches) >= 3 and away[-1] <= self._peak_away():
            return False  # within the swing the cycle already had
        if full:
            # The runaway's growth rate (1/s) is an unstable pole's 1/T once the MV is held.
            reach = react * math.log(steps[2] / steps[1]) / (m * loop.dt)
            raise endings.runaway_at_full_amp(loop.config.amp, reach, max(lags, default=0.0), REACH_ONE_POLE,
                                              self._stalled_note())
        self.rescued_at = k
        return True

    def _sum_distance(self, last: int, k: int) -> None:
        """Add sample ``k``'s distance of the PV from the set point to the sums since sample ``last`` (the
        latest switch or rescue), starting them anew when ``last`` moved."""
        if last != self._sums_from:
            self._sums_from, self._sums = last, [0.0]
        if k > last:
            self._sums.append(self._sums[-1] + (self.loop.record.pv(k) - self.loop.sp))

    def mean_distance(self, i: int, m: int) -> float:
        """The PV's mean distance from the set point over the ``m`` samples up to sample ``i`` (PV units).

        From the running sums since the latest switch (O(1) per mark, whatever the time since the switch);
        a window reaching back to the switch (samples denser than the noise stage's) is summed as it is.
        """
        first = i - m + 1
        if first > self._sums_from:
            return (self._sums[i - self._sums_from] - self._sums[first - 1 - self._sums_from]) / m
        return float(np.sum(self.loop.record.y[first:i + 1] - self.loop.sp)) / m

    def _runaway(self, k: int, m: int, samples: bool) -> tuple[list[float], np.ndarray] | None:
        """(distances from the set point, their steps) when the PV moves away faster and faster, else None.

        Over four marks ``m`` samples apart ending at sample ``k``: the PV at each (``samples``) or its mean
        over the ``m`` samples up to each. Equal windows of samples (a sampled ramp compared over unequal
        ones looks curved); the steps must grow by more than the noise, and geometrically: a stable
        process's answer to a ramp (a drifting load) grows too, but its steps converge to the ramp's, and
        an unstable pole's grow as ``s0·s2 = s1²``.
        """
        loop = self.loop
        marks = (k - 3 * m, k - 2 * m, k - m, k)
        distances = ([loop.record.pv(i) - loop.sp for i in marks] if samples
                     else [self.mean_distance(i, m) for i in marks])
        away = [-self.switching.relay * loop.sign * d for d in distances]
        steps = np.diff(away)
        # (And by more than the means' rounding: a followed drift's PV is a ramp, whose equal steps come out of
        # running sums a rounding apart, and a noise-free record's floor is nothing else.)
        floor = 3.0 * loop.noise / (1.0 if samples else math.sqrt(m)) + ROUNDING * max(abs(a) for a in away)
        if not (steps[0] > floor and steps[1] > steps[0] + floor and steps[2] > steps[1] + floor):
            return None
        if steps[0] * steps[2] < GEOMETRIC * steps[1] ** 2 - floor * (steps[0] + steps[2]):
            return None
        return away, steps

    def reaction(self, k: int) -> float:
        """Seconds the process takes to answer the relay, as known at sample ``k``: the runaway test's time scale
        (0 while unknown).

        The time from the relay's start to its first switch. A process without
        dead time crosses a zero hysteresis (no noise) at its first sample, and
        a high-order lag then still accelerates long after: for such a process
        (a first switch within ``REACT_SAMPLES`` samples) it is the time from
        the first switch until the PV turned back towards the set point.
        """
        loop, switching = self.loop, self.switching
        if switching.react > REACT_SAMPLES * loop.dt:
            return switching.react
        if not self._turn and switching.switches:
            first = switching.switches[0]
            time = loop.record.time
            if len(switching.switches) >= 2:
                self._turn = time(switching.switches[1]) - time(first)
            elif k - 1 > first:
                # After the first switch the relay pushes the PV back: it turns when its distance from the set
                # point stops growing.
                away = [switching.relay * loop.sign * (loop.sp - loop.record.pv(i)) for i in (k - 1, k)]
                if away[1] < away[0]:
                    self._turn = time(k - 1) - time(first)
        return self._turn

    def _peak_away(self) -> float:
        """Largest deviation of the PV from the set point over the last whole period before the current half
        (PV units)."""
        start, end = self.switching.switches[-3], self.switching.switches[-1]
        return float(np.max(np.abs(self.loop.record.y[start:end] - self.loop.sp)))

    def _stalled_note(self) -> str:
        """What a stall of the samples over the last period adds to a runaway's refusal ("" without one)."""
        record, switches = self.loop.record, self.switching.switches
        start = record.time(switches[-3] if len(switches) >= 3 else self.switching.start)
        gap = longest_gap(record.since(start).t, start, record.time(-1))
        return endings.stalled_note(gap) if gap > GAP * self.loop.dt else ""
