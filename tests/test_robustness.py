"""Robustness: Ms, Nyquist stability and the MIGO solver, against closed forms,
closed-loop polynomial roots (Padé for dead time) and the independent MIGO
reference of the benchmark batch."""

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from autotuner.engine.plant.expression import parse_process
from autotuner.engine.design.robustness import (
    Plant,
    check_loop,
    closed_loop_stable,
    log_grid,
    max_sensitivity,
    migo,
    pid_frequency_response,
)

BATCH = Path("/work/shared/bench/amigo-batch.csv")


# --------------------------------------------------------------------------- independent helpers


def pade(delay: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """[n/n] Padé approximation of ``e^{−delay·s}``: (numerator, denominator), highest power first."""
    c = [
        math.factorial(2 * n - k) * math.factorial(n) / (math.factorial(2 * n) * math.factorial(k) * math.factorial(n - k))
        for k in range(n + 1)
    ]
    num = np.array([c[k] * (-delay) ** k for k in range(n + 1)])[::-1]
    den = np.array([c[k] * delay**k for k in range(n + 1)])[::-1]
    return num, den


def closed_loop_poles(num, den, delay=0.0, n_pade=10):
    """Roots of ``den·Dp + num·Np`` for the open loop ``num/den·e^{−delay·s}``."""
    num, den = np.atleast_1d(np.asarray(num, float)), np.atleast_1d(np.asarray(den, float))
    if delay > 0.0:
        pn, pd = pade(delay, n_pade)
        num, den = np.polymul(num, pn), np.polymul(den, pd)
    return np.roots(np.polyadd(den, num))


def stable_by_roots(num, den, delay=0.0, n_pade=10) -> bool:
    return bool(np.all(closed_loop_poles(num, den, delay, n_pade).real < 0.0))


def rational(num, den, delay=0.0):
    def f(w):
        s = 1j * np.asarray(w, float)
        return np.polyval(num, s) / np.polyval(den, s) * np.exp(-delay * s)

    return f


def load_batch():
    with BATCH.open() as fh:
        return list(csv.DictReader(fh))


ROWS = load_batch()


def _subset():
    ids = {r["id"] for r in ROWS[::10]}
    ids |= {ROWS[0]["id"], ROWS[-1]["id"]}
    # Edge rows: the most lag-dominant FOPDT, the pure IPDT, the nearly delay-free integrator,
    # the slowest double lag, the highest-order lag.
    ids |= {"P1-021", "P6-076", "P6-068", "P2-041", "P4-058"}
    return [r for r in ROWS if r["id"] in ids]


SUBSET = _subset()


# --------------------------------------------------------------------------- grid and controller


def test_log_grid_spans_and_is_geometric():
    w = log_grid(2.5, below=1e-3, above=1e1, n=401)
    assert len(w) == 401
    assert w[0] == pytest.approx(2.5e-3, rel=1e-12)
    assert w[-1] == pytest.approx(25.0, rel=1e-12)
    ratios = w[1:] / w[:-1]
    assert np.allclose(ratios, 10 ** (4 / 400), rtol=1e-10)


@pytest.mark.parametrize("k, ti, td, nd", [(2.0, 3.0, 0.0, 10.0), (0.7, 1.5, 0.4, 8.0), (1.3, math.inf, 0.5, 5.0)])
def test_pid_frequency_response_equals_rational_form(k, ti, td, nd):
    w = np.logspace(-3, 3, 50)
    s = 1j * w
    # k·(ti·s·(td s/nd + 1) + (td s/nd + 1) + ti·td·s²) / (ti·s·(td s/nd + 1)) as polynomials
    if math.isinf(ti):
        num = np.polymul([k], np.polyadd([td / nd, 1.0], [td, 0.0]))
        den = np.array([td / nd, 1.0])
    else:
        lag = np.array([td / nd, 1.0])
        num = k * np.polyadd(np.polyadd(np.polymul([ti, 0.0], lag), lag), [ti * td, 0.0, 0.0])
        den = np.polymul([ti, 0.0], lag)
    want = np.polyval(num, s) / np.polyval(den, s)
    assert np.allclose(pid_frequency_response(w, k, ti, td, nd), want, rtol=1e-12, atol=0)


def test_pid_without_derivative_is_pi():
    w = np.array([0.1, 1.0, 10.0])
    assert np.allclose(pid_frequency_response(w, 2.0, 4.0), 2.0 * (1.0 + 1.0 / (4.0j * w)), rtol=1e-14)


# --------------------------------------------------------------------------- maximum sensitivity


@pytest.mark.parametrize("k", [0.2, 0.5, 0.9])
def test_ms_of_pure_delay_loop_is_one_over_one_minus_k(k):
    # L = k·e^{−2s}: |1 + L| is smallest (1 − k) where e^{−2jω} = −1, ω = π/2.
    w = np.sort(np.append(np.logspace(-2, 1, 500), math.pi / 2.0))
    loop = k * np.exp(-2j * w)
    assert max_sensitivity(loop) == pytest.approx(1.0 / (1.0 - k), rel=1e-12)


@pytest.mark.parametrize("k", [0.3, 1.0, 4.0, 20.0])
def test_ms_of_integrator_with_lag_matches_calculus(k):
    # L = k/(s(s+1)): |S|² = x(1+x)/((k−x)² + x) with x = ω². Its stationary points solve
    # (1+2x)((k−x)²+x) − x(1+x)(1 − 2(k−x)) = 0; the supremum is the largest of those and the limit 1.
    poly = np.polysub(
        np.polymul([2.0, 1.0], np.polyadd(np.polymul([-1.0, k], [-1.0, k]), [1.0, 0.0])),
        np.polymul([1.0, 1.0, 0.0], [2.0, 1.0 - 2.0 * k]),
    )
    xs = [r.real for r in np.roots(poly) if abs(r.imag) < 1e-9 and r.real > 0.0]
    s2 = [x * (1 + x) / ((k - x) ** 2 + x) for x in xs] + [1.0]
    ms_exact = math.sqrt(max(s2))
    w = np.logspace(-3, 3, 400001)
    loop = k / (1j * w * (1j * w + 1.0))
    assert max_sensitivity(loop) == pytest.approx(ms_exact, rel=1e-7)
    assert ms_exact > 1.0 or k < 0.5


def test_ms_of_first_order_loop_approaches_one_from_below():
    # L = k/(s+1), k > 0: |S|² = (1+ω²)/((1+k)²+ω²) < 1, increasing; the grid maximum is at its end.
    k = 3.0
    w = np.logspace(-2, 2, 300)
    loop = k / (1j * w + 1.0)
    end = w[-1]
    assert max_sensitivity(loop) == pytest.approx(math.sqrt((1 + end**2) / ((1 + k) ** 2 + end**2)), rel=1e-12)
    assert max_sensitivity(loop) < 1.0


def test_ms_is_inf_when_loop_passes_through_minus_one():
    loop = np.array([2.0 + 0.0j, -1.0 + 0.0j, 0.1j])
    assert max_sensitivity(loop) == math.inf


# --------------------------------------------------------------------------- Nyquist stability, rational loops


W_WIDE = np.logspace(-5, 5, 6000)


@pytest.mark.parametrize("k", [0.5, 2.0, 6.0, 7.5, 8.5, 12.0, 50.0])
def test_stability_of_third_order_lag_matches_roots(k):
    # L = k/(s+1)³: stable for k < 8.
    num, den = [k], np.polymul([1, 1], np.polymul([1, 1], [1, 1]))
    loop = rational(num, den)(W_WIDE)
    assert closed_loop_stable(loop, W_WIDE, 0, 0) == stable_by_roots(num, den)
    assert closed_loop_stable(loop, W_WIDE) == (k < 8.0)


@pytest.mark.parametrize("kp, ti", [(0.5, 3.0), (0.5, 0.8), (2.0, 1.5), (2.0, 0.6), (10.0, 2.0), (10.0, 0.9), (0.05, 20.0)])
def test_stability_of_pi_on_integrator_with_lag_matches_roots(kp, ti):
    # C = kp(1 + 1/(ti s)), F = 1/(s(s+1)): two integrators; ti s³ + ti s² + kp ti s + kp, stable iff ti > 1.
    num = kp * np.array([ti, 1.0])
    den = np.polymul([ti, 0.0], [1.0, 1.0, 0.0])
    loop = rational(num, den)(W_WIDE)
    assert closed_loop_stable(loop, W_WIDE, integrators=2) == stable_by_roots(num, den)
    assert closed_loop_stable(loop, W_WIDE, integrators=2) == (ti > 1.0)


@pytest.mark.parametrize("k", [0.3, 0.9, 1.1, 3.0, 100.0])
def test_stability_with_unstable_open_loop_pole(k):
    # L = k/(s − 1): closed-loop pole at 1 − k, stable for k > 1 (one counter-clockwise encirclement).
    num, den = [k], [1.0, -1.0]
    w = np.logspace(-5, 7, 6000)
    loop = rational(num, den)(w)
    assert closed_loop_stable(loop, w, rhp_poles=1) == stable_by_roots(num, den)
    assert closed_loop_stable(loop, w, rhp_poles=1) == (k > 1.0)
    # Ignoring the unstable pole would give the opposite answer.
    assert closed_loop_stable(loop, w, rhp_poles=0) != (k > 1.0)


@pytest.mark.parametrize("kp, ti", [(2.0, 1.0), (1.2, 5.0), (0.8, 1.0), (5.0, 0.3), (3.0, 0.2)])
def test_stability_of_pi_on_unstable_lag_matches_roots(kp, ti):
    # C = kp(1 + 1/(ti s)), F = 1/((s − 1)(0.1 s + 1)): one integrator, one RHP pole.
    num = kp * np.array([ti, 1.0])
    den = np.polymul([ti, 0.0], np.polymul([1.0, -1.0], [0.1, 1.0]))
    loop = rational(num, den)(W_WIDE)
    assert closed_loop_stable(loop, W_WIDE, integrators=1, rhp_poles=1) == stable_by_roots(num, den)


def test_stability_cases_cover_both_outcomes():
    # The parametrisations above must include stable and unstable loops (else they prove little).
    assert stable_by_roots(0.5 * np.array([3.0, 1.0]), np.polymul([3.0, 0.0], [1.0, 1.0, 0.0]))
    assert not stable_by_roots(0.5 * np.array([0.8, 1.0]), np.polymul([0.8, 0.0], [1.0, 1.0, 0.0]))
    den = lambda ti: np.polymul([ti, 0.0], np.polymul([1.0, -1.0], [0.1, 1.0]))  # noqa: E731
    assert stable_by_roots(2.0 * np.array([1.0, 1.0]), den(1.0))
    assert not stable_by_roots(0.8 * np.array([1.0, 1.0]), den(1.0))


# --------------------------------------------------------------------------- Nyquist stability, dead time (Padé)


W_DELAY = np.logspace(-5, 4, 20000)


@pytest.mark.parametrize("k", [0.5, 1.5, 2.1, 2.4, 3.0, 4.0])
def test_stability_of_fopdt_loop_matches_pade(k):
    # L = k·e^{−s}/(s+1): critical gain √(1+ω²) with ω + atan ω = π (≈ 2.26).
    num, den = [k], [1.0, 1.0]
    loop = rational(num, den, 1.0)(W_DELAY)
    got = closed_loop_stable(loop, W_DELAY)
    assert got == stable_by_roots(num, den, 1.0, 10) == stable_by_roots(num, den, 1.0, 14)
    wc = 2.0287578381104345  # ω + atan ω = π
    assert abs(wc + math.atan(wc) - math.pi) < 1e-12
    assert got == (k < math.sqrt(1.0 + wc * wc))


@pytest.mark.parametrize("k", [0.5, 1.5, 1.65, 2.5])
def test_stability_of_integrator_with_delay_matches_pade(k):
    # L = k·e^{−s}/s: stable for k < π/2.
    num, den = [k], [1.0, 0.0]
    loop = rational(num, den, 1.0)(W_DELAY)
    got = closed_loop_stable(loop, W_DELAY, integrators=1)
    assert got == stable_by_roots(num, den, 1.0, 10)
    assert got == (k < math.pi / 2.0)


@pytest.mark.parametrize("kp, ti", [(0.3, 7.0), (0.3, 1.0), (0.9, 3.0), (1.4, 6.0), (0.1, 0.5)])
def test_stability_of_pi_on_ipdt_matches_pade(kp, ti):
    num = kp * np.array([ti, 1.0])
    den = np.polymul([ti, 0.0], [1.0, 0.0])
    loop = rational(num, den, 1.0)(W_DELAY)
    assert closed_loop_stable(loop, W_DELAY, integrators=2) == stable_by_roots(num, den, 1.0, 10)


@pytest.mark.parametrize("k", [0.8, 1.2, 2.0, 4.0, 6.0])
def test_stability_of_unstable_fopdt_matches_pade(k):
    # L = k·e^{−0.2s}/(s − 1): needs k > 1, and loses stability again at high gain.
    num, den = [k], [1.0, -1.0]
    loop = rational(num, den, 0.2)(W_DELAY)
    got = closed_loop_stable(loop, W_DELAY, rhp_poles=1)
    assert got == stable_by_roots(num, den, 0.2, 10)


def test_unstable_fopdt_cases_cover_both_outcomes():
    outcomes = {stable_by_roots([k], [1.0, -1.0], 0.2, 10) for k in (0.8, 2.0, 6.0)}
    assert outcomes == {True, False}


# --------------------------------------------------------------------------- check_loop


def test_check_loop_stable_reports_ms():
    f = rational([1.0], [1.0, 2.0, 1.0], 0.5)
    c = lambda w: pid_frequency_response(w, 0.8, 2.0)  # noqa: E731
    w = np.logspace(-4, 3, 20000)
    res = check_loop(f, c, w, integrators=1)
    assert res.stable == stable_by_roots(np.polymul([0.8 * 2.0, 0.8], [1.0]), np.polymul([2.0, 0.0], [1.0, 2.0, 1.0]), 0.5)
    assert res.stable
    brute = 1.0 / np.min(np.abs(1.0 + c(w) * f(w)))
    assert res.ms == pytest.approx(brute, rel=1e-12)
    assert 1.0 < res.ms < 3.0


def test_check_loop_unstable_reports_inf_even_if_far_from_minus_one():
    # L = 20/(s+1)³ is unstable (k > 8) although min|1 + L| is finite.
    f = rational([1.0], [1.0, 3.0, 3.0, 1.0])
    w = np.logspace(-4, 4, 6000)
    res = check_loop(f, lambda w: 20.0 * np.ones_like(w, dtype=complex), w)
    assert not res.stable
    assert res.ms == math.inf
    assert max_sensitivity(20.0 * f(w)) < 2.5  # finite: the inf comes from the instability


# --------------------------------------------------------------------------- MIGO


def _plant(process):
    return Plant(process.freqresp, integrators=process.integrator_count)


def _independently_stable(process, k, ti, td=0.0, nd=10.0) -> bool:
    """Closed-loop roots of the controller on the process (Padé for its dead time)."""
    if td > 0.0:
        # k(1 + 1/(ti s) + td s/(td s/nd + 1)) as one rational function
        lag = np.array([td / nd, 1.0])
        cnum = k * np.polyadd(np.polyadd(np.polymul([ti, 0.0], lag), lag), [ti * td, 0.0, 0.0])
        cden = np.polymul([ti, 0.0], lag)
    else:
        cnum, cden = k * np.array([ti, 1.0]), np.array([ti, 0.0])
    return stable_by_roots(np.polymul(cnum, process.num), np.polymul(cden, process.den), process.delay, 10)


def _fine_grid(w_ref):
    return log_grid(w_ref, 1e-5, 1e3, 40000)


@pytest.mark.parametrize("row", SUBSET, ids=[r["id"] for r in SUBSET])
def test_migo_pi_matches_batch_reference(row):
    process = parse_process(row["expr"])
    w135 = float(row["w135"])
    res = migo([_plant(process)], w135)
    assert res.td == 0.0
    assert res.ki == pytest.approx(float(row["migo_pi_ki"]), rel=0.01)
    assert res.k == pytest.approx(float(row["migo_pi_k"]), rel=0.01)
    assert res.ti == pytest.approx(float(row["migo_pi_ti"]), rel=0.01)
    # The result meets the constraint on a much finer and wider grid, and the loop is stable.
    w = _fine_grid(w135)
    loop = pid_frequency_response(w, res.k, res.ti) * process.freqresp(w)
    assert max_sensitivity(loop) <= 1.4 * 1.005
    assert closed_loop_stable(loop, w, process.integrator_count + 1)
    assert _independently_stable(process, res.k, res.ti)


def test_migo_two_plants_is_no_larger_than_either_alone():
    a = parse_process("exp(-0.5*s)/((2*s+1)*(0.5*s+1))")
    b = parse_process("1.6*exp(-0.8*s)/((2*s+1)*(0.5*s+1))")
    w_ref = 1.2
    ra = migo([_plant(a)], w_ref)
    rb = migo([_plant(b)], w_ref)
    both = migo([_plant(a), _plant(b)], w_ref)
    # Same limit on a common grid would need the solver's own tolerance: 1e-6 relative.
    assert both.ki <= min(ra.ki, rb.ki) * (1.0 + 1e-6)
    # b has more gain and more delay: the pair is limited by b, and strictly below a alone.
    assert both.ki < ra.ki * 0.99
    w = _fine_grid(w_ref)
    for p in (a, b):
        loop = pid_frequency_response(w, both.k, both.ti) * p.freqresp(w)
        assert max_sensitivity(loop) <= 1.4 * 1.005
        assert _independently_stable(p, both.k, both.ti)


def _brute_force_pi_ki(processes, ms=1.4):
    """Largest k/ti over a dense ti grid, k found by bisection of ``min |1 + L| ≥ 1/ms`` on a dense ω grid.

    The bisection runs below the gain margin (the first crossing of the negative real
    axis), where the loop is stable; there the admissible gains form an interval from 0
    for these plants.
    """
    w = np.logspace(-2, 1.5, 2500)
    ti = np.logspace(-1.5, 1.5, 300)[:, None]
    c0 = 1.0 + 1.0 / (ti * 1j * w[None, :])
    zs = [c0 * p.freqresp(w)[None, :] for p in processes]
    hi = np.full(ti.shape, np.inf)
    for z in zs:
        cross = (np.sign(z.imag[:, 1:]) != np.sign(z.imag[:, :-1])) & (z.real[:, 1:] < 0.0)
        first = np.argmax(cross, axis=1)
        hi = np.minimum(hi, 1.0 / np.abs(z[np.arange(len(ti)), first + 1])[:, None])
    lo = np.zeros(ti.shape)
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        ok = np.ones(ti.shape, dtype=bool)
        for z in zs:
            ok &= np.min(np.abs(1.0 + mid * z), axis=1, keepdims=True) >= 1.0 / ms
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    return float(np.max(lo / ti))


def test_migo_two_plants_with_different_dynamics_matches_brute_force():
    # Two plants whose limits bind at different frequencies: the joint design is below both.
    a = parse_process("exp(-1*s)/(0.2*s+1)")
    b = parse_process("exp(-0.3*s)/(s+1)^3")
    w_ref = 1.0
    ra, rb = migo([_plant(a)], w_ref), migo([_plant(b)], w_ref)
    both = migo([_plant(a), _plant(b)], w_ref)
    assert both.ki <= min(ra.ki, rb.ki) * (1.0 + 1e-6)
    brute = _brute_force_pi_ki([a, b])
    assert both.ki == pytest.approx(brute, rel=0.01)
    assert brute < 0.99 * min(_brute_force_pi_ki([a]), _brute_force_pi_ki([b]))
    w = _fine_grid(w_ref)
    for p in (a, b):
        loop = pid_frequency_response(w, both.k, both.ti) * p.freqresp(w)
        assert max_sensitivity(loop) <= 1.4 * 1.005
        assert _independently_stable(p, both.k, both.ti)


@pytest.mark.parametrize("ratio", [0.1, 0.25])
def test_migo_pid_beats_pi_on_lag_dominant_process(ratio):
    process = parse_process("exp(-s)/(10*s+1)^2")
    w_ref = 0.12
    pi = migo([_plant(process)], w_ref)
    pid = migo([_plant(process)], w_ref, td_ratio=ratio, nd=10.0)
    assert pid.td == pytest.approx(ratio * pid.ti, rel=1e-12)
    assert pid.ki >= pi.ki
    assert pid.ki > 1.2 * pi.ki  # derivative action pays off clearly on a lag-dominant double lag
    w = _fine_grid(w_ref)
    loop = pid_frequency_response(w, pid.k, pid.ti, pid.td, 10.0) * process.freqresp(w)
    assert max_sensitivity(loop) <= 1.4 * 1.005
    assert _independently_stable(process, pid.k, pid.ti, pid.td, 10.0)


@pytest.mark.parametrize("ms", [1.2, 2.0])
def test_migo_respects_other_ms_values_and_is_monotone(ms):
    process = parse_process("exp(-s)/(2*s+1)")
    w_ref = 1.18475
    res = migo([_plant(process)], w_ref, ms=ms)
    w = _fine_grid(w_ref)
    loop = pid_frequency_response(w, res.k, res.ti) * process.freqresp(w)
    assert max_sensitivity(loop) <= ms * 1.005
    # The constraint is active: Ms is not much below the limit.
    assert max_sensitivity(loop) >= ms * 0.995
    ref = migo([_plant(process)], w_ref, ms=1.4)
    assert (res.ki < ref.ki) == (ms < 1.4)
