"""Fourier coefficients of measured loop signals over a time window.

The process input (MV) is held between samples, so its coefficient is
integrated exactly for a piecewise-constant signal: treating it as a sampled
signal would add the hold's half-sample delay to the identified phase. The
process output (PV) is a continuous signal seen at the sample instants; it is
integrated with the trapezoidal rule (linear interpolation at the window ends).

The window ``[ta, tb]`` (seconds) may start and end between samples, so that it
can span exactly whole periods of a limit cycle whose period is not a
multiple of the sample time. A Hann window further reduces the leakage of
whatever is not periodic (transients, noise).

Coefficients are normalised so that ``A·cos(ω(t − ta) + φ)`` over whole
periods gives ``A·e^{jφ}``, and ``omega = 0`` gives the (weighted) mean.

Each function reads only the samples that reach into its window (found by
bisection): its work is the window's, however long the record it is given.
"""

from __future__ import annotations

import numpy as np

_RECT = ((1.0, 0),)
_HANN = ((0.5, 0), (-0.25, 1), (-0.25, -1))


def _primitive(tau: np.ndarray, omega: float, width: float, hann: bool) -> np.ndarray:
    """``∫_0^tau w(σ)·e^{−jωσ} dσ`` for the window ``w`` of length ``width`` (seconds)."""
    big = 2.0 * np.pi / width
    out = np.zeros(np.shape(tau), dtype=complex)
    for coef, harmonic in _HANN if hann else _RECT:
        nu = harmonic * big - omega
        if abs(nu) * width < 1e-12:
            out += coef * tau
        else:
            out += coef * (np.exp(1j * nu * tau) - 1.0) / (1j * nu)
    return out


def _normalise(integral: complex, omega: float, width: float, hann: bool) -> complex:
    total = 0.5 * width if hann else width
    return (1.0 if omega == 0.0 else 2.0) * integral / total


def held_coefficient(t: np.ndarray, u: np.ndarray, ta: float, tb: float, omega: float, hann: bool = True) -> complex:
    """Coefficient at ``omega`` (rad/s) over [``ta``, ``tb``] (s) of the held signal ``u``, Hann-windowed if
    ``hann``.

    ``u[i]`` holds over ``[t[i], t[i+1])`` (the last value until ``tb``); ``t``
    in seconds, increasing, with ``t[0] ≤ ta < tb``.
    """
    width = tb - ta
    # The samples from the last one at or before ta to the last one before tb: the others hold outside.
    first = max(int(np.searchsorted(t[: len(u)], ta, side="right")) - 1, 0)
    end = int(np.searchsorted(t[: len(u)], tb, side="left"))
    t, u = t[first:end], u[first:end]
    edges = np.clip(np.append(t, np.inf), ta, tb) - ta
    edges[-1] = width
    integral = np.dot(u, np.diff(_primitive(edges, omega, width, hann)))
    return _normalise(integral, omega, width, hann)


def sampled_coefficient(t: np.ndarray, y: np.ndarray, ta: float, tb: float, omega: float, hann: bool = True) -> complex:
    """Coefficient at ``omega`` (rad/s) over [``ta``, ``tb``] (s) of the continuous signal sampled as ``y`` at
    ``t``, Hann-windowed if ``hann``."""
    width = tb - ta
    # The samples inside the window and the one on each side of it (the interpolation at its ends).
    first = max(int(np.searchsorted(t, ta, side="right")) - 1, 0)
    end = int(np.searchsorted(t, tb, side="left")) + 1
    t, y = t[first:end], y[first:end]
    inside = (t > ta) & (t < tb)
    tau = np.concatenate(([0.0], t[inside] - ta, [width]))
    values = np.concatenate(([np.interp(ta, t, y)], y[inside], [np.interp(tb, t, y)]))
    weight = np.ones_like(tau) if not hann else 0.5 - 0.5 * np.cos(2.0 * np.pi * tau / width)
    f = weight * values * np.exp(-1j * omega * tau)
    integral = np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(tau))
    return _normalise(integral, omega, width, hann)
