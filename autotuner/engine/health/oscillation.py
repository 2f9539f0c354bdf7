"""Oscillation: Hägglund's detector, the regularity of the zero crossings, the period and the amplitude.

Hägglund (1995), "A control-loop performance monitor", Control Engineering Practice 3(11):1543–1551: a load
disturbance is detected when the integrated absolute error between two zero crossings of the control error,
IAE = ∫|e|dt, exceeds IAE_lim = 2a/ωu (a half-period of a sinusoid of amplitude a at the ultimate frequency
ωu); the loop oscillates when more than n_lim = 10 are detected within the supervision time T_sup = 50·Tu
(here 50 periods of the slower of Tu and the oscillation itself, so a slow limit cycle is judged over as many
of its own periods).
Without a model (no ωu) each half-cycle is held against a half sine of amplitude a and its own length,
IAE_lim,i = 2a·Δi/π, which asks that its mean deviation be that of a sine of amplitude a.

Thornhill and Hägglund (1997), "Detection and diagnosis of oscillation in control loops", Control Engineering
Practice 5(10):1343–1354: the oscillation is regular when the periods between alternate zero crossings vary
little, r = mean(Tp) / (3·std(Tp)) > 1; here with the median and the median absolute deviation (×1.4826, the
standard deviation of a normal spread), so one spurious crossing does not make a regular oscillation
irregular.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autotuner.engine.health.signals import HalfCycles, half_cycles

N_LIM = 10  # detections within the supervision time that make an oscillation (Hägglund)
SUPERVISION_PERIODS = 50.0  # T_sup in ultimate periods (Hägglund)
REGULAR = 1.0  # r above which the crossings are regular (Thornhill)
MIN_HALF_CYCLES = 10  # fewer complete half-cycles say nothing about regularity


@dataclass(frozen=True)
class Oscillation:
    """What the error's zero crossings say.

    ``cycles``: the half-cycles of the error. ``detected``: which of them exceeded IAE_lim (Hägglund's load
    detections), ``detections`` how many. ``rate``: detections per
    supervision time T_sup. ``regularity``: Thornhill's r (None: too few half-cycles). ``period``: the mean
    period, s; ``amplitude``: the mean amplitude of the error, PV units, as a sine of equal mean absolute value
    (π/2 · IAE/Δ) — both None without half-cycles.
    """

    cycles: HalfCycles
    detected: np.ndarray
    rate: float
    regularity: float | None
    period: float | None
    amplitude: float | None

    @property
    def detections(self) -> int:
        """How many half-cycles Hägglund's detector counted."""
        return int(np.count_nonzero(self.detected))

    @property
    def alarm(self) -> bool:
        """Hägglund's alarm: at least n_lim detections per supervision time."""
        return self.rate >= N_LIM

    @property
    def oscillating(self) -> bool:
        """Hägglund's alarm on crossings that are regular (Thornhill), with at least n_lim detections in the
        window: a sustained oscillation, not a run of irregular load disturbances nor one ringing response."""
        return (self.alarm and self.detections >= N_LIM and self.regularity is not None
                and self.regularity > REGULAR)


def oscillation(e: np.ndarray, ts: float, a: float, tu: float | None, hysteresis: float) -> Oscillation:
    """Hägglund's detector and the regularity on the control error ``e`` (PV units, every ``ts`` seconds).

    ``a``: the deviation that counts, PV units; ``tu``: the ultimate period, s (None: unknown, each half-cycle
    against its own length); ``hysteresis``: PV units the error must pass beyond zero to cross (noise).
    """
    cycles = half_cycles(e, ts, hysteresis)
    if not len(cycles):
        return Oscillation(cycles, np.zeros(0, dtype=bool), 0.0, None, None, None)
    limit = a * tu / math.pi if tu is not None else 2.0 * a * cycles.duration / math.pi
    detected = cycles.iae > limit
    periods = cycles.periods
    period = float(np.mean(periods)) if len(periods) else 2.0 * float(np.mean(cycles.duration))
    # 50 periods of the slower of Tu and the oscillation: a slow limit cycle (a sticking valve's) is counted
    # over as many of its own periods as Hägglund counts of Tu
    supervision = SUPERVISION_PERIODS * max(tu or 0.0, period)
    rate = int(np.count_nonzero(detected)) * supervision / (len(e) * ts)
    regularity = None
    if len(cycles) >= MIN_HALF_CYCLES:
        # median and MAD: one spurious crossing (noise, a load) makes two odd periods, which the standard
        # deviation would weigh heavily; the sample time bounds how exactly a period is known
        spread = 1.4826 * float(np.median(np.abs(periods - np.median(periods))))
        regularity = float(np.median(periods) / (3.0 * max(spread, 0.5 * ts)))
    amplitude = float(0.5 * math.pi * np.mean(cycles.iae / cycles.duration))
    return Oscillation(cycles, detected, rate, regularity, period, amplitude)
