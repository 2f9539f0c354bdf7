"""MCU, SAT, SWU, SELU blocks: each documented behaviour against a hand computation."""

import math
import random

import pytest

from autotuner.engine.control.blocks import ManualControlUnit, SaturationUnit, SelectorUnit, SwitchUnit
from autotuner.engine.control.gains import Gains
from autotuner.engine.control.pid import PidUnit
from autotuner.engine.plant.process import Process
from autotuner.engine.plant.simulation import PlantSim


def times(h, n, t0=0.0):
    return [t0 + i * h for i in range(n)]


# -- MCU ------------------------------------------------------------------

# tm = 10, q = 2, ta = 1, tf = 3: rate 0.1 on [0,1), 0.2 on [1,2), 0.4 on [2,3),
# 0.8 from 3 s on (multiplications at 1, 2 and 3 s, the one at tf included).
# Ramp distance R(τ) by hand:
RAMP = [
    (0.5, 0.05),
    (1.0, 0.1),
    (1.5, 0.1 + 0.5 * 0.2),
    (2.5, 0.1 + 0.2 + 0.5 * 0.4),
    (3.0, 0.7),
    (5.0, 0.7 + 2.0 * 0.8),
]


def mcu(**kw):
    params = dict(tm=10.0, q=2.0, ta=1.0, tf=3.0, tt=1.0)
    params.update(kw)
    return ManualControlUnit(**params)


@pytest.mark.parametrize("tau, dist", RAMP)
def test_mcu_ramp_distance_is_piecewise_linear_with_accelerating_rate(tau, dist):
    assert mcu().ramp_distance(tau) == pytest.approx(dist, rel=1e-12)


def test_mcu_rate_steps_and_final_rate():
    m = mcu()
    assert [m.rate(x) for x in (0.0, 0.99, 1.0, 2.5, 3.0, 100.0)] == pytest.approx(
        [0.1, 0.1, 0.2, 0.4, 0.8, 0.8]
    )
    # tf not a multiple of ta: multiplications at 1 and 2 s only
    m = mcu(tf=2.5)
    assert m.rate(2.7) == pytest.approx(0.4) and m.rate(50.0) == pytest.approx(0.4)
    # tf < ta: constant rate 1/tm
    assert mcu(tf=0.5).rate(10.0) == pytest.approx(0.1)
    # REX defaults: 0.01 → 0.05 at 4 s → 0.25 at 8 s
    d = ManualControlUnit()
    assert [d.rate(x) for x in (1.0, 5.0, 9.0)] == pytest.approx([0.01, 0.05, 0.25])


def test_mcu_holding_up_follows_the_analytic_ramp():
    h = 0.1
    m = mcu(y0=1.0)
    m.step(0.0)
    m.step(h)  # idle
    # UP first seen at t = 0.2: it has acted over (0.1, 0.2], so the press counts from 0.1
    got = {}
    for t in times(h, 60, t0=0.2):
        got[round(t - 0.1, 9)] = m.step(t, up=True)
    for tau, dist in RAMP:
        assert got[tau] == pytest.approx(1.0 + dist, rel=1e-12)


def test_mcu_dn_ramps_down_and_direction_change_restarts_acceleration():
    h = 0.25
    m = mcu(y0=0.0)
    m.step(0.0)
    for t in times(h, 10, t0=h):  # DN over (0, 2.5]
        y = m.step(t, dn=True)
    assert y == pytest.approx(-(0.1 + 0.2 + 0.5 * 0.4))
    for t in times(h, 2, t0=2.5 + h):  # UP over (2.5, 3.0]: back at the base rate
        y = m.step(t, up=True)
    assert y == pytest.approx(-0.5 + 0.05)


def test_mcu_release_resets_the_acceleration():
    m = mcu()
    m.step(0.0)
    for t in times(0.5, 6, t0=0.5):  # UP over (0, 3]
        m.step(t, up=True)
    assert m.y == pytest.approx(0.7)
    m.step(3.5)  # idle (no tv: holds)
    assert m.y == pytest.approx(0.7)
    m.step(4.0, up=True)  # new press: base rate again
    assert m.y == pytest.approx(0.75)


