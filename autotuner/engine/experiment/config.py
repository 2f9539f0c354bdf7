"""The settings of one relay experiment (:class:`RelayConfig`), checked when made."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class RelayConfig:
    """Settings of one experiment.

    amp: largest change of the MV from its starting value (MV units, > 0).
    phase_deg: requested process phase lag at the identified point, degrees (90–170).
    hysteresis: relay hysteresis in PV units; ``None`` measures the noise first.
    bias: asymmetry of the relay as a fraction of ``amp`` (0 ≤ bias < 0.5); the
        MV alternates between ``mv0 + amp`` and ``mv0 − amp·(1 − 2·bias)``.
    reverse: reverse-acting loop (more MV gives less PV).
    pv_limits, mv_limits: safety range of the PV and allowed range of the MV.
    mv_rate: largest rate of change of the MV, MV units per second (the relay
        then ramps between its levels; the estimate uses the MV as applied).
    time_limit: longest experiment, seconds.
    noise_samples: samples of the noise-measuring stage.
    max_periods: give up after this many oscillation periods.
    phase_tol_deg: accepted error of the phase, degrees (this and the three tolerances below: > 0).
    gain_tol: accepted relative change of the point between consecutive estimates.
    static_tol: accepted change of ``|F(jω)|/K0`` between consecutive estimates
        (measured this way, the tolerance on the static gain stays meaningful as
        ``K0`` grows towards an integrator).
    noise_tol: with measurement noise, the accepted standard error of the mean
        |F(jω)| (relative) over several periods (stopping.py); the experiment
        refuses with NOISE_TOO_HIGH when it is out of reach by ``max_periods``.
    expected_period: the oscillation period expected, seconds (only for the
        time-left estimate ``ite`` before the period is measured; None: a
        share of the time limit).
    follow_loads: look for load steps and drift in the record (load_fit.py),
        estimate the static gain through them and let the relay's centre
        follow them within ±amp; off, the experiment is the plain one (which
        takes a load's response for the relay's and reports a wrong static
        gain). A session whose writes can be late (a link, a busy machine)
        tells the experiment when each MV arrived (:meth:`RelayExperiment.applied`):
        a stall recorded as if the MV had arrived on time is what a load step
        looks like to the fit.
    """

    amp: float
    phase_deg: float = 135.0
    hysteresis: float | None = None
    bias: float = 0.2
    reverse: bool = False
    pv_limits: tuple[float, float] = (-math.inf, math.inf)
    mv_limits: tuple[float, float] = (-math.inf, math.inf)
    mv_rate: float = math.inf
    time_limit: float = math.inf
    noise_samples: int = 20
    max_periods: int = 25
    phase_tol_deg: float = 0.5
    gain_tol: float = 0.01
    static_tol: float = 0.02
    noise_tol: float = 0.004
    expected_period: float | None = None
    follow_loads: bool = True

    def __post_init__(self) -> None:
        if not (math.isfinite(self.amp) and self.amp > 0.0):
            raise ValueError(f"amp must be a positive number of MV units, got {self.amp}")
        if not 90.0 <= self.phase_deg <= 170.0:
            raise ValueError(f"phase must be between 90 and 170 degrees of lag, got {self.phase_deg}")
        if self.hysteresis is not None and not (math.isfinite(self.hysteresis) and self.hysteresis >= 0.0):
            raise ValueError(f"hysteresis must be ≥ 0 PV units, got {self.hysteresis}")
        if not 0.0 <= self.bias < 0.5:
            raise ValueError(f"bias must be in [0, 0.5), got {self.bias}")
        if not self.mv_rate > 0.0:
            raise ValueError(f"mv_rate must be positive MV units per second, got {self.mv_rate}")
        if not self.time_limit > 0.0:
            raise ValueError(f"time limit must be positive seconds, got {self.time_limit}")
        if self.expected_period is not None and not (math.isfinite(self.expected_period) and self.expected_period > 0):
            raise ValueError(f"expected_period must be a positive number of seconds, got {self.expected_period}")
        if self.noise_samples < 5:
            raise ValueError(f"noise_samples must be at least 5, got {self.noise_samples}")
        if self.max_periods < 1:
            raise ValueError(f"max_periods must be at least 1, got {self.max_periods}")
        for name in ("phase_tol_deg", "gain_tol", "static_tol", "noise_tol"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):  # 0 would be a tolerance nothing meets (and a division)
                raise ValueError(f"{name} must be a positive number, got {value}")
        for name, (lo, hi) in (("pv_limits", self.pv_limits), ("mv_limits", self.mv_limits)):
            if not lo < hi:
                raise ValueError(f"{name} must be (low, high) with low < high, got ({lo}, {hi})")
