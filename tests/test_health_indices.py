"""The loop-health indices, each against an analytic case or an independent computation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from autotuner.engine.health.oscillation import oscillation
from autotuner.engine.health.record import LoopRecord
from autotuner.engine.health.sensor import frozen_share
from autotuner.engine.health.signals import half_cycles, noise_std
from autotuner.engine.health.sluggish import sluggishness
from autotuner.engine.health.stiction import band, ccf_zero_lag, shape_index
from autotuner.engine.health.tracking import tracking
from autotuner.engine.health.usage import reversals, saturation, travel, utilization
from autotuner.engine.health.variability import delay_samples, harris_index

TS = 0.5


def sine(period: float, amplitude: float, n: int, phase: float = 0.0) -> np.ndarray:
    return amplitude * np.sin(2.0 * math.pi * np.arange(n) * TS / period - phase)


# -- the record ------------------------------------------------------------------------------------------------


def test_record_names_the_first_bad_sample() -> None:
    t = [0.0, 1.0, 2.0, 3.0]
    with pytest.raises(ValueError, match="pv is not a finite number at sample 2"):
        LoopRecord.of(t, [1] * 4, [1.0, 1.0, math.nan, 1.0], [0] * 4)
    with pytest.raises(ValueError, match="t does not increase at sample 2: 1 s after 1 s"):
        LoopRecord.of([0.0, 1.0, 1.0, 3.0], [1] * 4, [1] * 4, [0] * 4)
    with pytest.raises(ValueError, match="mv has 3 samples, t has 4"):
        LoopRecord.of(t, [1] * 4, [1] * 4, [0] * 3)


def test_window_resampling_and_the_longest_automatic_stretch() -> None:
    rec = LoopRecord.of([0.0, 1.0, 3.0, 4.0], [5.0, 5.0, 7.0, 7.0], [0.0, 2.0, 6.0, 8.0], [1.0, 1.0, 3.0, 3.0],
                        [True, False, True, True])
    assert list(rec.last(1.5).t) == [3.0, 4.0]
    even = rec.uniform(1.0)
    assert list(even.t) == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert list(even.pv) == [0.0, 2.0, 4.0, 6.0, 8.0]  # linear between 2 at 1 s and 6 at 3 s
    assert list(even.sp) == [5.0, 5.0, 5.0, 7.0, 7.0]  # the set point holds until it changes
    assert list(even.auto) == [True, False, False, True, True]
    stretch = even.longest_auto()
    assert stretch is not None and list(stretch.t) == [3.0, 4.0]


# -- noise and half-cycles ---------------------------------------------------------------------------------------


def test_noise_level_of_white_noise_on_a_slow_signal() -> None:
    rng = np.random.default_rng(1)
    x = sine(600.0, 5.0, 20000) + 0.3 * rng.standard_normal(20000)
    assert noise_std(x) == pytest.approx(0.3, rel=0.05)


def test_half_cycles_of_a_sinusoid() -> None:
    period, amplitude = 40.0, 2.0
    cycles = half_cycles(sine(period, amplitude, 2000), TS, 0.1)
    assert len(cycles) >= 45
    np.testing.assert_allclose(cycles.duration, period / 2, atol=TS)
    # ∫|A sin| over half a period = A·T/π
    np.testing.assert_allclose(cycles.iae, amplitude * period / math.pi, rtol=0.02)


# -- oscillation -------------------------------------------------------------------------------------------------


def test_a_pure_sinusoid_is_an_oscillation_of_its_period_and_amplitude() -> None:
    osc = oscillation(sine(42.0, 1.8, 7200), TS, a=0.5, tu=42.0, hysteresis=0.05)
    assert osc.period == pytest.approx(42.0, abs=TS)
    assert osc.amplitude == pytest.approx(1.8, rel=0.01)
    assert osc.regularity is not None and osc.regularity > 10.0
    assert osc.oscillating


def test_hagglund_counts_half_cycles_whose_iae_exceeds_that_of_a_sine_of_amplitude_a() -> None:
    e = sine(30.0, 1.0, 3600)  # at the ultimate period: IAE = A·Tu/π against a·Tu/π
    assert oscillation(e, TS, a=0.9, tu=30.0, hysteresis=0.05).detections >= 100
    assert oscillation(e, TS, a=1.1, tu=30.0, hysteresis=0.05).detections == 0
    assert not oscillation(e, TS, a=1.1, tu=30.0, hysteresis=0.05).oscillating


def test_white_noise_is_no_oscillation() -> None:
    e = np.random.default_rng(2).standard_normal(3600)
    osc = oscillation(e, TS, a=0.5, tu=30.0, hysteresis=3.0)
    assert not osc.oscillating


# -- sluggishness --------------------------------------------------------------------------------------------------


def _load_responses(u_sign: float, n: int = 400) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Five load steps of alternating sign, one at sample 20 of each 400-sample block: the PV jumps 1 away at
    once and recovers slowly; the MV moves ``u_sign`` × the recovery (+1: on and on the way the PV recovers,
    as a sluggish loop's; -1: back against it)."""
    k = np.arange(n)
    recovery = np.where(k >= 20, np.exp(-(k - 20) / 60.0), 0.0)
    signs = np.repeat([1.0, -1.0, 1.0, -1.0, 1.0], n)
    y = -signs * np.tile(recovery, 5)
    u = u_sign * signs * np.tile((1.0 - recovery) * (k >= 20), 5)
    return u, y, np.zeros(5 * n)


