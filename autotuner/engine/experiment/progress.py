"""Progress: the experiment's stage, the seconds it still needs (``ite``) and its progress report.

The time left is the noise stage's rest plus the periods the stopping rule
still needs, at the oscillation period as well as it is known: measured once
a whole period (or half of one) has passed; before, the caller's
``expected_period``, else a share of the time limit, else
``SAMPLES_PER_PERIOD`` samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

from autotuner.engine.experiment.convergence import MIN_PERIODS
from autotuner.engine.experiment.estimates import GAP, STALL
from autotuner.engine.experiment.loop import Loop
from autotuner.engine.experiment.switching import Switching
from autotuner.engine.outcome import Code

# Without an expected period, the time-left estimate starts from this share of the time limit.
LIMIT_SHARE = 200.0
# ... and without a time limit, from this many samples.
SAMPLES_PER_PERIOD = 100.0


class Stage(str, Enum):
    """What the experiment is doing now."""

    NOISE = "noise"
    RELAY = "relay"
    DONE = "done"


@dataclass(frozen=True)
class Status:
    """Progress report: ``ite`` is the estimated seconds left while running, the code when done.

    stage: what the experiment is doing; progress: 0–1; relay: +1 high, −1 low, 0 before the relay;
    filter_phase_deg: the phase filter's lag at the cycle's frequency, degrees (negative: a lead);
    periods: whole periods so far; code, message: how it ended (None, "" while running).
    """

    stage: Stage
    progress: float
    ite: float
    relay: int
    filter_phase_deg: float
    periods: int
    code: Code | None
    message: str


class Progress:
    """The time-left estimate and the progress, which never goes backwards (``loop``, ``switching``: the loop
    under test and the relay's switches)."""

    def __init__(self, loop: Loop, switching: Switching) -> None:
        self.loop = loop
        self.switching = switching
        self._progress = 0.0

    def period_guess(self, dt: float | None, relaying: bool) -> float:
        """The oscillation period as well as it is known now (s), given the mean sample interval ``dt`` (s;
        None before two samples); ``relaying``: the relay has started.

        Before the first switch it is at least twice the time since the relay
        started (the first switch comes after a quarter to half a period).
        """
        time, switching = self.loop.record.time, self.switching
        if len(switching.rising) >= 2:
            return switching.period()
        if len(switching.switches) >= 2:
            return 2.0 * (time(switching.switches[-1]) - time(switching.switches[-2]))
        c = self.loop.config
        if c.expected_period is not None:
            guess = c.expected_period
        elif math.isfinite(c.time_limit):
            guess = c.time_limit / LIMIT_SHARE
        else:
            guess = SAMPLES_PER_PERIOD * (dt if dt else 1.0)
        if relaying:
            guess = max(guess, 2.0 * (time(-1) - time(switching.start)))
        return guess

    def stall_tolerance(self, relaying: bool) -> float:
        """The longest time without a sample (s) that leaves the estimates usable (``relaying``: the relay has
        started): STALL of the period as well as it is known now, and at least GAP sample intervals."""
        dt = self.loop.mean_interval()
        return max(STALL * self.period_guess(dt, relaying), GAP * (dt or 0.0))

    def seconds_left(self, relaying: bool, longer: bool) -> float:
        """Estimated seconds to the end (``relaying``: the relay has started; ``longer``: a disturbed or noisy
        run, which averages at least two more periods)."""
        loop = self.loop
        c = loop.config
        elapsed = loop.elapsed()
        dt = loop.mean_interval()
        noise_left = max(c.noise_samples - len(loop.record), 0) * (dt or 0.0)
        period = self.period_guess(dt, relaying)
        rising = len(self.switching.rising)
        done = max(rising - 1, 0)
        needed = MIN_PERIODS + 1.0
        if rising == 0:
            needed += 0.5  # the half period before the first rising switch
        if longer:
            needed = max(needed, done + 2.0)
        needed = min(needed, float(c.max_periods))
        left = noise_left + max(needed - done, 0.5) * period
        if math.isfinite(c.time_limit):
            left = min(left, max(c.time_limit - elapsed, 0.0))
        return max(left, dt or period / SAMPLES_PER_PERIOD)

    def fraction(self, left: float) -> float:
        """Progress (0–1) with ``left`` seconds to go."""
        elapsed = self.loop.elapsed()
        # Progress never goes backwards, even when a measured period
        # turns out longer than the estimate before it.
        self._progress = max(self._progress, elapsed / (elapsed + left))
        return self._progress


def final_ite(code: Code | None) -> float:
    """``ite`` once the experiment is done: its ``code`` (0 without one)."""
    return float(code) if code is not None else 0.0
