"""PID unit (PIDU semantics): each law checked against an independent computation."""

import math
import random

import pytest

from autotuner.engine.control.gains import Gains
from autotuner.engine.control.pid import PidUnit


def times(h, n, t0=0.0):
    return [t0 + i * h for i in range(n)]


# -- the terms ------------------------------------------------------------


def test_p_only_steady_output_with_weight_and_feedforward():
    u = PidUnit(Gains(k=2.0), kind="P")
    for t in times(0.1, 20):
        assert u.step(t, sp=5.0, pv=3.0) == pytest.approx(4.0)
    u = PidUnit(Gains(k=2.0, b=0.5), kind="P")
    for t in times(0.1, 5):
        assert u.step(t, sp=5.0, pv=3.0, dv=0.3) == pytest.approx(2.0 * (2.5 - 3.0) + 0.3)


def test_pi_integral_ramp_rate_is_k_over_ti_times_error():
    k, ti, e = 2.0, 4.0, 1.5
    u = PidUnit(Gains(k=k, ti=ti), kind="PI")
    ts = times(0.1, 101)
    for t in ts:
        mv = u.step(t, sp=e, pv=0.0)
        assert mv == pytest.approx(k * e + k / ti * e * t, rel=1e-12)
    # 10 s of constant error → integral k/ti·e·10
    assert u.integral == pytest.approx(k / ti * e * 10.0)


def test_integral_is_tustin_exact_for_a_linear_error():
    # I controller, error e(t) = t: ∫ = t²/2. Trapezoid is exact; Euler is not.
    k, ti, h = 3.0, 2.0, 0.25
    u = PidUnit(Gains(k=k, ti=ti), kind="I")
    for t in times(h, 41):
        mv = u.step(t, sp=t, pv=0.0)
        assert mv == pytest.approx(k / ti * t * t / 2.0, abs=1e-12)
    # the forward-Euler result would be off by k/ti·h·t/2 = 1.875 at t = 10
    assert abs(mv - k / ti * (10.0**2 / 2 - h * 10.0 / 2)) > 1.0


def test_i_only_ignores_proportional_and_set_point_weight():
    u = PidUnit(Gains(k=2.0, ti=4.0, b=0.3, td=1.0), kind="I")
    assert u.step(0.0, sp=1.0, pv=0.0) == 0.0
    assert u.step(1.0, sp=1.0, pv=0.0) == pytest.approx(0.5)


def test_derivative_of_pv_ramp_settles_to_minus_k_td_slope():
    k, td, nd, slope = 2.0, 1.5, 10.0, 0.4
    u = PidUnit(Gains(k=k, td=td, nd=nd), kind="PD")
    for t in times(0.05, 400):
        pv = slope * t
        mv = u.step(t, sp=0.0, pv=pv)
    d_term = mv - k * (0.0 - pv)
    assert d_term == pytest.approx(-k * td * slope, rel=1e-9)


def test_derivative_filter_step_response_backward_difference():
    k, td, nd, h, dpv = 2.0, 1.0, 5.0, 0.05, 1.0
    tf = td / nd
    u = PidUnit(Gains(k=k, td=td, nd=nd), kind="PD")
    for t in times(h, 10):
        u.step(t, sp=0.0, pv=0.0)
    t0 = 10 * h
    for j in range(30):
        mv = u.step(t0 + j * h, sp=0.0, pv=dpv)
        # independent backward-difference filter: y0 = −Δ/(Tf+h), y_j = y0·(Tf/(Tf+h))^j
        y = -dpv / (tf + h) * (tf / (tf + h)) ** j
        assert mv == pytest.approx(-k * dpv + k * td * y, rel=1e-12, abs=1e-12)