@pytest.mark.parametrize("u_sign", [1.0, -1.0])
def test_idle_index_counts_the_time_mv_and_pv_move_the_same_way(u_sign: float) -> None:
    u, y, sp = _load_responses(u_sign)
    cycles = half_cycles(sp - y, TS, 0.01)
    assert len(cycles) == 3  # the blocks between the first and the last crossing
    # the filtered error peaks at 0.44 (below): a disturbance beyond a = 0.3
    result = sluggishness(u, y, sp, cycles, np.ones(len(cycles), dtype=bool), a=0.3, sign=1, ts=TS)
    assert result.idle is not None and u_sign * result.idle > 0.6  # Ii → +1 sluggish, → -1 well tuned
    # The error e^(-k/60) through the first-order filter of a tenth of the 400-sample half-cycles, τf = 40:
    # 3·(e^(-k/60) − e^(-k/40)) in continuous time; the time it spends beyond a quarter of its peak.
    k = np.arange(0.0, 380.0, 0.01)
    filtered = 3.0 * (np.exp(-k / 60.0) - np.exp(-k / 40.0))
    beyond = k[filtered > 0.25 * filtered.max()]
    assert result.recovery == pytest.approx((beyond[-1] - beyond[0]) * TS, rel=0.15)


# -- stiction ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("phase_deg", [0.0, 60.0, 90.0, 150.0])
def test_horch_zero_lag_correlation_of_two_shifted_sines_is_cos_phi(phase_deg: float) -> None:
    u = sine(40.0, 1.0, 4000)
    y = sine(40.0, 2.0, 4000, math.radians(phase_deg))
    assert ccf_zero_lag(u, y, int(20.0 / TS)) == pytest.approx(abs(math.cos(math.radians(phase_deg))), abs=0.02)


def _triangle(period: float, amplitude: float, n: int) -> np.ndarray:
    phase = (np.arange(n) * TS / period) % 1.0
    return amplitude * (4.0 * np.abs(phase - 0.5) - 1.0)


def test_shape_index_tells_a_triangle_from_a_sine() -> None:
    tri, sin = _triangle(40.0, 2.0, 4000), sine(40.0, 2.0, 4000)
    assert shape_index(tri, half_cycles(tri, TS, 0.1)) > 0.9
    assert shape_index(sin, half_cycles(sin, TS, 0.1)) < 0.1


def test_band_is_the_mv_swing_per_pv_cycle() -> None:
    y = np.sign(sine(40.0, 1.0, 4000) + 1e-9)  # a square PV
    u = _triangle(40.0, 2.0, 4000)  # an MV swinging 4 peak to peak
    assert band(u, half_cycles(y, TS, 0.1), 1) == pytest.approx(4.0, abs=0.05)


