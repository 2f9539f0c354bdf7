"""Fourier coefficients of held and sampled signals, checked against closed forms.

Normalisation under test: ``A·cos(ω(t − ta) + φ)`` over whole periods gives
``A·e^{jφ}``; ``omega = 0`` gives the (weighted) mean. The rectangular window
weighs 1, the Hann window ``w(τ) = ½ − ½cos(2πτ/W)`` with ``∫w = W/2``.
"""

import cmath
import math

import numpy as np
import pytest
from scipy.integrate import quad

from autotuner.engine.experiment.fourier import held_coefficient, sampled_coefficient


# --------------------------------------------------------------------------- helpers (independent of the module)


def _window(tau: float, width: float, hann: bool) -> float:
    return 0.5 - 0.5 * math.cos(2.0 * math.pi * tau / width) if hann else 1.0


def _int_exp(mu: float, width: float) -> complex:
    """``∫_0^W e^{−jμτ} dτ`` in closed form."""
    if mu == 0.0:
        return complex(width)
    return (1.0 - cmath.exp(-1j * mu * width)) / (1j * mu)


def _windowed_exp(mu: float, width: float, hann: bool) -> complex:
    """``∫_0^W w(τ)·e^{−jμτ} dτ`` in closed form (Hann = ½ − ¼e^{jβτ} − ¼e^{−jβτ})."""
    if not hann:
        return _int_exp(mu, width)
    beta = 2.0 * math.pi / width
    return 0.5 * _int_exp(mu, width) - 0.25 * _int_exp(mu - beta, width) - 0.25 * _int_exp(mu + beta, width)


def _norm(omega: float, width: float, hann: bool) -> float:
    return (1.0 if omega == 0.0 else 2.0) / (0.5 * width if hann else width)


def _quad_held(t, u, ta, tb, omega, hann):
    """Same coefficient by adaptive quadrature of the piecewise-constant signal, piece by piece."""
    width = tb - ta
    edges = list(t[: len(u)]) + [math.inf]
    total = 0.0 + 0.0j
    for i, value in enumerate(u):
        a, b = max(edges[i], ta), min(edges[i + 1], tb)
        if b <= a:
            continue
        re = quad(lambda x: _window(x - ta, width, hann) * math.cos(omega * (x - ta)), a, b, epsabs=1e-14, epsrel=1e-13)[0]
        im = quad(lambda x: -_window(x - ta, width, hann) * math.sin(omega * (x - ta)), a, b, epsabs=1e-14, epsrel=1e-13)[0]
        total += value * complex(re, im)
    return _norm(omega, width, hann) * total


def _square_wave_grid(period, duty, t0, h, t_end, jitter=0.0, rng=None):
    """Sample instants on a clock of period ``h`` (optionally jittered) plus the exact switch instants.

    The signal is high on ``[t0 + nP, t0 + nP + duty·P)`` and low elsewhere; the
    switch instants fall between clock ticks.
    """
    clock = np.arange(0.0, t_end, h)
    if jitter:
        clock = clock + rng.uniform(-jitter, jitter, clock.size) * h
        clock[0] = 0.0
    n = np.arange(-1, int(t_end / period) + 2)
    switches = np.concatenate((t0 + n * period, t0 + (n + duty) * period))
    switches = switches[(switches > 0.0) & (switches < t_end)]
    t = np.unique(np.concatenate((clock, switches)))
    # Decide high/low from the middle of each hold interval (robust to rounding at a switch).
    mid = np.append(0.5 * (t[1:] + t[:-1]), t[-1] + 0.5 * h)
    high = np.mod(mid - t0, period) < duty * period
    return t, high


def _square_coefficient(k, period, duty, t0, ta, hi, lo):
    """Exact normalised coefficient of the k-th harmonic (k ≥ 1) of the pulse train, phase referred to ``ta``."""
    w = k * 2.0 * math.pi / period
    # 2/P ∫_{t0}^{t0+dP} (hi − lo) e^{−jw(t−ta)} dt (the constant lo has no harmonic content)
    return 2.0 * (hi - lo) / period * (cmath.exp(-1j * w * (t0 - ta)) - cmath.exp(-1j * w * (t0 + duty * period - ta))) / (1j * w)


# --------------------------------------------------------------------------- held signal