def test_mcu_both_buttons_cancel_and_hold():
    m = mcu(y0=2.0)
    m.step(0.0)
    for t in times(0.1, 10, t0=0.1):
        assert m.step(t, up=True, dn=True, tv=-5.0) == 2.0


def test_mcu_limits_clip_the_ramp_without_windup():
    m = mcu(lolim=-0.2, hilim=0.5)
    m.step(0.0)
    for t in times(0.5, 10, t0=0.5):  # UP over (0, 5]: R(5) = 2.3, clipped
        y = m.step(t, up=True)
        assert y == pytest.approx(min(0.5, mcu().ramp_distance(t)))
    assert y == 0.5
    # DN moves away from the limit at once (the state is the limited value)
    assert m.step(5.5, dn=True) == pytest.approx(0.5 - 0.05)
    for t in times(0.5, 20, t0=6.0):
        y = m.step(t, dn=True)
    assert y == -0.2
    # y0 outside the limits is limited
    assert mcu(y0=3.0, hilim=1.0).y == 1.0


def test_mcu_tracks_tv_when_idle_exactly_on_any_grid():
    tt, tv, y0 = 2.0, 3.0, -1.0
    rng = random.Random(3)
    m = mcu(tt=tt, y0=y0)
    t = 0.0
    m.step(t, tv=tv)
    assert m.y == y0  # no interval elapsed yet
    for _ in range(50):
        t += rng.uniform(0.01, 0.4)
        y = m.step(t, tv=tv)
        assert y == pytest.approx(tv + (y0 - tv) * math.exp(-t / tt), rel=1e-12)


def test_mcu_without_tv_holds_and_tt_zero_copies():
    m = mcu(y0=4.0)
    m.step(0.0)
    assert m.step(1.0) == 4.0
    m = mcu(tt=0.0, y0=4.0, hilim=5.0)
    m.step(0.0)
    assert m.step(0.1, tv=2.5) == 2.5
    assert m.step(0.2, tv=7.0) == 5.0  # tracked value limited too


def test_mcu_tracking_is_ignored_while_a_button_is_held():
    m = mcu(tt=0.0)
    m.step(0.0)
    assert m.step(0.5, up=True, tv=10.0) == pytest.approx(0.05)


def test_mcu_remote_passes_rv_through_limited_and_return_is_bumpless():
    m = mcu(hilim=2.0)
    m.step(0.0)
    assert m.step(0.1, rem=True, rv=1.5, up=True, tv=-3.0) == 1.5
    assert m.step(0.2, rem=True, rv=2.5) == 2.0
    assert m.step(0.3, rem=True, rv=1.2) == 1.2
    # back to local: continues from the last remote value
    assert m.step(0.4) == 1.2
    assert m.step(0.9, up=True) == pytest.approx(1.2 + 0.05)


def test_mcu_variable_sample_time_gives_the_same_ramp():
    rng = random.Random(7)
    m = mcu(y0=0.0)
    t = 0.0
    m.step(t)
    t_prev = t
    t += 0.05
    y = m.step(t, up=True)  # press counts from t_prev
    press = t_prev
    assert y == pytest.approx(mcu().ramp_distance(t - press))
    while t < 6.0:
        t += rng.uniform(0.001, 0.35)
        y = m.step(t, up=True)
        assert y == pytest.approx(mcu().ramp_distance(t - press), rel=1e-12)


def test_mcu_press_at_the_first_sample_starts_the_clock_there():
    m = mcu()
    assert m.step(2.0, up=True) == 0.0
    assert m.step(3.5, up=True) == pytest.approx(0.1 + 0.5 * 0.2)


@pytest.mark.parametrize(
    "kw, name",
    [
        (dict(tm=0.0), "tm"),
        (dict(tm=-1.0), "tm"),
        (dict(ta=0.0), "ta"),
        (dict(ta=-2.0), "ta"),
        (dict(tf=-1.0), "tf"),
        (dict(tt=-0.5), "tt"),
        (dict(q=0.0), "q"),
        (dict(q=math.inf), "q"),
        (dict(y0=math.nan), "y0"),
        (dict(lolim=1.0, hilim=0.0), "lolim"),
    ],
)
def test_mcu_invalid_parameters_name_the_parameter(kw, name):
    with pytest.raises(ValueError, match=name):
        mcu(**kw)


