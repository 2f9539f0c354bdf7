"""The loop under test as every part of the experiment sees it, and the noise stage that measures it.

Before the relay starts, the MV is held for ``noise_samples`` samples: the
PV's mean is the relay's set point, the scatter about a fitted line is the
measurement noise, and a slope well beyond its standard error is a PV still
settling when TUNE came (a load step just before, a set point change).
Twenty samples measure σ to about ±17 % (one in twenty runs 30 % low): each
whole period of the relay measures it again from the PV's third differences
(:func:`cycle_noise`, kept with that period's estimate), and the stopping rule
judges the larger of the two (convergence.sigma).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autotuner.engine.experiment.config import RelayConfig
from autotuner.engine.experiment.record import Record

# A PV slope over the noise stage beyond this many of its standard errors is a PV still settling at TUNE.
SETTLING_EVIDENCE = 5.0
# σ of a normal distribution over its median absolute deviation.
MAD_SIGMA = 1.4826


@dataclass
class Loop:
    """The settings, the starting MV, the loop's sign and the record; the rest the noise stage measures.

    config: the experiment's settings.
    mv0: the MV at the start, MV units.
    record: the samples.
    sign: −1 for a reverse-acting loop, else 1.
    sp: the relay's set point (the PV's mean over the noise stage), PV units.
    noise: standard deviation of the measurement noise over the noise stage, PV units.
    dt: the mean sample interval over the noise stage, s.
    settling: (the PV's slope at the start, sign-corrected PV units per s; its time, s), (0, 0) when
        the PV was steady.
    """

    config: RelayConfig
    mv0: float
    record: Record
    sign: float = 1.0
    sp: float = 0.0
    noise: float = 0.0
    dt: float = 0.0
    settling: tuple[float, float] = (0.0, 0.0)

    def measure_noise(self) -> None:
        """The noise stage's figures from the record so far (at least ``noise_samples`` samples)."""
        t, y = self.record.t, self.record.y
        slope, offset = np.polyfit(t - t[0], y, 1)
        residual = y - (offset + slope * (t - t[0]))
        self.noise = float(np.std(residual, ddof=2))
        self.sp = float(np.mean(y))
        # A PV still moving when TUNE came: the lag's free response, which the static ratio takes out
        # (settled_x). Noise alone gives a slope within a few of its standard errors.
        centred = t - float(np.mean(t))
        slope_std = self.noise / math.sqrt(float(centred @ centred)) if np.any(centred) else math.inf
        if abs(slope) > SETTLING_EVIDENCE * slope_std:
            self.settling = (self.sign * float(slope), float(np.mean(t)))
        self.dt = float(t[-1] - t[0]) / (len(t) - 1)

    def elapsed(self) -> float:
        """Seconds from the first sample to the latest (0 before any)."""
        record = self.record
        return record.time(-1) - record.time(0) if len(record) else 0.0

    def mean_interval(self) -> float | None:
        """The mean time between the samples so far (s); None before two."""
        samples = len(self.record)
        return (self.record.time(-1) - self.record.time(0)) / (samples - 1) if samples >= 2 else None


def cycle_noise(t: np.ndarray, y: np.ndarray) -> float:
    """σ of white measurement noise on the PV samples ``y`` (PV units) taken at the times ``t`` (s) over a
    relay's period.

    A third divided difference over four samples, Σ w_i·y_i with w_i = 1/Π_{j≠i}(t_i − t_j), has
    σ·sqrt(Σ w_i²) of white noise; scaled by that it is σ whatever the spacing (evenly spaced: the third
    difference over sqrt(20)). The plain third difference of samples taken unevenly (a field session's ±30 %
    jitter) reads the cycle's slope times the jitter as noise: 0.7–1.5 of the scatter gate on a noise-free
    record. The cycle's own at 100 samples per period is 2.5e-4 of its swing (a second difference's, 4e-3,
    would pass for noise of 0.2 %), and the kinks where the MV's switches reach the PV touch six samples per
    period: the median absolute deviation ignores them.
    """
    if len(y) < 10:
        return 0.0
    t0, t1, t2, t3 = t[:-3], t[1:-2], t[2:-1], t[3:]
    d01, d02, d03, d12, d13, d23 = t1 - t0, t2 - t0, t3 - t0, t2 - t1, t3 - t1, t3 - t2
    w = (-1.0 / (d01 * d02 * d03), 1.0 / (d01 * d12 * d13), -1.0 / (d02 * d12 * d23), 1.0 / (d03 * d13 * d23))
    d3 = (w[0] * y[:-3] + w[1] * y[1:-2] + w[2] * y[2:-1] + w[3] * y[3:])
    d3 /= np.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2 + w[3] ** 2)
    return MAD_SIGMA * float(np.median(np.abs(d3 - np.median(d3))))
