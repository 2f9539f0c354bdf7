"""The relay's limit cycle on a known linear process: the filter phase that puts it at a chosen frequency.

The loop's phase balance is not the describing function's ``π − lag − θ``:
the relay switches where the filtered error itself crosses the hysteresis,
not where its first harmonic does, and a lag-dominant process's triangular
PV moves that crossing by up to 7° of the period (the batch's settled cycles:
−4° on a dead time, +7° on a lag). A process model says by how much. With the
relay high over ``[0, D)`` of a period ``P = 2π/ω`` the MV's harmonics are
known in closed form, the filtered error is their sum through the filter,
the process and the switch's delay, and the cycle is periodic where that
error meets ``+h`` at ``0`` and ``−h`` at ``D``: two equations in the filter
phase and ``D``, solved by Newton's method (the process's response at the
harmonics is computed once).

Phases in radians (lag positive), frequencies in rad/s, times in s.
"""

from __future__ import annotations

import math

import numpy as np

from autotuner.engine.experiment.phase_filter import MAX_LAG, MAX_LEAD, PhaseFilter

# Harmonics summed: the error through a process with one lag falls as 1/n², so the error at a switch is within
# about 1/HARMONICS of its swing (0.1° of the period).
HARMONICS = 400
_STEPS = 12  # Newton steps (it converges in 3–5 from the describing function's guess)
_TOL = 1e-9  # of the equations, in the error's swing


def filter_response(theta: float, omega: float, w: np.ndarray) -> np.ndarray:
    """The phase filter's frequency response at ``w`` (rad/s) when its phase at ``omega`` is ``theta``."""
    f = PhaseFilter()
    f.set_phase(theta, omega)
    jw = 1j * w * f.tau
    return (1.0 + jw) / (1.0 + jw / 5.0) if f.lead else 1.0 / (1.0 + jw)


def _errors(theta: float, duty: float, omega: float, response: np.ndarray, k0: float, high: float, low: float,
            hysteresis: float, delay: float) -> np.ndarray:
    """The filtered error (PV units) less ``+h`` at the rising switch and ``−h`` at the falling one, the switch
    ``delay`` after the error's crossing, for the relay high over a share ``duty`` of the period."""
    n = np.arange(1, HARMONICS + 1)
    w = n * omega
    # u − ū = Σ c_n e^{jnωt} + conj: a rectangle of height high − low over [0, duty·P).
    c = (high - low) * (1.0 - np.exp(-2j * math.pi * n * duty)) / (2j * math.pi * n)
    h = c * response * filter_response(theta, omega, w) * np.exp(-1j * w * delay)
    mean = -k0 * (low + duty * (high - low))
    at_rise = mean - 2.0 * float(np.sum(h).real)
    at_fall = mean - 2.0 * float(np.sum(h * np.exp(2j * math.pi * n * duty)).real)
    return np.array([at_rise - hysteresis, at_fall + hysteresis])


def filter_phase(response: np.ndarray, omega: float, k0: float, high: float, low: float, hysteresis: float,
                 delay: float, guess: float) -> float | None:
    """The filter phase at ``omega`` that makes the relay's cycle periodic at ``omega``, or None where Newton's
    method finds none within the filter's range.

    ``response``: the process's F at ``omega``·1..HARMONICS (PV per MV unit, times the loop's sign), ``k0`` its
    static gain; ``high``, ``low``: the relay's levels less the MV of the operating point (MV units);
    ``hysteresis`` (PV units); ``delay``: the switch's lag behind the filtered error's crossing (s);
    ``guess``: the filter phase to start from.
    """
    # (The MV mean that holds the operating point on average is where the duty starts.)
    duty = min(max(-low / (high - low), 0.05), 0.95) if high > low else 0.5
    x = np.array([guess, duty])
    scale = abs(k0) * (high - low) + 1e-12
    for _ in range(_STEPS):
        f = _errors(x[0], x[1], omega, response, k0, high, low, hysteresis, delay)
        if float(np.max(np.abs(f))) < _TOL * scale:
            return float(x[0])
        jac = np.empty((2, 2))
        for i, d in enumerate((1e-6, 1e-7)):
            step = x.copy()
            step[i] += d
            jac[:, i] = (_errors(step[0], step[1], omega, response, k0, high, low, hysteresis, delay) - f) / d
        try:
            move = np.linalg.solve(jac, -f)
        except np.linalg.LinAlgError:
            return None
        # Newton's step, kept inside the filter's range and a period.
        x = x + move
        if not (-MAX_LEAD <= x[0] <= MAX_LAG and 0.0 < x[1] < 1.0):
            return None
    return None