def test_mcu_parameter_assignment_is_validated_and_inputs_checked():
    m = mcu()
    with pytest.raises(ValueError, match="ta"):
        m.ta = -1.0
    assert m.ta == 1.0
    m.tm = 5.0
    assert m.rate(0.0) == pytest.approx(0.2)
    m.step(1.0)
    with pytest.raises(ValueError, match="t must increase"):
        m.step(1.0)
    with pytest.raises(ValueError, match="rv"):
        m.step(2.0, rem=True)
    with pytest.raises(ValueError, match="up"):
        m.step(2.0, up=2)
    with pytest.raises(ValueError, match="tv"):
        m.step(2.0, tv=math.nan)


# -- SAT ------------------------------------------------------------------


def test_sat_fixed_limits_and_flags():
    s = SaturationUnit(lolim=-1.0, hilim=2.0)
    for t, u, y, hl, ll in [
        (0.0, 0.5, 0.5, False, False),
        (0.1, 3.0, 2.0, True, False),
        (0.2, 2.0, 2.0, False, False),  # at the limit, not beyond: not held
        (0.3, -4.0, -1.0, False, True),
    ]:
        out = s.step(t, u)
        assert (out.y, out.hl, out.ll) == (y, hl, ll)
        assert (out.lo, out.hi) == (-1.0, 2.0)


def test_sat_input_limits_override_the_fixed_ones():
    s = SaturationUnit(lolim=-1.0, hilim=1.0)
    out = s.step(0.0, 5.0, hi=3.0)
    assert (out.y, out.hl) == (3.0, True)
    out = s.step(0.1, -5.0, lo=-4.0, hi=3.0)
    assert (out.y, out.ll) == (-4.0, True)
    out = s.step(0.2, 0.5, lo=0.7)  # hi unconnected → hilim
    assert (out.y, out.ll, out.hi) == (0.7, True, 1.0)


def test_sat_limit_moves_are_rate_limited_analytically():
    # tp = 2 s/unit → rises at most 0.5 units/s; tn = 4 s/unit → falls at most 0.25 units/s
    h = 0.1
    s = SaturationUnit(lolim=-10.0, hilim=1.0, tp=2.0, tn=4.0)
    for t in times(h, 5):  # up to t = 0.4 at the fixed limit
        assert s.step(t, 100.0).hi == 1.0
    # hi steps 1 → 3, first seen at t = 0.5: it acts over (0.4, 0.5], ramp from 0.4
    for t in times(h, 60, t0=0.5):
        out = s.step(t, 100.0, hi=3.0)
        assert out.hi == pytest.approx(min(3.0, 1.0 + 0.5 * (t - 0.4)), abs=1e-12)
        assert out.y == out.hi and out.hl
    assert out.hi == 3.0  # reached after 4 s, then stays
    # hi falls 3 → 2 from t_last: 0.25 units/s, i.e. 4 s
    t0 = t
    for t in times(h, 50, t0=t0 + h):
        out = s.step(t, 100.0, hi=2.0)
        assert out.hi == pytest.approx(max(2.0, 3.0 - 0.25 * (t - t0)), abs=1e-12)
    assert out.hi == 2.0
    # the output itself is not rate limited while within the limits
    assert s.step(t + h, -3.0, hi=2.0).y == -3.0


def test_sat_low_limit_rate_limited_with_variable_sample_time():
    rng = random.Random(11)
    s = SaturationUnit(lolim=0.0, hilim=10.0, tp=0.5)  # rise ≤ 2 units/s
    t = 0.0
    s.step(t, -1.0)
    t_start = t
    while t < 3.0:
        t += rng.uniform(0.01, 0.3)
        out = s.step(t, -1.0, lo=5.0)
        assert out.lo == pytest.approx(min(5.0, 2.0 * (t - t_start)), abs=1e-12)
        assert out.y == out.lo and out.ll and not out.hl


