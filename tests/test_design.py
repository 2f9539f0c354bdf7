"""Model fit through one point and robust design, against the exact process,
the batch's independent MIGO reference and an independent set-point response."""

import cmath
import csv
import functools
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import brentq

from autotuner.engine.design.point_design import INTEGRATING_RATIO, design, fit_model
from autotuner.engine.outcome import Code
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.experiment.relay import Point
from autotuner.engine.design.robustness import Plant, closed_loop_stable, migo

BATCH = Path("/work/shared/bench/amigo-batch.csv")
with BATCH.open() as _fh:
    ROWS = {r["id"]: r for r in csv.DictReader(_fh)}


def point_of(value_gain: float, lag_deg: float, omega: float) -> Point:
    return Point(omega, value_gain * cmath.exp(-1j * math.radians(lag_deg)))


# --------------------------------------------------------------------------- fit_model


@pytest.mark.parametrize("omega", [0.013, 0.9, 17.0])
@pytest.mark.parametrize("lag", [90.0, 91.0, 120.0, 135.0, 170.0, 180.0])
@pytest.mark.parametrize("ratio", [1.001, 1.5, 10.0, 150.0])
def test_fopdt_reproduces_point_and_static_gain(omega, lag, ratio):
    r = 0.37
    point = point_of(r, lag, omega)
    k0 = ratio * r
    model = fit_model(point, k0)
    assert model.integrator_count == 0
    assert model.order == 1
    assert model.delay >= 0.0
    got = complex(model.freqresp(omega))
    assert abs(got - point.value) < 1e-9 * abs(point.value)
    assert model.static_gain() == pytest.approx(k0, rel=1e-12)
    # First order: the time constant from the gain ratio, |F| = K0/√(1 + (ωT)²).
    t = 1.0 / model.den[1]  # den = (1, 1/T) after normalisation
    assert k0 / math.sqrt(1.0 + (omega * t) ** 2) == pytest.approx(r, rel=1e-12)


@pytest.mark.parametrize("lag", [90.0, 135.0, 180.0])
@pytest.mark.parametrize("k0", [math.inf, "ratio"])
def test_integrating_model_reproduces_point(lag, k0):
    omega, r = 0.45, 2.2
    point = point_of(r, lag, omega)
    static = math.inf if k0 == math.inf else INTEGRATING_RATIO * r
    model = fit_model(point, static)
    assert model.integrator_count == 1
    assert model.static_gain() == math.inf
    assert abs(complex(model.freqresp(omega)) - point.value) < 1e-9 * r
    # Kv·e^{−Ls}/s: the delay adds the lag beyond 90°.
    assert model.delay == pytest.approx(math.radians(lag - 90.0) / omega, rel=1e-12, abs=1e-15)


def test_static_gain_not_above_point_gain_gives_dead_time_model_through_point():
    point = point_of(1.3, 150.0, 2.0)
    model = fit_model(point, 1.0)
    assert abs(complex(model.freqresp(2.0)) - point.value) < 1e-9
    assert model.order == 0


@pytest.mark.parametrize(
    "point, k0, words",
    [
        (point_of(1.0, 60.0, 1.0), 2.0, "lag"),
        (point_of(1.0, 89.0, 1.0), 2.0, "lag"),
        (point_of(1.0, 181.0, 1.0), 2.0, "lag"),
        (point_of(1.0, 270.0, 1.0), 2.0, "lag"),
        (point_of(1.0, 300.0, 1.0), 2.0, "lag"),
        (Point(1.0, 0j), 2.0, "gain"),
        (Point(1.0, complex(math.nan, -1.0)), 2.0, "gain"),
        (Point(math.nan, -1.0 - 1.0j), 2.0, "frequency"),
        (Point(0.0, -1.0 - 1.0j), 2.0, "frequency"),
        (Point(-1.0, -1.0 - 1.0j), 2.0, "frequency"),
        (Point(math.inf, -1.0 - 1.0j), 2.0, "frequency"),
        (point_of(1.0, 135.0, 1.0), 0.0, "static gain"),
        (point_of(1.0, 135.0, 1.0), -3.0, "static gain"),
        (point_of(1.0, 135.0, 1.0), math.nan, "static gain"),
    ],
)
def test_fit_model_rejects_bad_data(point, k0, words):
    with pytest.raises(ValueError, match=words):
        fit_model(point, k0)


# --------------------------------------------------------------------------- design on exact models