def test_derivative_filter_time_constant_is_td_over_nd():
    # with a tiny step the discrete filter approaches −K·N·Δ·exp(−t/Tf)
    k, td, nd, h = 1.0, 2.0, 8.0, 1e-4
    tf = td / nd
    u = PidUnit(Gains(k=k, td=td, nd=nd), kind="PD")
    u.step(0.0, 0.0, 0.0)
    n = int(round(3 * tf / h))
    samples = {}
    for j in range(1, n + 1):
        samples[j] = u.step(j * h, 0.0, 1.0) + k * 1.0
    for j in (1, n // 3, 2 * n // 3, n):
        t = (j - 1) * h
        assert samples[j] == pytest.approx(-k * nd * math.exp(-t / tf), rel=2e-3)


def test_set_point_weights_b_and_c():
    k, td, nd, h, dsp = 2.0, 1.0, 10.0, 0.1, 1.0
    tf = td / nd
    for b, c in ((1.0, 0.0), (0.3, 0.0), (0.3, 0.5), (0.0, 1.0)):
        u = PidUnit(Gains(k=k, td=td, nd=nd, b=b, c=c), kind="PD")
        before = u.step(0.0, sp=0.0, pv=0.0)
        after = u.step(h, sp=dsp, pv=0.0)
        expected = k * b * dsp + k * td * c * dsp / (tf + h)
        assert after - before == pytest.approx(expected, rel=1e-12), (b, c)


def test_integral_acts_on_true_error_whatever_b():
    u = PidUnit(Gains(k=1.0, ti=2.0, b=0.0), kind="PI")
    u.step(0.0, sp=1.0, pv=0.0)
    assert u.step(1.0, sp=1.0, pv=0.0) == pytest.approx(0.5)  # P part is k·(0·1 − 0) = 0


def test_reverse_action_flips_the_law_not_the_feedforward():
    g = Gains(k=1.5, ti=3.0, td=0.4, b=0.8, c=0.2)
    fwd, rev = PidUnit(g), PidUnit(g, reverse=True)
    rng = random.Random(1)
    for t in times(0.1, 50):
        sp, pv, dv = rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1)
        a = fwd.step(t, sp, pv, dv=dv)
        r = rev.step(t, sp, pv, dv=dv)
        assert r - dv == pytest.approx(-(a - dv), rel=1e-12, abs=1e-12)


# -- limits, anti-windup, tracking ---------------------------------------


def test_output_limits_and_flags():
    u = PidUnit(Gains(k=10.0), kind="P", lolim=-1.0, hilim=1.0)
    assert u.step(0.0, sp=0.5, pv=0.0) == 1.0
    assert (u.hl, u.ll, u.sat) == (True, False, True)
    assert u.step(0.1, sp=-0.5, pv=0.0) == -1.0
    assert (u.hl, u.ll, u.sat) == (False, True, True)
    assert u.step(0.2, sp=0.05, pv=0.0) == pytest.approx(0.5)
    assert (u.hl, u.ll, u.sat) == (False, False, False)
    assert u.de == pytest.approx(0.05)
    assert u.dmv == pytest.approx(1.5)


def _time_to_leave_high_limit(tt):
    u = PidUnit(Gains(k=1.0, ti=10.0), kind="PI", lolim=0.0, hilim=1.0, tt=tt)
    h = 0.1
    for t in times(h, 1001):  # 100 s with error +1: saturated at 1
        assert u.step(t, sp=1.0, pv=0.0) == 1.0
    t = 100.0
    while t < 300.0:
        t += h
        if u.step(t, sp=1.0, pv=2.0) < 1.0:  # error now −1
            return t - 100.0
    return math.inf


def test_anti_windup_leaves_limit_promptly_compared_with_no_tracking():
    with_tracking = _time_to_leave_high_limit(tt=None)  # default ti/2 = 5 s
    without = _time_to_leave_high_limit(tt=1e12)
    assert with_tracking <= 0.1 + 1e-9  # first sample after the sign change
    # without tracking the integral wound up to ≈ 10 and drains at 0.1/s
    assert without > 70.0


def test_tracking_steady_offset_in_saturation():
    # In saturation the unlimited output settles where integration and tracking
    # balance: δ = (k/ti·e·h)/(1 − exp(−h/tt)) ≈ tt·k·e/ti above the limit.
    k, ti, tt, h, e = 1.0, 10.0, 2.0, 0.1, 1.0
    u = PidUnit(Gains(k=k, ti=ti), kind="PI", hilim=1.0, tt=tt)
    for t in times(h, 2000):
        u.step(t, sp=e, pv=0.0)
    v = u.integral + k * e
    assert v - 1.0 == pytest.approx(k / ti * e * h / (1 - math.exp(-h / tt)), rel=1e-9)
    assert v - 1.0 == pytest.approx(tt * k * e / ti, rel=0.03)


def test_tracking_input_converges_with_time_constant_tt():
    tt, target = 2.0, 3.0
    u = PidUnit(Gains(k=1.0, ti=5.0), kind="PI", tt=tt)
    u.reset(0.0, sp=0.0, pv=0.0)
    rng = random.Random(7)
    t, t0 = 0.0, 0.0
    assert u.step(t, 0.0, 0.0, tv=target) == 0.0
    for _ in range(60):
        t += rng.uniform(0.01, 0.3)  # variable sample time
        mv = u.step(t, 0.0, 0.0, tv=target)
        assert mv == pytest.approx(target * (1 - math.exp(-(t - t0) / tt)), rel=1e-12)


