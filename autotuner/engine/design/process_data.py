"""What the tuning rules need to know about a process, from a model, a plant or a measured point.

Three sources (methods.md §1, §4):

* an FOPDT model ``K·e^{−Ls}/(Ts + 1)``: every characteristic number follows
  exactly (tangent ``D = L``, ``R = K/T``; 63 % time ``L + T``; the ultimate
  point from the frequency response);
* any plant expression: the unit step response is simulated exactly (ZOH,
  :mod:`autotuner.engine.plant.simulation`) and the rules get the tangent at the point of
  steepest slope (``D``, ``R``), the 63 % time, a least-squares FOPDT fit
  (static gain fixed at the exact ``F(0)``, ``T`` and ``L`` fitted), and the
  exact frequency-response points (root of the unwrapped phase);
* a measured point ``F(jω)`` (the relay experiment), with the static gain if
  known, which then fixes the FOPDT or IPDT model through the point
  (:func:`autotuner.engine.design.point_design.fit_model`).

Times are in seconds, frequencies in rad/s, gains in PV units per MV unit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq, least_squares

from autotuner.engine.design.point_design import fit_model
from autotuner.engine.plant.process import Process
from autotuner.engine.experiment.relay import Point
from autotuner.engine.plant.simulation import simulate_open_loop

# Samples of each of the two step-response simulations (whole horizon, then
# a fine one up to just past the steepest point).
STEP_SAMPLES = 2000
# Horizon of the step response in units of the slowest time constant (or dead time).
HORIZON_SCALES = 12.0
# Tolerance on the phase of a measured point taken as the ultimate (180°) or 90° point, degrees.
PHASE_TOL_DEG = 0.5


class DataError(ValueError):
    """The data cannot give what a rule needs (message says what and why)."""


@dataclass(frozen=True)
class Fopdt:
    """First order plus dead time ``k·e^{−l s}/(t s + 1)``: static gain, lag t (s), dead time l (s)."""

    k: float
    t: float
    l: float

    @property
    def tau(self) -> float:
        """Normalised dead time ``L/(L + T)`` in [0, 1]."""
        return self.l / (self.l + self.t)

    def process(self) -> Process:
        """The model as a :class:`Process`."""
        return Process.from_tf((self.k,), (self.t, 1.0), self.l, text="FOPDT model")


@dataclass(frozen=True)
class Tangent:
    """Reaction curve of a unit MV step: apparent dead time ``d`` (s), steepest slope ``r`` (PV/s per MV).

    ``t63`` is the time (s) at which a stable response reaches 63.2 % of its
    final value (None for integrating processes).
    """

    d: float
    r: float
    t63: float | None

    @property
    def a(self) -> float:
        """``a = R·D``, the reaction-curve gain of methods.md §4 (PV per MV)."""
        return self.r * self.d


@dataclass(frozen=True)
class ProcessData:
    """Everything known about the process; ``None`` where the source cannot give it.

    source: "fopdt", "plant" or "point". process: the plant or the model
    (None for a point without static gain). static_gain: ``F(0)``, ``inf``
    for integrating, None if unknown. fopdt: the FOPDT model (given, fitted,
    or through the point). tangent: reaction curve. point: the measured point.
    """

    source: str
    process: Process | None
    static_gain: float | None
    fopdt: Fopdt | None
    tangent: Tangent | None
    point: Point | None = None

    @property
    def integrating(self) -> bool:
        return self.static_gain is not None and math.isinf(self.static_gain)

    @property
    def unstable(self) -> bool:
        return self.process is not None and self.process.is_unstable

    def phase_point(self, lag_deg: float) -> Point | None:
        """The point with the given phase lag (degrees): exact on the process, else the measured one.

        A measured point counts only if it lags by ``lag_deg`` within
        ``PHASE_TOL_DEG``; None if there is no such point.
        """
        if self.source == "point":
            if self.point is not None and abs(-self.point.phase_deg - lag_deg) <= PHASE_TOL_DEG:
                return self.point
            return None
        return exact_point(self.process, lag_deg)


def from_fopdt(k: float, t: float, l: float) -> ProcessData:
    """Data of the FOPDT model ``k·e^{−l s}/(t s + 1)`` (k ≠ 0, t > 0, l ≥ 0), all exact."""
    if not (math.isfinite(k) and k != 0.0):
        raise DataError(f"FOPDT static gain K must be finite and non-zero, got {k}")
    if not (math.isfinite(t) and t > 0.0):
        raise DataError(f"FOPDT time constant T must be > 0 s, got {t}")
    if not (math.isfinite(l) and l >= 0.0):
        raise DataError(f"FOPDT dead time L must be >= 0 s, got {l}")
    model = Fopdt(k, t, l)
    return ProcessData("fopdt", model.process(), k, model, Tangent(l, k / t, l + t))


def from_plant(process: Process) -> ProcessData:
    """Data of a plant: exact static gain, step-response tangent and least-squares FOPDT.

    Unstable plants get neither (no step response to read).

    ``process``: the process.
    """
    if process.is_unstable:
        return ProcessData("plant", process, process.static_gain(), None, None)
    tangent = step_tangent(process)
    gain = process.static_gain()
    fopdt = None if math.isinf(gain) else fit_fopdt(process, tangent)
    return ProcessData("plant", process, gain, fopdt, tangent)


def from_point(point: Point, static_gain: float | None) -> ProcessData:
    """Data of a measured point; with the static gain, the FOPDT (or IPDT) model through it.

    Raises DataError when the model cannot be fitted (see :func:`autotuner.engine.design.point_design.fit_model`).

    ``point``: the measured point; ``static_gain``: F(0), PV per MV unit (None: unknown).
    """
    if static_gain is None:
        return ProcessData("point", None, None, None, None, point)
    try:
        model = fit_model(point, static_gain)
    except ValueError as exc:
        raise DataError(str(exc)) from None
    if model.integrator_count:
        kv = model.num[-1]
        return ProcessData("point", model, math.inf, None, Tangent(model.delay, kv, None), point)
    if model.order == 0:
        raise DataError(f"the static gain {static_gain:g} is not larger than |F| = {point.gain:g} "
                        "at the point: no lag fits, only a pure dead time")
    t = model.den[0] / model.den[1]
    fopdt = Fopdt(static_gain, t, model.delay)
    return ProcessData("point", model, static_gain, fopdt, Tangent(model.delay, static_gain / t, model.delay + t),
                       point)


# -- exact frequency-response points ------------------------------------------


def exact_point(process: Process, lag_deg: float) -> Point | None:
    """Lowest-frequency point where the process lags by ``lag_deg`` degrees (None if it never does).

    The unwrapped phase is bracketed on a log grid from 1e-6 to 1e6 rad/s and
    the crossing solved to rounding accuracy with Brent's method.

    ``process``: the process.
    """
    w = np.logspace(-6, 6, 12001)
    lag = -np.unwrap(np.angle(process.freqresp(w)))
    target = math.radians(lag_deg)
    above = np.nonzero(lag >= target)[0]
    if len(above) == 0 or above[0] == 0:
        return None
    i = above[0]

    def residual(log_w: float) -> float:
        raw = -float(np.angle(process.freqresp(math.exp(log_w))))
        # the multiple of 2π that puts the phase next to the unwrapped grid value
        return raw + 2.0 * math.pi * round((lag[i] - raw) / (2.0 * math.pi)) - target

    root = brentq(residual, math.log(w[i - 1]), math.log(w[i]), xtol=1e-14)
    omega = math.exp(root)
    return Point(omega, complex(process.freqresp(omega)))


def least_lag_point(process: Process) -> Point | None:
    """The point where an open-loop unstable process lags least, below 180° (None if it never does).

    Its lag falls from 180° at ω = 0 to a least value and rises after it, so
    it may never lag as little as a requested phase (``exact_point`` None).

    ``process``: the process.
    """
    w = np.logspace(-6, 6, 12001)
    lag = -np.unwrap(np.angle(process.freqresp(w)))
    i = int(np.argmin(lag))
    if not 0 < i < len(w) - 1 or lag[i] >= math.pi:
        return None
    return Point(float(w[i]), complex(process.freqresp(w[i])))


# -- step response -------------------------------------------------------------


def _time_scale(process: Process) -> float:
    """Slowest time constant or dead time of the process, s."""
    scales = [1.0 / abs(p.real) for p in process.poles if abs(p) > 1e-12 and abs(p.real) > 1e-12]
    return max(scales + [process.delay, 1e-9])


def step_response(process: Process, horizon: float, samples: int = STEP_SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """Times (s) and exact unit-step response over ``[0, horizon]`` on ``samples`` intervals.

    ``process``: the process; ``horizon``: s.
    """
    dt = horizon / samples
    y = simulate_open_loop(process, np.ones(samples), dt)
    return dt * np.arange(samples + 1), y


def _steepest(t: np.ndarray, y: np.ndarray) -> tuple[int, float]:
    """Index of the interval with the steepest chord and its slope."""
    slopes = np.diff(y) / np.diff(t)
    i = int(np.argmax(slopes))
    return i, float(slopes[i])


def step_tangent(process: Process) -> Tangent:
    """Tangent at the steepest point of the unit step response (methods.md §4.1).

    The slope is the chord of one sample interval, located at its midpoint
    (second-order accurate like a central difference, and exact for the kink
    of a first-order response at the dead time). A coarse simulation over the
    whole horizon finds the steepest interval, a fine one up to just past it
    refines it. For an integrating process the slope keeps rising and the
    tangent is the final asymptote.

    ``process``: the process.
    """
    gain = process.static_gain()
    if gain == 0.0:
        raise DataError("the process has zero static gain: its step response has no reaction curve")
    horizon = process.delay + HORIZON_SCALES * _time_scale(process)
    t, y = step_response(process, horizon)
    sign = math.copysign(1.0, gain)
    i, _ = _steepest(t, sign * y)
    if i < len(t) - 2:
        t_f, y_f = step_response(process, t[i + 2])
        j, _ = _steepest(t_f, sign * y_f)
    else:
        t_f, y_f, j = t, y, i
    slope = (y_f[j + 1] - y_f[j]) / (t_f[j + 1] - t_f[j])
    mid_t, mid_y = 0.5 * (t_f[j] + t_f[j + 1]), 0.5 * (y_f[j] + y_f[j + 1])
    d = mid_t - mid_y / slope
    if d <= 0.0:
        raise DataError(f"the step-response tangent crosses the initial value at {d:.3g} s: no apparent dead time")
    t63 = None if math.isinf(gain) else float(np.interp(0.632, sign * y / abs(gain), t))
    return Tangent(float(d), float(slope), t63)


def fit_fopdt(process: Process, tangent: Tangent) -> Fopdt:
    """Least-squares FOPDT fit of the unit step response, static gain fixed at the exact ``F(0)``.

    ``T`` and ``L`` minimise the squared error over the simulated response on
    the horizon, starting from the tangent (``L = D``, ``T = t63 − D``).

    ``process``: the process; ``tangent``: its step tangent (the starting guess).
    """
    gain = process.static_gain()
    horizon = process.delay + HORIZON_SCALES * _time_scale(process)
    t, y = step_response(process, horizon)

    def residual(x: np.ndarray) -> np.ndarray:
        lag, dead = x
        return gain * (1.0 - np.exp(-np.maximum(t - dead, 0.0) / lag)) - y

    t0 = max(tangent.t63 - tangent.d, 1e-6 * horizon)
    fit = least_squares(residual, [t0, tangent.d], bounds=([1e-9 * horizon, 0.0], [np.inf, horizon]),
                        x_scale=[t0, max(tangent.d, 1e-3 * horizon)])
    return Fopdt(gain, float(fit.x[0]), float(fit.x[1]))