def _w135(process, lo, hi):
    """Frequency where the process lags 135°, solved on the unwrapped phase."""
    def f(w):
        w = float(w)
        # first-order lag or integrator: the rational part lags by less than 180°, no wrapping
        phase = -w * process.delay + float(np.angle(np.polyval(process.num, 1j * w) / np.polyval(process.den, 1j * w)))
        return phase + 0.75 * math.pi
    return brentq(f, lo, hi, xtol=1e-14, rtol=1e-15)


CASES = ["P1-001", "P1-005", "P1-008", "P1-012", "P1-016", "P1-019", "P6-076"]


def _case(row_id):
    row = ROWS[row_id]
    process = parse_process(row["expr"])
    w = _w135(process, 1e-4, 10.0)
    assert w == pytest.approx(float(row["w135"]), rel=1e-4)  # agrees with the batch
    point = Point(w, complex(process.freqresp(w)))
    static = process.static_gain()
    return row, process, point, static


@functools.lru_cache(maxsize=None)
def _design(row_id, controller, ms=1.4):
    """Design from the exact point of a batch process (cached: several tests look at one design)."""
    _, _, point, static = _case(row_id)
    return design(point, static, controller, ms)


def _ms_on(process, k, ti, td, nd, w_ref):
    w = np.logspace(math.log10(w_ref) - 5, math.log10(w_ref) + 3, 40000)
    s = 1j * w
    c = k * (1.0 + 1.0 / (ti * s) + td * s / (td * s / nd + 1.0))
    loop = c * process.freqresp(w)
    return float(np.max(1.0 / np.abs(1.0 + loop))), loop, w


def _setpoint_peak(process, gains, w):
    """max |G_yr| with U = k(b·R − Y) + k/(ti s)(R − Y) − k·td s/(td s/nd + 1)·Y (c = 0)."""
    s = 1j * w
    f = process.freqresp(w)
    c_fb = gains.k * (1.0 + 1.0 / (gains.ti * s) + gains.td * s / (gains.td * s / gains.nd + 1.0))
    c_ff = gains.k * (gains.b + 1.0 / (gains.ti * s))
    return float(np.max(np.abs(c_ff * f / (1.0 + c_fb * f))))


def _brute_force_pi_ki(limits, w_ref, ti_guess):
    """Largest k/ti keeping ``min|1 + L| ≥ 1/limit`` for every (process, limit), by brute force.

    Dense ti grid (a factor 3 either side of ``ti_guess``; the optimum must fall inside it),
    and for each ti a bisection on k below the gain margin (the first frequency where the
    loop's phase falls through −180°; none for the two-lag bound), where the loop is
    stable and the admissible gains of these plants form an interval from 0.
    """
    w = w_ref * np.logspace(-3, 2, 2000)
    ti = ti_guess * np.logspace(-0.5, 0.5, 120)[:, None]
    c0 = 1.0 + 1.0 / (ti * 1j * w[None, :])
    zs = [(c0 * p.freqresp(w)[None, :], limit) for p, limit in limits]
    hi = np.full(ti.shape, 1e3 / np.min(np.abs(zs[0][0])))
    for z, _ in zs:
        phase = np.unwrap(np.angle(z), axis=1)
        falls = (phase[:, 1:] < -math.pi) & (phase[:, :-1] >= -math.pi)
        for i in range(len(ti)):
            idx = np.flatnonzero(falls[i])
            if idx.size:
                hi[i] = min(hi[i, 0], 1.0 / abs(z[i, idx[0] + 1]))
    lo = np.zeros(ti.shape)
    for _ in range(45):
        mid = 0.5 * (lo + hi)
        ok = np.ones(ti.shape, dtype=bool)
        for z, limit in zs:
            ok &= np.min(np.abs(1.0 + mid * z), axis=1, keepdims=True) >= 1.0 / limit
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    ki = (lo / ti).ravel()
    best = int(np.argmax(ki))
    assert 0 < best < len(ki) - 1
    return float(ki[best])


DELAY_DOMINANT = ["P1-001", "P1-005", "P1-008"]