def test_default_tracking_time_constants():
    assert PidUnit(Gains(k=1.0, ti=8.0), kind="PI").tt_effective == 4.0
    assert PidUnit(Gains(k=1.0, ti=8.0, td=2.0)).tt_effective == 4.0  # sqrt(16)
    assert PidUnit(Gains(k=1.0, ti=9.0, td=1.0)).tt_effective == 3.0
    assert PidUnit(Gains(k=1.0, ti=9.0, td=1.0), kind="PI").tt_effective == 4.5
    assert PidUnit(Gains(k=1.0, ti=9.0), tt=0.7).tt_effective == 0.7


# -- manual mode, reset, bumpless changes ----------------------------------


def test_manual_copies_hv_limited_and_return_to_auto_is_bumpless():
    k, ti, h = 2.0, 4.0, 0.1
    u = PidUnit(Gains(k=k, ti=ti), kind="PI", lolim=0.0, hilim=10.0)
    t = 0.0
    for t in times(h, 30):
        u.step(t, sp=2.0, pv=1.0)  # wind the integral somewhere
    t += h
    assert u.step(t, sp=2.0, pv=1.0, man=True, hv=12.0) == 10.0
    assert u.hl
    t += h
    assert u.step(t, sp=2.0, pv=1.0, man=True, hv=4.0) == 4.0
    assert not u.sat
    t += h
    # back to auto: only the integral increment over one sample, k/ti·e·h
    assert u.step(t, sp=2.0, pv=1.0) - 4.0 == pytest.approx(k / ti * 1.0 * h, rel=1e-12)


def test_manual_to_auto_with_sp_equal_pv_has_no_jump():
    u = PidUnit(Gains(k=3.0, ti=2.0, td=0.5), kind="PID")
    for t in times(0.1, 20):
        u.step(t, sp=1.0, pv=0.2)
    # PV moves to the set point while in manual; the derivative transient of
    # that move decays (Tf = 0.05 s) before the switch back
    for t in times(0.1, 30, t0=2.0):
        assert u.step(t, sp=1.0, pv=1.0, man=True, hv=7.5) == 7.5
    assert u.step(5.0, sp=1.0, pv=1.0) == pytest.approx(7.5, abs=1e-12)


def test_p_unit_manual_to_auto_is_bumpless_through_its_bias():
    u = PidUnit(Gains(k=2.0), kind="P")
    u.step(0.0, sp=1.0, pv=0.0, man=True, hv=5.0)
    assert u.step(0.1, sp=1.0, pv=0.0) == pytest.approx(5.0)
    assert u.step(0.2, sp=1.0, pv=0.5) == pytest.approx(4.0)  # then plain P action
    # no integrator: the tracking input does not move the bias
    assert u.step(0.3, sp=1.0, pv=0.5, tv=-3.0) == pytest.approx(4.0)


def test_manual_needs_hv():
    u = PidUnit(Gains(k=1.0, ti=1.0))
    with pytest.raises(ValueError, match="hv"):
        u.step(0.0, 0.0, 0.0, man=True)


def test_reset_gives_the_requested_next_output():
    u = PidUnit(Gains(k=2.0, ti=3.0, td=0.5, b=0.5), lolim=-5.0, hilim=5.0)
    for t in times(0.1, 10):
        u.step(t, sp=3.0, pv=-1.0)
    u.reset(2.5, sp=1.0, pv=0.5, dv=0.2)
    assert u.step(10.0, sp=1.0, pv=0.5, dv=0.2) == pytest.approx(2.5)
    u.reset(9.0, sp=1.0, pv=0.5)
    assert u.step(11.0, sp=1.0, pv=0.5) == pytest.approx(5.0)  # limited


def test_gain_change_is_bumpless():
    u = PidUnit(Gains(k=1.0, ti=5.0, td=1.0, b=0.5, c=0.3), kind="PID")
    t = 0.0
    for t in times(0.1, 50):
        u.step(t, sp=2.0, pv=0.05 * t)  # error and derivative both non-zero
    before = u.mv
    new = Gains(k=4.0, ti=2.0, td=0.2, nd=5.0, b=1.0, c=0.0)
    # what the law alone would jump by (P term only, at the last sample)
    assert abs((new.k - 1.0) * (2.0 - 0.05 * t)) > 1.0
    u.gains = new
    after = u.step(t + 1e-9, sp=2.0, pv=0.05 * t)
    assert after == pytest.approx(before, abs=1e-6)
    # and the new gains are in force afterwards: integral rate k/ti·e
    e = 2.0 - 0.05 * t
    m1 = u.step(t + 1.0, sp=2.0, pv=0.05 * t)
    m2 = u.step(t + 2.0, sp=2.0, pv=0.05 * t)
    assert m2 - m1 == pytest.approx(new.k / new.ti * e, rel=1e-3)