@pytest.mark.parametrize("hann", [False, True])
@pytest.mark.parametrize("duty", [0.5, 0.3])
@pytest.mark.parametrize("jitter", [0.0, 0.3])
def test_held_square_wave_matches_its_fourier_series(hann, duty, jitter):
    # Period 7.3 s on a 0.25 s clock: neither the switches nor the window ends fall on a tick.
    period, h, t0 = 7.3, 0.25, 0.913
    hi, lo = 2.0, -0.7
    rng = np.random.default_rng(7)
    t, high = _square_wave_grid(period, duty, t0, h, 60.0, jitter, rng)
    u = np.where(high, hi, lo)
    ta = 10.123
    assert np.all(np.abs(t - ta) > 1e-3)  # the window starts between samples
    for n_periods in (2, 3):
        tb = ta + n_periods * period
        for k in (1, 2, 3, 5):
            got = held_coefficient(t, u, ta, tb, k * 2.0 * math.pi / period, hann)
            want = _square_coefficient(k, period, duty, t0, ta, hi, lo)
            assert abs(got - want) < 1e-9, (n_periods, k, got, want)
        mean = held_coefficient(t, u, ta, tb, 0.0, hann)
        assert abs(mean - (lo + duty * (hi - lo))) < 1e-9


def test_held_symmetric_square_wave_fundamental_is_4_over_pi():
    # sign(cos(ω(t − t0))) = (4/π)(cos x − cos 3x / 3 + cos 5x / 5 − …), x = ω(t − t0)
    period, t0, amp = 5.0, 1.7, 1.5
    t, high = _square_wave_grid(period, 0.5, t0 - period / 4.0, 0.3, 40.0)
    u = np.where(high, amp, -amp)
    ta, w = 6.05, 2.0 * math.pi / period
    tb = ta + 2 * period
    phi = -w * (t0 - ta)
    for hann in (False, True):
        c1 = held_coefficient(t, u, ta, tb, w, hann)
        c3 = held_coefficient(t, u, ta, tb, 3 * w, hann)
        c2 = held_coefficient(t, u, ta, tb, 2 * w, hann)
        assert abs(c1 - 4 * amp / math.pi * cmath.exp(1j * phi)) < 1e-9
        assert abs(c3 + 4 * amp / (3 * math.pi) * cmath.exp(3j * phi)) < 1e-9
        assert abs(c2) < 1e-9  # even harmonics vanish for a 50 % duty cycle


@pytest.mark.parametrize("hann", [False, True])
@pytest.mark.parametrize("omega", [0.0, 0.37, 2.9])
def test_held_arbitrary_signal_matches_quadrature(hann, omega):
    # Random jittered instants, random held values, window starting and ending mid-interval,
    # last value held beyond the last sample up to tb.
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.05, 0.4, 40))
    u = rng.normal(size=t.size)
    ta = 0.5 * (t[2] + t[3]) + 0.01
    tb = t[-1] + 0.37
    got = held_coefficient(t, u, ta, tb, omega, hann)
    want = _quad_held(t, u, ta, tb, omega, hann)
    assert abs(got - want) < 1e-10 * max(1.0, abs(want))


@pytest.mark.parametrize("hann", [False, True])
def test_held_constant_gives_constant_mean_and_no_harmonic_over_whole_periods(hann):
    t = np.linspace(0.0, 10.0, 41)
    u = np.full(t.size, 3.25)
    ta, tb = 0.11, 9.61  # not on the 0.25 s grid
    assert abs(held_coefficient(t, u, ta, tb, 0.0, hann) - 3.25) < 1e-12
    # Two whole periods of the analysis frequency: a constant has no content there.
    w = 2.0 * 2.0 * math.pi / (tb - ta)
    assert abs(held_coefficient(t, u, ta, tb, w, hann)) < 1e-12


def test_held_weighted_mean_of_step():
    # u = a on the first quarter of the window, b after. Rectangular mean: a/4 + 3b/4.
    # Hann weight of the first quarter: (W/8 − W/(4π)) / (W/2) = 1/4 − 1/(2π).
    a, b = 5.0, -1.0
    ta, tb = 0.3, 8.3
    t = np.array([0.0, ta + 0.25 * (tb - ta)])
    u = np.array([a, b])
    assert abs(held_coefficient(t, u, ta, tb, 0.0, False) - (0.25 * a + 0.75 * b)) < 1e-12
    f = 0.25 - 1.0 / (2.0 * math.pi)
    assert abs(held_coefficient(t, u, ta, tb, 0.0, True) - (f * a + (1.0 - f) * b)) < 1e-12


