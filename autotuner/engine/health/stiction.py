"""Valve stiction in an oscillating loop: Horch's cross-correlation test, a shape test, and the band.

Horch (1999), "A simple method for detection of stiction in control valves", Control Engineering Practice
7(10):1221–1231: in a loop around a self-regulating process, a sticking valve makes the cross-correlation of
the controller output u and the process output y an odd function of the lag (zero at lag 0: the integral
action ramps u while the valve, stuck, holds y), while the loop's own oscillation through aggressive gains makes
it even (an extremum at lag 0: u and y in phase opposition). The index here is the correlation at lag 0
relative to its largest magnitude within half a period, ρ0 = |r_uy(0)| / max|r_uy(τ)|: 0 for an odd
function, 1 for an even one (for two sines shifted by φ, |cos φ|). A slow external sinusoid correlates
unevenly too (the integral action lags the PV by up to 90°): the shape test tells it apart.

He, Wang, Pottmann and Qin (2007), "A curve fitting method for detecting valve stiction in oscillating control
loops", Ind. Eng. Chem. Res. 46:4549–4560: around an integrating process a sticking valve (steps of the valve
position) makes the PV a triangular wave, an aggressive loop a sinusoidal one; around a self-regulating
process a sticking valve's PV is no sine either (square-ish or triangular), an external sinusoid's is. Each
half-cycle of the PV is fitted with a half sine and with a triangle (its peak anywhere); the stiction index
SI = MSE_sine / (MSE_sine + MSE_triangle) is above 0.5 when the triangle fits better. How the verdict combines
the two tests: :func:`autotuner.engine.health.verdict.is_stiction`.

The band: for the valve to move after a reversal the controller output must travel the valve's deadband plus
stickband S, so in a stiction limit cycle the MV swings at least S per cycle (Choudhury, Shah and Thornhill
(2008), "Diagnosis of process nonlinearities and valve stiction", Springer, read the apparent stiction off the
PV–MV plot the same way). The estimate is the median over the PV's cycles of the MV's peak-to-peak within each,
the MV smoothed first over a twentieth of the period so its noise does not add. It is an upper estimate: the
output also runs on while the process answers the slip.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from autotuner.engine.health.signals import HalfCycles, half_cycles

HORCH_EVEN = 0.93  # ρ0 from this on: even (MV and PV within 22° of phase opposition), the loop's own oscillation
SHAPE_TRIANGLE = 0.65  # SI above this: triangular, a sticking valve's around an integrating process
SHAPE_SINE = 0.35  # SI up to this: sinusoidal, an external disturbance's or the loop's own oscillation
_PEAKS = np.linspace(0.1, 0.9, 17)  # where a fitted triangle may peak, share of the half-cycle
_GRID = 32  # points each half-cycle is put on for the fits
MAX_CYCLES = 100  # the latest this many (half-)cycles tell the shape and the band as well as all of them


@dataclass(frozen=True)
class Stiction:
    """The stiction tests of an oscillating loop.

    ``ccf_zero_lag``: Horch's ρ0 (0 odd … 1 even; None: no period to look within). ``shape``: the shape index
    SI of the PV's half-cycles (None: too few). ``band``: the MV's median swing per PV cycle, an estimate of the
    valve's S, MV units (None: no cycle to measure it on).
    """

    ccf_zero_lag: float | None
    shape: float | None
    band: float | None


def ccf_zero_lag(u: np.ndarray, y: np.ndarray, half_period: int) -> float | None:
    """Horch's ρ0 = |r_uy(0)| / max over |τ| ≤ ``half_period`` samples of |r_uy(τ)| (None: flat signals).

    ``u``: the controller output; ``y``: the PV (samples of one record).
    """
    u, y = u - u.mean(), y - y.mean()
    if not (np.any(u) and np.any(y)) or half_period < 1:
        return None
    n = len(u)
    size = 1 << (2 * n - 1).bit_length()
    r = np.fft.irfft(np.fft.rfft(y, size) * np.conj(np.fft.rfft(u, size)), size)  # r[τ] = Σ u[k] y[k+τ]
    lags = np.concatenate((r[: half_period + 1], r[-half_period:]))
    return float(abs(r[0]) / np.max(np.abs(lags)))


def shape_index(y: np.ndarray, cycles: HalfCycles) -> float | None:
    """He et al.'s SI over the half-cycles of ``y`` (its mean removed) that ``cycles`` delimits: each half-cycle
    of at least 8 samples, put on a grid of 32 points, fitted with the best half sine and the best triangle
    (amplitude and peak fitted); SI from the summed mean squared errors over the latest 100 (None: fewer than
    two half-cycles)."""
    keep = np.flatnonzero((cycles.end - cycles.start) >= 8)[-MAX_CYCLES:]
    if len(keep) < 2:
        return None
    s = (np.arange(_GRID) + 0.5) / _GRID
    rows = np.stack([np.interp(s, (np.arange(b - a) + 0.5) / (b - a), y[a:b])
                     for a, b in zip(cycles.start[keep], cycles.end[keep])])
    sine = np.sin(np.pi * s)
    mse_sine = np.mean((rows - np.outer(rows @ sine / (sine @ sine), sine)) ** 2, axis=1)
    tri = np.minimum(s[None, :] / _PEAKS[:, None], (1.0 - s[None, :]) / (1.0 - _PEAKS[:, None]))  # peak × grid
    amp = (rows @ tri.T) / np.sum(tri * tri, axis=1)  # half-cycle × peak
    residual = rows[:, None, :] - amp[:, :, None] * tri[None, :, :]
    mse_tri = np.min(np.mean(residual ** 2, axis=2), axis=1)
    total_sine, total_tri = float(np.sum(mse_sine)), float(np.sum(mse_tri))
    return total_sine / (total_sine + total_tri) if total_sine + total_tri > 0.0 else None


def band(u: np.ndarray, cycles: HalfCycles, smooth: int) -> float | None:
    """The median over the latest 100 cycles delimited by ``cycles`` (the PV's) of the peak-to-peak of ``u`` (MV
    units), ``u`` first averaged over ``smooth`` samples (None: no complete cycle)."""
    if len(cycles) < 2:
        return None
    width = max(1, smooth)
    smoothed = np.convolve(u, np.ones(width) / width, mode="same")
    starts = cycles.start[::2][-MAX_CYCLES:]
    swings = [np.ptp(smoothed[a:b]) for a, b in zip(starts[:-1], starts[1:]) if b > a]
    return float(np.median(swings)) if swings else None


def stiction(u: np.ndarray, y: np.ndarray, ts: float, period: float | None, hysteresis: float) -> Stiction:
    """The stiction tests on the controller output ``u`` (MV units) and the PV ``y`` (PV units) sampled every
    ``ts`` seconds, of a loop oscillating with ``period`` seconds (None: unknown); ``hysteresis``: PV units the
    PV must pass beyond its mean to cross it (noise)."""
    centred = y - y.mean()
    cycles = half_cycles(centred, ts, hysteresis)
    if period is None:
        return Stiction(None, shape_index(centred, cycles), None)
    return Stiction(ccf_zero_lag(u, y, int(round(0.5 * period / ts))), shape_index(centred, cycles),
                    band(u, cycles, int(round(period / ts / 20.0))))