@pytest.mark.parametrize("row_id", CASES)
def test_pi_design_on_exact_point(row_id):
    row, process, point, static = _case(row_id)
    d = _design(row_id, "PI", 1.4)
    g = d.gains
    assert g.td == 0.0
    # The model is the process itself.
    w = np.logspace(-3, 2, 200) * point.omega
    assert np.allclose(d.model.freqresp(w), process.freqresp(w), rtol=1e-9, atol=0)
    # The no-dead-time bound goes through the same point with the same static gain.
    assert abs(complex(d.bound.freqresp(point.omega)) - point.value) < 1e-9 * abs(point.value)
    assert d.bound.static_gain() == pytest.approx(static, rel=1e-12)
    ms, loop, wd = _ms_on(process, g.k, g.ti, 0.0, g.nd, point.omega)
    ms_bound, loop_b, _ = _ms_on(d.bound, g.k, g.ti, 0.0, g.nd, point.omega)
    assert ms <= 1.4 * 1.005
    assert ms_bound <= 1.4 * 1.05 * 1.005
    assert ms >= 1.4 * 0.99 or ms_bound >= 1.4 * 1.05 * 0.99  # one of the limits is active
    assert closed_loop_stable(loop, wd, process.integrator_count + 1)
    assert closed_loop_stable(loop_b, wd, d.bound.integrator_count + 1)
    ki = g.k / g.ti
    # The extra plant can only lower the integral gain below the batch's MIGO on the process.
    assert ki <= float(row["migo_pi_ki"]) * 1.01
    # Independent solution of the same two-plant problem.
    brute = _brute_force_pi_ki([(process, 1.4), (d.bound, 1.4 * 1.05)], point.omega, g.ti)
    assert ki == pytest.approx(brute, rel=0.01)


@pytest.mark.parametrize("row_id", DELAY_DOMINANT)
def test_pi_design_on_delay_dominant_point_is_migo_on_the_process(row_id):
    # Here the lag bound is not the binding plant: Ms on the process is at the limit and
    # ki is the MIGO one (batch reference, and migo on the process).
    row, process, point, static = _case(row_id)
    g = _design(row_id, "PI", 1.4).gains
    ms, _, _ = _ms_on(process, g.k, g.ti, 0.0, g.nd, point.omega)
    assert abs(ms - 1.4) <= 0.01
    ki = g.k / g.ti
    assert ki == pytest.approx(float(row["migo_pi_ki"]), rel=0.01)
    ref = migo([Plant(process.freqresp, integrators=process.integrator_count)], point.omega)
    assert ki == pytest.approx(ref.ki, rel=0.01)


@pytest.mark.parametrize("row_id", ["P1-004", "P1-008", "P1-016", "P6-076"])
def test_pid_design_has_at_least_pi_integral_gain_and_meets_ms(row_id):
    _, process, point, static = _case(row_id)
    pi = _design(row_id, "PI")
    pid = _design(row_id, "PID")
    assert pid.gains.k / pid.gains.ti >= pi.gains.k / pi.gains.ti
    g = pid.gains
    assert 0.0 < g.td <= 0.25 * g.ti * (1 + 1e-12)
    ms, loop, wd = _ms_on(process, g.k, g.ti, g.td, g.nd, point.omega)
    ms_bound, _, _ = _ms_on(pid.bound, g.k, g.ti, g.td, g.nd, point.omega)
    assert ms <= 1.4 * 1.005
    assert ms_bound <= 1.4 * 1.05 * 1.005
    assert ms >= 1.4 * 0.99 or ms_bound >= 1.4 * 1.05 * 0.99
    assert closed_loop_stable(loop, wd, process.integrator_count + 1)


@pytest.mark.parametrize("row_id", ["P1-001", "P2-022"])
def test_pid_for_a_near_pure_dead_time_survives_a_static_gain_a_little_high(row_id):
    """|F|/K0 near 1 cannot tell a tiny lag from none: 0.2 % on K0 (within what the experiment resolves)
    once made a PID with Ms 1.63-1.65 on the true process; the dead-time model in the family keeps it at
    1.4, and the derivative it gives up is said (te false, DERIVATIVE_DROPPED)."""
    _, process, point, static = _case(row_id)
    pid = design(point, static * 1.002, "PID")
    g = pid.gains
    ms, loop, wd = _ms_on(process, g.k, g.ti, g.td, g.nd, point.omega)
    assert ms <= 1.4 * 1.01
    assert closed_loop_stable(loop, wd, process.integrator_count + 1)
    if g.td == 0.0:
        assert pid.warning is Code.DERIVATIVE_DROPPED and pid.notes


def _with_b(gains, b):
    return type(gains)(k=gains.k, ti=gains.ti, td=gains.td, nd=gains.nd, b=b, c=gains.c)