def test_sat_zero_times_mean_instant_limits_and_infinite_limits_jump():
    s = SaturationUnit(lolim=-1.0, hilim=1.0)
    s.step(0.0, 0.0)
    assert s.step(0.1, 9.0, hi=5.0).y == 5.0
    s = SaturationUnit(lolim=-math.inf, hilim=math.inf, tp=10.0, tn=10.0)
    assert s.step(0.0, 7.0).y == 7.0
    out = s.step(0.1, 7.0, hi=2.0)  # from +inf: cannot ramp, takes the target
    assert (out.y, out.hl) == (2.0, True)
    # removing the limit again widens it at the maximum rate (0.1 units/s)
    assert s.step(1.1, 7.0).y == pytest.approx(2.1)


@pytest.mark.parametrize(
    "kw, name",
    [
        (dict(lolim=2.0, hilim=1.0), "lolim"),
        (dict(tp=-1.0), "tp"),
        (dict(tn=-0.1), "tn"),
        (dict(tp=math.inf), "tp"),
        (dict(hilim=math.nan), "hilim"),
    ],
)
def test_sat_invalid_parameters_name_the_parameter(kw, name):
    with pytest.raises(ValueError, match=name):
        SaturationUnit(**kw)


def test_sat_crossed_input_limits_raise():
    s = SaturationUnit(lolim=-1.0, hilim=1.0)
    with pytest.raises(ValueError, match="lo must be <= hi"):
        s.step(0.0, 0.0, lo=2.0, hi=1.5)
    with pytest.raises(ValueError, match="lo must be <= hilim"):
        s.step(0.0, 0.0, lo=2.0)
    with pytest.raises(ValueError, match="hilim"):
        s.hilim = -5.0


# -- SWU ------------------------------------------------------------------


@pytest.mark.parametrize("which", ["or1", "or2", "or3", "or4"])
def test_swu_any_or_input_selects_uo(which):
    s = SwitchUnit()
    assert s.step(0.0, 1.0, 2.0) == 1.0 and not s.sw
    assert s.step(0.1, 1.0, 2.0, **{which: True}) == 2.0 and s.sw
    assert s.step(0.2, 1.0, 2.0, **{which: False}) == 1.0


def test_swu_several_or_inputs_and_validation():
    s = SwitchUnit()
    assert s.step(0.0, 1.0, 2.0, or1=True, or4=1) == 2.0
    with pytest.raises(ValueError, match="or3"):
        s.step(0.0, 1.0, 2.0, or3=0.5)
    with pytest.raises(ValueError, match="uo"):
        s.step(0.0, 1.0, math.inf)


# -- SELU -----------------------------------------------------------------


@pytest.mark.parametrize("isel", [1, 2, 3, 4])
def test_selu_selects_by_integer_and_tells_the_others_to_track(isel):
    u = (10.0, 20.0, 30.0, 40.0)
    out = SelectorUnit().step(0.0, *u, isel=isel)
    assert out.y == u[isel - 1] and out.isel == isel
    assert out.track == tuple(i != isel for i in range(1, 5))
    assert out.tv == tuple(None if i == isel else u[isel - 1] for i in range(1, 5))


@pytest.mark.parametrize(
    "sl1, sl2, isel", [(False, False, 1), (True, False, 2), (False, True, 3), (True, True, 4)]
)
def test_selu_selects_by_binary_inputs(sl1, sl2, isel):
    out = SelectorUnit(binary=True).step(0.0, 1.0, 2.0, 3.0, 4.0, sl1=sl1, sl2=sl2)
    assert out.isel == isel and out.y == float(isel)


@pytest.mark.parametrize("isel", [0, 5, -1])
def test_selu_isel_out_of_range(isel):
    with pytest.raises(ValueError, match="isel"):
        SelectorUnit().step(0.0, 1.0, 2.0, isel=isel)


def test_selu_invalid_use():
    s = SelectorUnit()
    with pytest.raises(ValueError, match="isel"):
        s.step(0.0, 1.0, 2.0, isel=True)
    with pytest.raises(ValueError, match="isel"):
        s.step(0.0, 1.0, 2.0, isel=2.0)
    with pytest.raises(ValueError, match="isel"):
        s.step(0.0, 1.0, 2.0)  # integer mode needs isel
    with pytest.raises(ValueError, match="u3"):
        s.step(0.0, 1.0, 2.0, isel=3)  # u3 unconnected
    with pytest.raises(ValueError, match="isel"):
        SelectorUnit(binary=True).step(0.0, 1.0, 2.0, isel=1)
    with pytest.raises(ValueError, match="binary"):
        SelectorUnit(binary=1)
    with pytest.raises(ValueError, match="u2"):
        s.step(0.0, 1.0, math.nan, isel=1)
    # unconnected inputs are fine while not selected
    assert s.step(0.0, 1.0, None, isel=1).y == 1.0