# -- variability -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("phi, b", [(0.0, 3), (0.8, 1), (0.8, 4), (0.95, 10)])
def test_harris_index_of_an_ar1_error_is_one_minus_phi_to_the_2b(phi: float, b: int) -> None:
    rng = np.random.default_rng(3)
    a = rng.standard_normal(40000)
    e = np.empty_like(a)
    e[0] = a[0]
    for k in range(1, len(a)):
        e[k] = phi * e[k - 1] + a[k]
    # e = Σ φ^i a(k-i): σ²_mv/σ²_e = (1 - φ^(2b)) / (1 - φ²) · (1 - φ²)
    assert harris_index(e, b) == pytest.approx(1.0 - phi ** (2 * b), abs=0.03)


def test_dead_time_in_samples_counts_the_hold() -> None:
    assert delay_samples(0.7, 0.5) == 2
    assert delay_samples(1.0, 0.5) == 3
    assert delay_samples(None, 0.5) == 1


# -- tracking ----------------------------------------------------------------------------------------------------


def test_first_order_step_response_settles_in_tau_ln20_without_overshoot() -> None:
    n, k0, tau, step = 1000, 100, 10.0, 5.0
    t = (np.arange(n) - k0) * TS
    sp = np.where(t >= 0, step, 0.0)
    pv = np.where(t >= 0, step * (1.0 - np.exp(-np.maximum(t, 0.0) / tau)), 0.0)
    result = tracking(sp, pv, TS, noise=0.0, a=0.1, long_enough=0.0)
    assert result.steps == 1 and result.unsettled == 0
    assert result.overshoot == 0.0
    assert result.settling_time == pytest.approx(tau * math.log(20.0), abs=TS)


def test_second_order_overshoot_is_exp_of_minus_pi_zeta_over_sqrt() -> None:
    zeta, wn, step, n, k0 = 0.3, 0.5, 4.0, 2000, 100
    t = np.maximum((np.arange(n) - k0) * TS, 0.0)
    wd = wn * math.sqrt(1 - zeta ** 2)
    y = 1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta ** 2) * np.sin(wd * t))
    sp = np.where(np.arange(n) >= k0, step, 0.0)
    result = tracking(sp, step * y, TS, noise=0.0, a=0.1, long_enough=0.0)
    expected = 100.0 * math.exp(-math.pi * zeta / math.sqrt(1 - zeta ** 2))
    assert result.overshoot == pytest.approx(expected, abs=0.5)


def test_a_step_that_never_settles_is_counted() -> None:
    sp = np.where(np.arange(600) >= 10, 5.0, 0.0)
    pv = np.where(np.arange(600) >= 10, 2.0, 0.0)  # stuck short of the set point
    result = tracking(sp, pv, TS, noise=0.0, a=0.1, long_enough=0.0)
    assert result.unsettled == 1 and result.settling_time is None


# -- usage and the sensor ----------------------------------------------------------------------------------------


def test_utilization_saturation_travel_and_reversals() -> None:
    auto = np.array([True] * 75 + [False] * 25)
    assert utilization(auto) == 0.75
    mv = np.concatenate((np.full(30, 100.0), np.full(70, 50.0)))
    assert saturation(mv, auto, (0.0, 100.0)) == pytest.approx(30 / 75)
    tri = 10.0 + _triangle(40.0, 2.0, 800)  # 10 periods of 40 s in 400 s: 20 reversals, 8 units each
    hours = 400.0 / 3600.0
    assert travel(tri, hours) == pytest.approx(float(np.sum(np.abs(np.diff(tri)))) / hours)
    assert reversals(tri, 0.5, hours) == pytest.approx(19 / hours, abs=1.0 / hours)
    small = tri + 0.2 * np.random.default_rng(4).standard_normal(len(tri))
    assert reversals(small, 1.5, hours) == pytest.approx(19 / hours, abs=1.0 / hours)  # the deadzone hides noise


def test_frozen_share_is_the_longest_unchanged_run() -> None:
    pv = np.concatenate((np.random.default_rng(5).standard_normal(300), np.full(101, 3.0)))
    assert frozen_share(pv) == pytest.approx(100 / 400)