@pytest.mark.parametrize(
    "row_id, controller, ms",
    [
        ("P1-001", "PI", 1.4),
        ("P1-001", "PID", 1.4),
        ("P1-008", "PI", 1.6),
        ("P1-008", "PID", 1.4),
        ("P1-012", "PI", 1.4),
    ],
)
def test_setpoint_weight_keeps_response_peak_at_one(row_id, controller, ms):
    _, process, point, static = _case(row_id)
    d = _design(row_id, controller, ms)
    g = d.gains
    assert 0.0 < g.b <= 1.0
    assert g.c == 0.0
    w = np.logspace(math.log10(point.omega) - 5, math.log10(point.omega) + 3, 40000)
    assert _setpoint_peak(d.model, g, w) <= 1.0 + 1e-6
    assert _setpoint_peak(process, g, w) <= 1.0 + 1e-6  # the model is the process here
    if g.b < 1.0:
        # b is the largest such weight, to the 0.001 it is reported with.
        assert _setpoint_peak(d.model, _with_b(g, g.b + 0.002), w) > 1.0 + 1e-9


@pytest.mark.parametrize("row_id", ["P1-001", "P1-008", "P1-016", "P6-076"])
@pytest.mark.parametrize("controller", ["PI", "PID"])
def test_setpoint_weight_is_in_unit_interval_and_maximal(row_id, controller):
    _, process, point, static = _case(row_id)
    d = _design(row_id, controller)
    g = d.gains
    assert 0.0 <= g.b <= 1.0
    w = np.logspace(math.log10(point.omega) - 5, math.log10(point.omega) + 3, 20000)
    if g.b > 0.0:
        assert _setpoint_peak(d.model, g, w) <= 1.0 + 1e-6
    if g.b < 1.0:
        assert _setpoint_peak(d.model, _with_b(g, min(1.0, g.b + 0.002)), w) > 1.0 + 1e-9


def test_lower_ms_gives_lower_integral_gain():
    _, process, point, static = _case("P1-008")
    low = _design("P1-008", "PI", 1.2)
    high = _design("P1-008", "PI", 2.0)
    for d, target in ((low, 1.2), (high, 2.0)):
        ms, _, _ = _ms_on(process, d.gains.k, d.gains.ti, 0.0, d.gains.nd, point.omega)
        assert abs(ms - target) <= 0.01
        assert d.model_ms == pytest.approx(ms, abs=0.01)
    assert low.gains.k / low.gains.ti < high.gains.k / high.gains.ti


@pytest.mark.parametrize("controller", ["P", "PD", "pi", "", None])
def test_design_rejects_unknown_controller(controller):
    with pytest.raises(ValueError, match="controller"):
        design(point_of(0.5, 135.0, 1.0), 1.0, controller)


@pytest.mark.parametrize("ms", [1.0, 1.04, 4.01, 10.0, math.nan, math.inf])
def test_design_rejects_ms_out_of_range(ms):
    with pytest.raises(ValueError, match="Ms"):
        design(point_of(0.5, 135.0, 1.0), 1.0, "PI", ms)


def test_design_propagates_model_errors():
    with pytest.raises(ValueError, match="lag"):
        design(point_of(0.5, 45.0, 1.0), 1.0, "PI")


def test_a_pid_whose_slower_filter_finds_no_design_drops_its_derivative_instead_of_dividing_by_zero():
    # The identification of exp(-0.55*s)/(2*s-1) under 1 % noise (tests/test_golden.py): lowering N for the noise
    # budget left MIGO without a controller (k = 0), and the next pass divided by it.
    from autotuner.engine.experiment.point import Point
    from autotuner.engine.experiment.relay import Identification
    from autotuner.engine.simulated_tuning import DesignJob

    point = Point(1.8261248115570847, complex(-0.2527711246152208, -0.0775990979204372))
    ident = Identification(point=point, static_gain=-1.0055906163480068, duration=30.0, periods=10.0, samples=3000,
                           hysteresis=0.02, noise_std=0.00570887356594577)
    code, message, des = DesignJob(ident, Code.OK, "ok", "PID", 1.4, 1.0).run()
    if des is None:  # no design: said in words, with a code of its own
        assert code in (Code.NO_DESIGN, Code.NOT_STABILISABLE, Code.UNSTABLE_DEAD_TIME_TOO_LONG), (code, message)
        assert "noise" in message or "Ms" in message or "dead time" in message, message
    else:
        assert des.gains.k > 0.0 and code in (Code.DERIVATIVE_DROPPED, Code.DERIVATIVE_LIMITED,
                                              Code.ROBUSTNESS_MISSED, Code.OK), (code, message)
