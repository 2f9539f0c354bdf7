"""Robust PI/PID gains from one frequency-response point and the static gain.

The static gain ``K0`` and the point ``F(jω*) = r·e^{−jφ}`` fix a
three-parameter model exactly: first order plus dead time
``K0·e^{−Ls}/(Ts + 1)`` with ``T = sqrt((K0/r)² − 1)/ω*`` and
``L = (φ − atan(ω*T))/ω*``, or, when the static gain is too large to tell from
an integrator, ``Kv·e^{−Ls}/s`` with ``Kv = r·ω*`` and ``L = (φ − π/2)/ω*``.
That model puts all the lag beyond the first-order one into dead time. The
same data are explained just as well by the other extreme, two lags and no
dead time (``K0/((T1 s + 1)(T2 s + 1))`` or ``Kv/(s(Ts + 1))``), and a real
process lies in between; designing for the first model alone overshoots the
Ms of lag-dominant higher-order processes by up to 10 %. So the gains are
those with the largest integral gain ``ki = k/ti`` for which the loop keeps
``Ms`` on the first model and ``1.05·Ms`` on the second (MIGO on both, see
:mod:`autotuner.engine.design.robustness`). PID fixes ``td`` as a fraction of ``ti``
(at most ¼, so a series form always exists) and takes the fraction with the
largest ``ki``; PI is the fraction 0, so PID never has less integral gain on
the model. The set-point weight ``b`` is the largest in [0, 1] whose
set-point response has no resonance peak on the model.

The derivation and its check on the benchmark batch are in docs/design-rule.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autotuner.engine.control.gains import Gains
from autotuner.engine.plant.process import Process
from autotuner.engine.experiment.relay import Point
from autotuner.engine.design.robustness import Plant, log_grid, max_sensitivity, migo, pid_frequency_response

# A static gain this many times |F(jω*)| or more is designed as an integrator.
INTEGRATING_RATIO = 200.0
# Ms allowance on the no-dead-time bound relative to the best-guess model:
# 1.0 holds every batch process under Ms·1.02 but costs up to 35 % of the
# integral gain on delay-dominant ones; 1.05 keeps Ms within 1.36–1.47.
BOUND_MARGIN = 1.05
TD_RATIOS = (0.0, 0.1, 0.15, 0.2, 0.25)
DEFAULT_ND = 10.0


@dataclass(frozen=True)
class Design:
    """Gains with the model they were designed on and the Ms they give on it."""

    gains: Gains
    model: Process
    model_ms: float
    bound: Process | None


def fit_model(point: Point, static_gain: float) -> Process:
    """Three-parameter model through ``point`` with the given static gain (``inf``: integrating).

    Raises ValueError if the point does not lag by 90°–180° or the data are not finite.
    """
    w, r = point.omega, point.gain
    lag = -math.radians(point.phase_deg)
    if not (math.isfinite(w) and w > 0.0 and math.isfinite(r) and r > 0.0):
        raise ValueError(f"the point must have a positive finite frequency and gain, got ω={w}, |F|={r}")
    if not math.pi / 2 <= lag <= math.pi:
        raise ValueError(f"the point must lag by 90° to 180° for a PI(D) design, it lags by {math.degrees(lag):.1f}°")
    if math.isnan(static_gain) or static_gain <= 0.0:
        raise ValueError(
            f"the static gain must be positive (or inf for integrating), got {static_gain:.4g}: "
            "an unstable process, or a load change during the experiment"
        )
    if static_gain >= INTEGRATING_RATIO * r:
        kv = r * w
        return Process.from_tf((kv,), (1.0, 0.0), (lag - math.pi / 2) / w, text="IPDT model")
    if static_gain <= r:
        # No lag can explain a gain at ω* as large as the static gain: dead time only.
        return Process.from_tf((r,), (1.0,), lag / w, text="dead-time model")
    t = math.sqrt((static_gain / r) ** 2 - 1.0) / w
    return Process.from_tf((static_gain,), (t, 1.0), (lag - math.atan(w * t)) / w, text="FOPDT model")


def fit_lag_bound(point: Point, static_gain: float) -> Process | None:
    """The other extreme through the same data: two lags and no dead time (None if no lag can fit).

    With ``x = K0/r`` and the lag ``φ``, the lags ``a = ωT1``, ``b = ωT2`` satisfy
    ``a + b = x·sin φ`` and ``a·b = 1 + x·|cos φ|``; when they are not real the
    equal-lag model with the dead time that completes the phase is the bound.
    For an integrating process it is ``Kv/(s(Ts + 1))`` with ``atan(ωT) = φ − 90°``.
    """
    w, r = point.omega, point.gain
    lag = -math.radians(point.phase_deg)
    if static_gain >= INTEGRATING_RATIO * r:
        t = math.tan(lag - math.pi / 2) / w
        return Process.from_tf((r * w * math.hypot(1.0, w * t),), (t, 1.0, 0.0), 0.0, text="integrator + lag bound")
    x = static_gain / r
    if x <= 1.0:
        return None
    total, product = x * math.sin(lag), 1.0 + x * abs(math.cos(lag))
    disc = total * total - 4.0 * product
    if disc >= 0.0:
        return Process.from_tf((static_gain,), (product / w**2, total / w, 1.0), 0.0, text="two-lag bound")
    a = math.sqrt(x - 1.0)
    return Process.from_tf(
        (static_gain,), (a * a / w**2, 2.0 * a / w, 1.0), (lag - 2.0 * math.atan(a)) / w, text="equal-lag bound"
    )


def _plant(model: Process, margin: float = 1.0) -> Plant:
    return Plant(model.freqresp, integrators=model.integrator_count, rhp_poles=0, margin=margin)


def setpoint_weight(model: Process, k: float, ti: float, td: float, nd: float, w: np.ndarray) -> float:
    """Largest ``b`` in [0, 1] with ``|G_yr(jω)| ≤ 1`` on the model (no set-point overshoot peak).

    When even ``b = 0`` peaks above 1 (high integral gain on a lag-dominant
    process: the integral path alone overshoots), 0 is returned, which gives
    the lowest peak available from ``b``.
    """
    f = model.freqresp(w)
    loop = pid_frequency_response(w, k, ti, td, nd) * f
    s = 1j * w
    prop = k * f / (1.0 + loop)
    rest = (k / (ti * s)) * f / (1.0 + loop)
    lo, hi = 0.0, 1.0
    if np.max(np.abs(hi * prop + rest)) <= 1.0 + 1e-9:
        return 1.0
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        if np.max(np.abs(mid * prop + rest)) <= 1.0 + 1e-9:
            lo = mid
        else:
            hi = mid
    return math.floor(lo * 1000.0) / 1000.0  # rounding up could cross the limit


def design(point: Point, static_gain: float, controller: str = "PI", ms: float = 1.4, nd: float = DEFAULT_ND) -> Design:
    """Robust PI or PID gains (standard form) from the identified point and static gain.

    ``ms`` is the required maximum sensitivity (1.2–2.0 is the usual range).
    """
    if controller not in ("PI", "PID"):
        raise ValueError(f"controller must be PI or PID, got {controller!r}")
    if not 1.05 <= ms <= 4.0:
        raise ValueError(f"Ms must be between 1.05 and 4, got {ms}")
    model = fit_model(point, static_gain)
    bound = fit_lag_bound(point, static_gain)
    plants = [_plant(model)] + ([] if bound is None else [_plant(bound, BOUND_MARGIN)])
    w = log_grid(point.omega)
    ratios = TD_RATIOS if controller == "PID" else (0.0,)
    best = max((migo(plants, point.omega, ms, ratio, nd, w) for ratio in ratios), key=lambda m: m.ki)
    b = setpoint_weight(model, best.k, best.ti, best.td, nd, w)
    gains = Gains(k=best.k, ti=best.ti, td=best.td, nd=nd, b=b, c=0.0)
    loop = pid_frequency_response(w, best.k, best.ti, best.td, nd) * model.freqresp(w)
    return Design(gains=gains, model=model, model_ms=max_sensitivity(loop), bound=bound)