# --------------------------------------------------------------------------- sampled signal


def _trapezoid_bound(h, width, hann, omega, g0, g1, g2, y2):
    """Error bound of the composite (non-uniform) trapezoidal rule for ``f = w(τ)·g(τ)``.

    ``|E| ≤ W·h²/12 · max|f''|`` times the normalisation, where ``g = y·e^{−jωτ}`` has
    ``|g| ≤ g0``, ``|g'| ≤ g1``, ``|g''| ≤ g2``, and the Hann window ``|w'| ≤ π/W``,
    ``|w''| ≤ 2π²/W²``. The linear interpolation at each window end is off by at
    most ``h²·max|y''|/8`` and enters with a weight ≤ h/2.
    """
    if hann:
        f2 = 2 * math.pi**2 / width**2 * g0 + 2 * math.pi / width * g1 + g2
    else:
        f2 = g2
    return _norm(omega, width, hann) * (width * h * h / 12.0 * f2 + 2 * (h / 2.0) * (h * h * y2 / 8.0))


def _cos_bound(h, width, hann, omega, w0, amp, offset=0.0):
    """Trapezoid bound for ``y = A cos(w0·τ + φ) + D`` analysed at ``omega``.

    ``|y| ≤ A + |D|``, ``|y'| ≤ A·w0``, ``|y''| ≤ A·w0²``; ``g = y·e^{−jωτ}`` gives
    ``|g'| ≤ |y'| + ω|y|`` and ``|g''| ≤ |y''| + 2ω|y'| + ω²|y|``.
    """
    y0, y1, y2 = amp + abs(offset), amp * w0, amp * w0**2
    return _trapezoid_bound(h, width, hann, omega, y0, y1 + omega * y0, y2 + 2 * omega * y1 + omega**2 * y0, y2)


@pytest.mark.parametrize("hann", [False, True])
@pytest.mark.parametrize("jitter", [0.0, 0.4])
def test_sampled_sinusoid_with_unaligned_window(hann, jitter):
    amp, phi, period = 1.7, 0.6, 6.1
    w = 2.0 * math.pi / period
    h = 0.05
    rng = np.random.default_rng(11)
    t = np.arange(0.0, 40.0, h)
    t = t + jitter * h * rng.uniform(-0.5, 0.5, t.size)
    ta = 3.0333
    assert np.min(np.abs(t - ta)) > 1e-3
    for n_periods in (2, 3, 4):
        tb = ta + n_periods * period
        y = amp * np.cos(w * (t - ta) + phi) - 0.4  # with an offset, which whole periods reject
        got = sampled_coefficient(t, y, ta, tb, w, hann)
        want = amp * cmath.exp(1j * phi)
        hmax = float(np.max(np.diff(t)))
        bound = _cos_bound(hmax, tb - ta, hann, w, w, amp, -0.4)
        err = abs(got - want)
        assert err < bound, (n_periods, err, bound)
        # A half-sample timing error would be first order, ≈ A·ω·h/2: far above what is allowed.
        assert bound < 0.3 * amp * w * hmax / 2.0
        mean = sampled_coefficient(t, y, ta, tb, 0.0, hann)
        assert abs(mean - (-0.4)) < _cos_bound(hmax, tb - ta, hann, 0.0, w, amp, -0.4)


def test_sampled_error_is_second_order_in_the_sample_time():
    amp, phi, w = 1.0, -1.1, 0.9
    ta = 0.777
    tb = ta + 2.5 * 2 * math.pi / w  # not whole periods, so the error does not cancel
    want_rect = amp * (cmath.exp(1j * phi) + cmath.exp(-1j * phi) * _int_exp(2 * w, tb - ta) / (tb - ta))
    errors = []
    for h in (0.2, 0.1, 0.05, 0.025):
        t = np.arange(0.0, 30.0, h)
        y = amp * np.cos(w * (t - ta) + phi)
        errors.append(abs(sampled_coefficient(t, y, ta, tb, w, False) - want_rect))
        assert errors[-1] < _cos_bound(h, tb - ta, False, w, w, amp)
    # Halving h divides the error by about 4 (more where the window ends happen to fall
    # better on the grid); a first-order (timing) error would only halve it.
    for coarse, fine in zip(errors, errors[1:]):
        assert fine < coarse / 3.0


