"""The transient's share of a period's estimate, read off a model that went through the same record.

A period's estimate ``Y1/U1`` is exact only over a periodic cycle. Early in
the experiment the cycle is not periodic yet (the relay's start, the phase
filter's corrections, the PV's mean settling towards the bias's level), and
the process's memory of the periods before leaks into the window: 3–30 % off
in the first estimates of the batch's processes, where the stopping rule waits
periods for it to die out.

The first-order-plus-dead-time model through the estimate itself (its point
and ``|F|/K0``, methods.md §6) has a memory of the same length. Driven by the
MV as the process held it since the start, and estimated exactly as the
process was (same windows, same detrending), it makes the same kind of
error, while its own ``F(jω)`` is known exactly; that error is the bias taken
out: ``F̂ − (M̂ − M(jω))``. On a first-order process with dead time the model
is the process and the correction nearly exact (an estimate 5.5 % off becomes 0.02 %
off); on higher orders the model's memory is close, and the error falls 3–10
times. Once the cycle is periodic ``M̂ = M(jω)`` whatever the model: the
correction vanishes and the settled estimates are the measured ones.

A second model, two lags ``ALT_RATIO`` apart through the same point, remembers
as a higher-order process does; its estimates are judged beside the first-order
model's (estimates.alt_point, convergence.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from autotuner.engine.experiment.load_fit import MEMORY, first_order_model, lag_at, lag_states
from autotuner.engine.experiment.loop import Loop
from autotuner.engine.experiment.record import Samples


# The second model's lags: two through the same point and |F|/K0, the shorter ALT_RATIO times the longer. On the
# batch's higher orders (two lags and more, a lag and a lead) its estimates of the second and third periods are
# about twice as close as the first-order model's (sample medians 0.40 → 0.19 %, 0.28 → 0.12 %); on a first-order
# process it is the wrong model (0.27 % where the first-order one is exact), so the stopping rule judges both
# (convergence.py). Ratios 0.3, 0.5, 0.7, 0.9: batch medians 4.36, 4.15, 4.05, 4.05 periods (the last two with
# a worst PI Ms of 1.471 instead of 1.468).
ALT_RATIO = 0.5


def two_lags(x: float, gain: float, omega: float, lag: float,
             ratio: float) -> tuple[float, float, float, float] | None:
    """(K0, T1, T2, L) of ``K0·e^{−Ls}/((T1·s + 1)(T2·s + 1))`` with ``T2 = ratio·T1`` through the point ``gain``
    (|F|, PV per MV unit), ``lag`` (radians) at ``omega`` (rad/s) with ``|F|/K0 = x``: K0 in PV per MV unit, the
    rest in s; None where no such model has ``L ≥ 0`` (or ``x`` is not in (0, 1))."""
    if not 0.0 < x < 1.0 or ratio <= 0.0:
        return None
    # (1 + a²)(1 + r²a²) = 1/x² with a = ωT1: a quadratic in a².
    r2 = ratio * ratio
    b = 1.0 + r2
    a2 = (-b + math.sqrt(b * b - 4.0 * r2 * (1.0 - 1.0 / (x * x)))) / (2.0 * r2)
    if a2 <= 0.0:
        return None
    a = math.sqrt(a2)
    delay = (lag - math.atan(a) - math.atan(ratio * a)) / omega
    return None if delay < 0.0 else (gain / x, a / omega, ratio * a / omega, delay)


def model(x: float, value: complex, omega: float, ratio: float) -> tuple[float, float, float, float, float]:
    """(K0, T1, T2, L, rate) of the model through the point ``value`` (F at ``omega``, rad/s; PV per MV unit)
    with ``x`` = |F|/K0: two lags ``ratio`` apart (:func:`two_lags`) where there is such a model and ``ratio``
    > 0, else the first-order one (T2 = 0; an integrator ``rate`` = |F|·ω, PV per MV unit per s, for ``x`` ≤ 0).
    Times in s."""
    gain = abs(value)
    lag = (-math.atan2(value.imag, value.real)) % (2.0 * math.pi)
    two = two_lags(x, gain, omega, lag, ratio)
    if two is not None:
        k0, tc, tc2, delay = two
        return k0, tc, tc2, delay, gain * omega
    k0, tc, delay = first_order_model(max(x, 0.0), gain, omega, lag)
    return k0, tc, 0.0, delay, gain * omega


def model_output(history: Samples, times: np.ndarray, since: float, k0: float, tc: float, delay: float,
                 rate: float, tc2: float = 0.0) -> np.ndarray:
    """The model's output at ``times`` (s), as a deviation, for the MV deviations ``history.u`` held from
    ``history.s`` (s) on, from rest at ``since`` (s): gain ``k0`` (PV per MV unit), lags ``tc`` and ``tc2`` (0:
    first order) and dead time ``delay`` (s); with ``k0`` infinite an integrator of ``rate`` (PV per MV unit
    per s).

    Two lags are the difference of two first-order ones (partial fractions), each exact at any spacing of the
    samples. An integrator's output is the integral from ``since``: an offset, which no estimate sees (each
    removes the means).
    """
    first = max(int(np.searchsorted(history.s, since, side="right")) - 1, 0)
    s, u = history.s[first:] + delay, history.u[first:]
    if math.isfinite(k0):
        if tc2 > 0.0:
            slow = lag_at(s, u, lag_states(s, u, tc), tc, times)
            fast = lag_at(s, u, lag_states(s, u, tc2), tc2, times)
            return k0 / (tc - tc2) * (tc * slow - tc2 * fast)
        return k0 * lag_at(s, u, lag_states(s, u, tc), tc, times)
    # The held input's running integral at each hold, and the part of the interval a time falls in.
    area = np.concatenate(([0.0], np.cumsum(u[:-1] * np.diff(s))))
    i = np.searchsorted(s, times, side="right") - 1
    inside = i >= 0
    i = np.maximum(i, 0)
    return np.where(inside, rate * (area[i] + u[i] * (times - s[i])), 0.0)


def bias(loop: Loop, times: np.ndarray, measure: Callable[[np.ndarray], complex], bounds: list[float],
         value: complex, x: float, ratio: float = 0.0, load: np.ndarray | None = None) -> complex:
    """The transient's share of the estimate ``value`` (F over the last period of ``bounds``, crossing times,
    s; PV per MV unit) with ``x`` = |F|/K0 of the ``loop``: what the model through them (:func:`model`, two
    lags ``ratio`` apart or first order) reads when its output at the samples' ``times`` (s) goes through
    ``measure`` (the estimate as ``value`` was made, from a PV deviation), less its exact F(jω). ``load``: a
    fitted load at the process input at each of the record's holds (MV units), a second input to the model
    beside the MV (load_correction.py), or None.

    Zero for an open-loop unstable process (``x`` < 0 beyond ``static_tol``), whose model's run over the
    record would grow without bound; a slightly negative ``x`` is an integrator seen through noise.
    """
    if x < -loop.config.static_tol or value == 0.0:
        return 0j
    omega = 2.0 * math.pi / (bounds[-1] - bounds[-2])
    k0, tc, tc2, delay, rate = model(x, value, omega, ratio)
    # From rest: MEMORY time constants before the windows (an integrator: a period, any offset goes).
    since = bounds[0] - delay - (MEMORY * tc if math.isfinite(k0) else bounds[-1] - bounds[-2])
    history = loop.record.all()
    inputs = history.u - loop.mv0 if load is None else history.u - loop.mv0 + load
    output = model_output(replace(history, u=inputs), times, since, k0, tc, delay, rate, tc2)
    return measure(output) - model_response(k0, tc, delay, rate, omega, tc2)


def model_response(k0: float, tc: float, delay: float, rate: float, omega: float, tc2: float = 0.0) -> complex:
    """F(jω) at ``omega`` (rad/s) of the model with gain ``k0`` (PV per MV unit), lags ``tc`` and ``tc2`` (0:
    first order) and dead time ``delay`` (s); with ``k0`` infinite an integrator of ``rate`` (PV per MV unit
    per s)."""
    turn = complex(np.exp(-1j * omega * delay))
    first = k0 * turn / (1.0 + 1j * omega * tc) if math.isfinite(k0) else rate * turn / (1j * omega)
    return first / (1.0 + 1j * omega * tc2) if tc2 > 0.0 else first
