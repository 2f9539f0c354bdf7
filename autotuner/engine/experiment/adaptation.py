"""The phase filter's adaptation: the filter in front of the relay retuned once per period.

The control error passes through a first-order lag (or lead, phase_filter.py)
before the relay; the filter adds ``θ`` of phase so that the limit cycle
settles where the *process* lags by the target. ``θ`` starts at the
describing function's guess after the first half period and is corrected
once per period from the measured process lag (methods.md §6), so the
describing function's bias never enters. The hysteresis follows the noise as
it comes out of the filter.
"""

from __future__ import annotations

import math

import numpy as np

from autotuner.engine.experiment import relay_cycle
from autotuner.engine.experiment.loop import Loop
from autotuner.engine.experiment.phase_filter import PhaseFilter
from autotuner.engine.experiment.process_fit import ProcessModel

# The largest step of ln ω from one period to the next.
MAX_LOG_STEP = math.log(3.0)
# Measurements a period after a change still carry its transient; partial steps keep the correction from
# overshooting.
RELAXATION = 0.75
# Highest phase target (the RelayConfig's upper bound).
MAX_TARGET_DEG = 170.0


class Adaptation:
    """The filter, the hysteresis it implies and the phase target it aims at, for the ``loop`` under test."""

    def __init__(self, loop: Loop) -> None:
        self.loop = loop
        self.filter = PhaseFilter()
        self.omega = 0.0  # the frequency the filter's phase was set for, rad/s
        self.hysteresis = 0.0  # PV units
        # The phase the filter aims at: the requested one, or a reachable one (unstable processes).
        self.target_deg = loop.config.phase_deg
        self.lags: list[float] = []  # the process lag over every whole period, radians
        self._last: tuple[float, float] | None = None  # (ω, lag) of the latest correction
        self._slope = 1.0  # d lag / d ln ω of the process phase curve, as measured

    def begin(self) -> None:
        """The relay starts: a hysteresis of 3 noise standard deviations unless one was given."""
        h = self.loop.config.hysteresis
        self.hysteresis = 3.0 * self.loop.noise if h is None else h

    def start(self, half: float, peak_error: float, no_lag: bool) -> None:
        """Start the filter from the first half period (``half``, s) at the describing-function guess, given the
        filtered error's largest size (``peak_error``, PV units); ``no_lag``: a PV that already ran away
        (unstable), no lag until an estimate says what is reachable."""
        omega = math.pi / half
        sine = min(1.0, self.hysteresis / peak_error) if peak_error > 0 else 0.0
        theta = 0.0 if no_lag else math.pi - math.radians(self.target_deg) - math.asin(sine)
        self.set(theta, omega)

    def set(self, theta: float, omega: float) -> None:
        """The filter's phase ``theta`` (radians, lag positive) at ``omega`` (rad/s)."""
        self.filter.set_phase(theta, omega)
        self.omega = omega
        if self.loop.config.hysteresis is None:
            # Keep the hysteresis at three standard deviations of the noise as
            # it comes out of the filter, so a lead never makes the relay chatter.
            self.hysteresis = 3.0 * self.loop.noise * self.filter.noise_gain(self.loop.dt)

    def drop_lag(self) -> None:
        """No filter lag, and the secant forgotten (a rescued runaway: the requested phase may be out of reach)."""
        self.set(0.0, self.omega or 1.0)
        self._last = None

    def aim(self, wanted_deg: float) -> None:
        """Raise the target towards ``wanted_deg`` (degrees of lag; never lower, never above MAX_TARGET_DEG)."""
        self.target_deg = min(max(self.target_deg, wanted_deg), MAX_TARGET_DEG)

    def adapt(self, omega: float, lag: float) -> None:
        """Retune the filter for the next period from the period just measured (``omega``, rad/s; the
        process ``lag`` there, radians).

        Two things move when the filter changes: the frequency of the cycle and
        the process phase there. The measured pairs ``(ln ω, lag)`` trace the
        process phase curve, and a secant step on it predicts the frequency
        with the requested lag; the loop's phase balance, calibrated on the
        period just measured (it absorbs hysteresis and sampling delays),
        gives the filter phase needed there.
        """
        target = math.radians(self.target_deg)
        offset = math.pi - lag - self.filter.phase(omega)
        # Not from the first whole period: its lag still carries the start's transient (133° where the cycle
        # lags 140°), and a secant through it can even have the wrong sign.
        if self._last is not None and len(self.lags) > 2:
            w_prev, lag_prev = self._last
            dlog = math.log(omega / w_prev)
            if abs(dlog) > 0.005:
                self._slope = min(max((lag - lag_prev) / dlog, 0.2), 5.0)
        self._last = (omega, lag)
        step = min(max((target - lag) / self._slope, -MAX_LOG_STEP), MAX_LOG_STEP)
        omega_next = omega * math.exp(RELAXATION * step)
        now = self.filter.phase(omega_next)
        self.set(now + RELAXATION * (math.pi - target - offset - now), omega_next)

    def aim_from(self, model: ProcessModel, omega: float, lag: float, high: float, low: float) -> bool:
        """Retune the filter from a ``model`` of the process fitted to the record (process_fit.py) instead of the
        secant: the cycle at the frequency where the model lags by the target, with the filter phase that makes
        the relay's cycle periodic there (relay_cycle.py). ``omega`` (rad/s) and ``lag`` (radians): the period
        just measured, the guess's start; ``high``, ``low``: the relay's levels less its centre (MV units).
        False (nothing changed) where the model gives no such cycle within the filter's range.

        The measured lag of an early period carries the start's transient and the loop's phase balance is not
        the describing function's (the relay switches where the filtered error crosses, not its first
        harmonic): both are what the secant corrects period by period, and what the model knows at once.
        """
        target = math.radians(self.target_deg)
        aimed = model.frequency(target)
        if aimed is None or abs(math.log(aimed / omega)) > MAX_LOG_STEP:
            return False
        guess = math.pi - target - (math.pi - lag - self.filter.phase(omega))
        response = self.loop.sign * model.response(aimed * np.arange(1, relay_cycle.HARMONICS + 1))
        # (The switch lags the filtered error's crossing by half a sample: switching.py blends the MV from the
        # crossing a sample late, and the filter reads each sample as held over the interval before it.)
        theta = relay_cycle.filter_phase(response, aimed, self.loop.sign * model.k0, high, low, self.hysteresis,
                                         0.5 * self.loop.dt, guess)
        if theta is None:
            return False
        self.set(theta, aimed)
        self._last = None  # (the secant restarts from the aimed cycle)
        return True

    def phase_deg(self) -> float:
        """The filter's phase at the frequency it was set for, degrees."""
        return math.degrees(self.filter.phase(self.omega))