@pytest.mark.parametrize("hann", [False, True])
def test_sampled_linear_ramp_mean_is_exact_with_jitter(hann):
    # The trapezoid rule with linear end interpolation is exact for a linear signal (rectangular window).
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.05, 0.3, 200))
    y = 2.0 - 0.3 * t
    ta, tb = t[10] + 0.013, t[150] - 0.021
    got = sampled_coefficient(t, y, ta, tb, 0.0, hann)
    if not hann:
        assert abs(got - (2.0 - 0.3 * 0.5 * (ta + tb))) < 1e-12
    else:
        # The Hann window is symmetric about the window centre, so its weighted mean of a ramp
        # is also the centre value; the trapezoid rule is then only second-order accurate.
        hmax = float(np.max(np.diff(t)))
        bound = _trapezoid_bound(hmax, tb - ta, True, 0.0, float(np.abs(y).max()), 0.3, 0.0, 0.0)
        assert abs(got - (2.0 - 0.3 * 0.5 * (ta + tb))) < bound


def test_sampled_window_on_sample_instants_equals_plain_trapezoid():
    t = np.linspace(0.0, 10.0, 101)
    y = np.sin(1.3 * t) + 0.2 * t**2
    w = 0.8
    ta, tb = t[7], t[93]
    sel = slice(7, 94)
    tau = t[sel] - ta
    f = y[sel] * np.exp(-1j * w * tau)
    want = 2.0 / (tb - ta) * np.trapezoid(f, tau) if hasattr(np, "trapezoid") else 2.0 / (tb - ta) * np.trapz(f, tau)
    assert abs(sampled_coefficient(t, y, ta, tb, w, False) - want) < 1e-12


# --------------------------------------------------------------------------- Hann against rectangular leakage


def test_hann_reduces_leakage_of_an_offset_when_window_is_not_whole_periods():
    # A constant D held over a window of 2.25 periods leaks into the fundamental:
    # rect: 2D/W·∫e^{−jωτ}; Hann: 4D/W·∫w·e^{−jωτ} (closed forms above).
    period, d = 4.0, 1.0
    w = 2.0 * math.pi / period
    t = np.arange(0.0, 20.0, 0.2)
    u = np.full(t.size, d)
    ta = 1.05
    tb = ta + 2.25 * period
    rect = held_coefficient(t, u, ta, tb, w, False)
    hann = held_coefficient(t, u, ta, tb, w, True)
    want_rect = d * _norm(w, tb - ta, False) * _windowed_exp(w, tb - ta, False)
    want_hann = d * _norm(w, tb - ta, True) * _windowed_exp(w, tb - ta, True)
    assert abs(rect - want_rect) < 1e-12
    assert abs(hann - want_hann) < 1e-12
    # |rect| = 2√2/(4.5π) ≈ 0.200. The offset sits only 2.25 bins from ω, where the
    # Hann sidelobes have not decayed much: ≈ 0.049, still four times less.
    assert abs(abs(rect) - 2 * math.sqrt(2) / (4.5 * math.pi)) < 1e-12
    assert abs(hann) < abs(rect) / 4.0


def test_hann_reduces_leakage_of_the_mirror_frequency():
    # A·cos(ωτ+φ) over 2.25 periods: the estimate is A·e^{jφ} plus the leakage of the
    # e^{−j(ωτ+φ)} component from −ω: rect 2/(9π)·A ≈ 0.0707 A, Hann ≈ 0.0037 A.
    amp, phi, period = 1.0, 0.4, 3.0
    w = 2.0 * math.pi / period
    h = 0.002
    t = np.arange(0.0, 12.0, h)
    ta = 0.5003
    tb = ta + 2.25 * period
    y = amp * np.cos(w * (t - ta) + phi)
    results = {}
    for hann in (False, True):
        got = sampled_coefficient(t, y, ta, tb, w, hann)
        leak = amp * cmath.exp(-1j * phi) * _norm(w, tb - ta, hann) / 2.0 * _windowed_exp(2 * w, tb - ta, hann)
        want = amp * cmath.exp(1j * phi) + leak
        assert abs(got - want) < _cos_bound(h, tb - ta, hann, w, w, amp)
        results[hann] = abs(got - amp * cmath.exp(1j * phi))
    assert abs(results[False] - 2.0 / (9.0 * math.pi)) < 1e-4
    # Hann: (2/π)|1/9 − 1/14 − 1/22| ≈ 0.00367
    assert abs(results[True] - 2.0 / math.pi * abs(1 / 9 - 1 / 14 - 1 / 22)) < 1e-4
    assert results[True] < results[False] / 15.0