def test_kind_and_reverse_change_are_bumpless():
    u = PidUnit(Gains(k=2.0, ti=5.0), kind="PI")
    for t in times(0.1, 20):
        u.step(t, sp=1.0, pv=0.0)
    before = u.mv
    u.kind = "I"
    assert u.step(1.9 + 1e-9, 1.0, 0.0) == pytest.approx(before, abs=1e-6)
    u.reverse = True
    assert u.step(1.9 + 2e-9, 1.0, 0.0) == pytest.approx(before, abs=1e-6)


def test_invalid_reconfiguration_is_refused_and_changes_nothing():
    u = PidUnit(Gains(k=2.0, ti=5.0), kind="PI")
    u.step(0.0, 1.0, 0.0)
    with pytest.raises(ValueError, match="kind"):
        u.kind = "PIDX"
    with pytest.raises(ValueError, match="kind 'I' needs a finite ti"):
        PidUnit(Gains(k=1.0), kind="I")
    with pytest.raises(ValueError, match="gains"):
        u.gains = {"pk": 1.0}
    assert u.kind == "PI" and u.gains == Gains(k=2.0, ti=5.0)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"lolim": 1.0, "hilim": 0.0}, "lolim"),
        ({"lolim": math.nan}, "lolim"),
        ({"tt": 0.0}, "tt"),
        ({"tt": math.inf}, "tt"),
        ({"reverse": 1}, "reverse"),
    ],
)
def test_invalid_config(kwargs, name):
    with pytest.raises(ValueError, match=name):
        PidUnit(Gains(k=1.0, ti=1.0), **kwargs)


# -- closed loop and timing ----------------------------------------------


def _closed_loop(ts_fn, b=1.0, t_end=80.0):
    """PI on y' = (−y + K0·u)/T, Euler with a tiny step, controller sampled at ts_fn()."""
    k0, tau, dt, sp = 2.0, 5.0, 1e-3, 1.5
    u = PidUnit(Gains(k=1.0, ti=tau, b=b), kind="PI", lolim=-10.0, hilim=10.0)
    y, t, next_sample, mv = 0.0, 0.0, 0.0, 0.0
    while t < t_end:
        if t >= next_sample - 1e-12:
            mv = u.step(t, sp, y)
            next_sample = t + ts_fn()
        y += dt * (-y + k0 * mv) / tau
        t += dt
    return y, sp


def test_closed_loop_pi_reaches_set_point():
    y, sp = _closed_loop(lambda: 0.1)
    assert y == pytest.approx(sp, abs=1e-6)


def test_closed_loop_pi_with_b0_and_variable_sample_time():
    rng = random.Random(3)
    y, sp = _closed_loop(lambda: rng.uniform(0.05, 0.3), b=0.0, t_end=120.0)
    assert y == pytest.approx(sp, abs=1e-5)


def test_variable_dt_integral_and_derivative():
    k, ti, td, e, slope = 2.0, 4.0, 1.0, 0.5, 0.3
    rng = random.Random(11)
    ts, t = [], 0.0
    for _ in range(300):
        ts.append(t)
        t += rng.uniform(0.01, 0.5)
    pi = PidUnit(Gains(k=k, ti=ti), kind="PI")
    for t in ts:
        assert pi.step(t, sp=e, pv=0.0) == pytest.approx(k * e + k / ti * e * t, rel=1e-12)
    pd = PidUnit(Gains(k=k, td=td), kind="PD")
    for t in ts:
        mv = pd.step(t, sp=0.0, pv=slope * t)
    assert mv - k * (-slope * ts[-1]) == pytest.approx(-k * td * slope, rel=1e-9)


# -- input errors ---------------------------------------------------------


@pytest.mark.parametrize("name", ["t", "sp", "pv", "dv", "tv", "hv"])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_inputs_raise_naming_the_input(name, bad):
    u = PidUnit(Gains(k=1.0, ti=1.0))
    args = {"t": 0.0, "sp": 0.0, "pv": 0.0}
    kwargs = {"man": True, "hv": 0.0} if name == "hv" else {}
    if name in args:
        args[name] = bad
    else:
        kwargs[name] = bad
    with pytest.raises(ValueError, match=rf"^{name} must be finite"):
        u.step(args["t"], args["sp"], args["pv"], **kwargs)


def test_time_must_increase():
    u = PidUnit(Gains(k=1.0, ti=1.0))
    u.step(1.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="t must increase"):
        u.step(1.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="t must increase"):
        u.step(0.5, 0.0, 0.0)