# -- selector loop: bumpless switching through tracking -------------------

TS = 0.1
T_SWITCH = 60.0
K_B, TI_B, SP_A, SP_B = 1.0, 5.0, 1.0, 1.5


def selector_loop(track: bool, tt: float = TS):
    """Two PIs on 1/(10 s + 1)·e^{−s}; SELU picks A until T_SWITCH, then B.

    With ``track`` the SELU tracking values of the previous sample (a sampled
    loop cannot use this sample's) feed the PIs' tv; otherwise tv = None.
    Returns (mv, pv) lists.
    """
    plant = PlantSim(Process.from_tf([1.0], [10.0, 1.0], 1.0), TS)
    a = PidUnit(Gains(k=2.0, ti=8.0), kind="PI", tt=tt)
    b = PidUnit(Gains(k=K_B, ti=TI_B), kind="PI", tt=tt)
    sel = SelectorUnit()
    out = None
    mvs, pvs = [], []
    for k in range(1200):
        t = k * TS
        pv = plant.measure()
        tv = out.tv if (track and out is not None) else (None, None, None, None)
        ua = a.step(t, SP_A, pv, tv=tv[0])
        ub = b.step(t, SP_B, pv, tv=tv[1])
        out = sel.step(t, ua, ub, isel=1 if t < T_SWITCH else 2)
        mvs.append(out.y)
        pvs.append(pv)
        plant.advance(out.y)
    return mvs, pvs


def test_selector_switch_is_bumpless_when_the_inactive_pi_tracks():
    i = round(T_SWITCH / TS)  # first sample with B selected
    mv, pv = selector_loop(track=True)
    jump = abs(mv[i] - mv[i - 1])
    after = max(abs(mv[j + 1] - mv[j]) for j in range(i, i + 50))
    # A had settled: PV at its set point, MV steady
    assert pv[i - 1] == pytest.approx(SP_A, abs=1e-3)
    assert max(abs(mv[j + 1] - mv[j]) for j in range(i - 50, i - 1)) < 1e-4
    # The jump is B's tracking gap: each sample B integrates (k/ti)·e·h and the
    # tracking removes a fraction 1 − e^{−h/tt} of the gap, so the gap settles at
    # (k/ti)·e·h / (1 − e^{−h/tt}) — about 1.6 normal per-sample changes for tt = h.
    gap = K_B / TI_B * (SP_B - SP_A) * TS / (1.0 - math.exp(-TS / TS))
    assert jump == pytest.approx(gap, rel=1e-2)
    assert jump < 2.0 * after
    # and B then takes the loop to its own set point
    assert pv[-1] == pytest.approx(SP_B, abs=1e-2)

    mv_free, _ = selector_loop(track=False)
    jump_free = abs(mv_free[i] - mv_free[i - 1])
    assert mv_free[: i - 1] == pytest.approx(mv[: i - 1], abs=1e-12)  # same loop before the switch
    # Without tracking B's integrator winds up for 60 s on its 0.5 error.
    assert jump_free > 5.0
    assert jump_free > 100.0 * jump


def test_selector_slow_tracking_leaves_a_proportional_gap():
    # tt = 4 s: the gap tt·(k/ti)·e ≈ 0.4 (continuous-time value) is far larger
    # than the per-sample change — tracking for selectors wants tt ≈ Ts.
    i = round(T_SWITCH / TS)
    mv, _ = selector_loop(track=True, tt=4.0)
    gap = K_B / TI_B * (SP_B - SP_A) * TS / (1.0 - math.exp(-TS / 4.0))
    assert abs(mv[i] - mv[i - 1]) == pytest.approx(gap, rel=1e-2)
    assert gap == pytest.approx(4.0 * K_B / TI_B * (SP_B - SP_A), rel=2e-2)
