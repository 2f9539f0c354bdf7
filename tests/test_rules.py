"""Tuning rules against hand computation from the published formulas (methods.md §4) and published examples.

Every expected number is computed here by hand from the rule's table or
formula with the model parameters written out; none is the library's output.
"""

import math

import pytest

from autotuner.benchmarks.design_bench import default_batch, load_batch
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.design.process_data import from_fopdt, from_plant, from_point
from autotuner.engine.experiment.relay import Point
from autotuner.engine.design.robustness import check_loop, log_grid, pid_frequency_response
from autotuner.engine.design.rules import RULES, Options, RuleError, tune

REL = 1e-9


def gains(rule, data, controller, **options):
    g = tune(rule, data, controller, Options(**options)).gains
    return g.k, g.ti, g.td


# FOPDT K0 = 2, T = 10, L = 2: a = K0·L/T = 0.4, L/T = 0.2, τ = 2/12.
M = from_fopdt(2.0, 10.0, 2.0)


def test_zn_step_table():
    # Ziegler & Nichols (1942) reaction curve: P 1/a; PI 0.9/a, 3L; PID 1.2/a, 2L, L/2.
    assert gains("zn-step", M, "P") == pytest.approx((2.5, math.inf, 0.0), rel=REL)
    assert gains("zn-step", M, "PI") == pytest.approx((2.25, 6.0, 0.0), rel=REL)
    assert gains("zn-step", M, "PID") == pytest.approx((3.0, 4.0, 1.0), rel=REL)


def test_zn_frequency_on_first_order_with_delay_by_hand():
    # e^{-s}/(s+1): ultimate frequency solves atan(w) + w = π, K180 = 1/sqrt(1 + w²).
    w = 2.028757838110434  # root of atan(w) + w = π (checked below)
    assert math.atan(w) + w == pytest.approx(math.pi, abs=1e-12)
    kc, tu = math.sqrt(1 + w * w), 2 * math.pi / w
    data = from_fopdt(1.0, 1.0, 1.0)
    assert gains("zn-frequency", data, "P") == pytest.approx((0.5 * kc, math.inf, 0.0), rel=1e-9)
    assert gains("zn-frequency", data, "PI") == pytest.approx((0.45 * kc, tu / 1.2, 0.0), rel=1e-9)
    assert gains("zn-frequency", data, "PID") == pytest.approx((0.6 * kc, tu / 2, tu / 8), rel=1e-9)


def test_zn_frequency_and_astrom_hagglund_from_a_measured_ultimate_point():
    # Kc = 1/0.25 = 4, T180 = 2π/1 (e.g. 1/(s+1)^4, whose ultimate point is ω = 1, |F| = 1/4).
    data = from_point(Point(1.0, complex(-0.25, 0.0)), None)
    assert gains("zn-frequency", data, "PID") == pytest.approx((2.4, math.pi, math.pi / 4), rel=REL)
    # Åström–Hägglund with r_b = 0.5, φ_b = 30°: Kp = 4·0.5·cos30°, Ti = (2π/π)(1 + 0.5)/cos30° = 3/cos30°.
    c = math.cos(math.radians(30))
    assert gains("astrom-hagglund", data, "PID", phib_deg=30.0) == pytest.approx((2 * c, 3 / c, 0.75 / c), rel=1e-12)
    assert gains("astrom-hagglund", data, "PI", phib_deg=30.0) == pytest.approx((2 * c, 3 / c, 0.0), rel=1e-12)


def test_kappa_tau_by_hand():
    # Åström & Hägglund 1995, kappa–tau PI/PID (Ms = 1.4) at τ = 1/6, rows normalised by L (τ ≤ 0.5).
    tau = 2.0 / 12.0
    f = lambda a0, a1, a2: a0 * math.exp(a1 * tau + a2 * tau * tau)  # noqa: E731
    k, ti, td = gains("kappa-tau", M, "PI")
    assert (k, ti) == pytest.approx((f(0.29, -2.7, 3.7) / 0.4, f(8.9, -6.6, 3.0) * 2.0), rel=1e-12)
    assert tune("kappa-tau", M, "PI").gains.b == pytest.approx(f(0.81, 0.73, 1.9), rel=1e-12)
    assert gains("kappa-tau", M, "PID") == pytest.approx(
        (f(3.8, -8.4, 7.3) / 0.4, f(5.2, -2.5, -1.4) * 2.0, f(0.89, -0.37, -4.1) * 2.0), rel=1e-12)


def test_kappa_tau_uses_t_rows_for_delay_dominant_processes():
    data = from_fopdt(1.0, 1.0, 3.0)  # τ = 0.75, a = 3
    tau = 0.75
    f = lambda a0, a1, a2: a0 * math.exp(a1 * tau + a2 * tau * tau)  # noqa: E731
    assert gains("kappa-tau", data, "PID") == pytest.approx(
        (f(3.8, -8.4, 7.3) / 3.0, f(0.46, 2.8, -2.1) * 1.0, f(0.077, 5.0, -4.8) * 1.0), rel=1e-12)


def test_chien_hrones_reswick_tables():
    # τ/(Km L) = 10/(2·2) = 2.5
    assert gains("chr-regulation", M, "P") == pytest.approx((1.75, math.inf, 0.0), rel=REL)
    assert gains("chr-regulation", M, "PI") == pytest.approx((1.75, 4.6, 0.0), rel=REL)
    assert gains("chr-regulation", M, "PID") == pytest.approx((3.0, 4.0, 0.84), rel=REL)
    assert gains("chr-servo", M, "PI") == pytest.approx((1.5, 10.0, 0.0), rel=REL)
    assert gains("chr-servo", M, "PID") == pytest.approx((2.375, 13.6, 0.94), rel=REL)


def test_cohen_coon_by_hand():
    # L/T = 0.2, T/(Km L) = 2.5
    assert gains("cohen-coon", M, "P")[0] == pytest.approx(2.5 * (1 + 0.2 / 3), rel=REL)
    assert gains("cohen-coon", M, "PI") == pytest.approx((2.5 * (0.9 + 0.2 / 12), 2 * 30.6 / 13, 0.0), rel=REL)
    assert gains("cohen-coon", M, "PID") == pytest.approx(
        (2.5 * (4 / 3 + 0.05), 2 * 33.2 / 14.6, 8 / 11.4), rel=REL)


def test_takahashi_discrete_and_standard_forms():
    # τ/Km = 5, L = 2, T = 1 (sample time): L + T/2 = 2.5, (L + T/2)² = 6.25, L + T = 3.
    k = 1.2 * 5 / 3 - 0.3 * 5 * 1 / 6.25
    ki, kd = 0.6 * 5 * 1 / 6.25, 0.5 * 5 / 1
    t = tune("takahashi", M, "PID", Options(ts=1.0))
    assert t.extra["discrete"] == pytest.approx({"k": k, "ki": ki, "kd": kd, "ts": 1.0}, rel=REL)
    assert (t.gains.k, t.gains.ti, t.gains.td) == pytest.approx((k, k / ki, kd / k), rel=REL)
    pi = tune("takahashi", M, "PI", Options(ts=1.0)).extra["discrete"]
    assert (pi["k"], pi["ki"]) == pytest.approx((0.9 * 5 / 2.5 - 0.135 * 5 / 6.25, 0.27 * 5 / 6.25), rel=REL)


def test_amigo_by_hand():
    # Åström & Hägglund, Advanced PID Control (2006) §7: K=2, L=2, T=10.
    k, ti, _ = gains("amigo", M, "PI")
    assert k == pytest.approx(0.15 / 2 + (0.35 - 20 / 144) * 10 / 4, rel=REL)
    assert ti == pytest.approx(0.7 + 13 * 2 * 100 / (100 + 240 + 28), rel=REL)
    assert gains("amigo", M, "PID") == pytest.approx(
        ((0.2 + 0.45 * 5) / 2, (0.8 + 8) / 3 * 2, 0.5 * 20 / 10.6), rel=REL)
    assert tune("amigo", M, "PI").gains.b == 0.0  # τ = 1/6 ≤ 0.5


def test_amigo_integrating_from_plant():
    # e^{-0.5s}/(s(3s+1)): asymptote slope Kv = 1, apparent dead time L = 0.5 + 3 = 3.5.
    data = from_plant(parse_process("exp(-0.5*s)/(s*(3*s+1))"))
    assert gains("amigo", data, "PI") == pytest.approx((0.35 / 3.5, 13.4 * 3.5, 0.0), rel=2e-4)
    assert gains("amigo", data, "PID") == pytest.approx((0.45 / 3.5, 28.0, 1.75), rel=2e-4)


def test_itae_integral_recovers_fopdt_and_applies_itae_table():
    # On an FOPDT the integral-controller experiment identifies it exactly: T = 10, θ0 = L/T = 0.2.
    t = tune("itae-integral", M, "PID")
    assert t.extra["data"]["T"] == pytest.approx(10.0, rel=1e-9)
    assert t.extra["data"]["theta0"] == pytest.approx(0.2, rel=1e-9)
    # Rovira et al. (1969) ITAE set point: K Km = 0.965 θ^-0.85, T/Ti = 0.796 − 0.1465 θ, Td/T = 0.308 θ^0.929.
    expected = (0.965 * 0.2 ** -0.85 / 2, 10 / (0.796 - 0.1465 * 0.2), 0.308 * 0.2 ** 0.929 * 10)
    assert (t.gains.k, t.gains.ti, t.gains.td) == pytest.approx(expected, rel=1e-9)


def test_robust_is_the_project_design():
    from autotuner.engine.design.point_design import design
    point = Point(0.5, 0.3 * complex(math.cos(math.radians(-135)), math.sin(math.radians(-135))))
    data = from_point(point, 1.2)
    assert tune("robust", data, "PI").gains == design(point, 1.2, "PI").gains


@pytest.mark.parametrize(("rule", "data", "controller", "words"), [
    ("cohen-coon", from_plant(parse_process("exp(-s)/s")), "PI", "integrating"),
    ("zn-frequency", from_plant(parse_process("1/(s+1)^2")), "PI", "never lags"),
    ("amigo", from_point(Point(0.5, -0.3j), None), "PI", "--static-gain"),
    ("zn-frequency", from_point(Point(0.5, -0.3j), None), "PI", "lags by 90.0°"),
    ("kappa-tau", M, "P", "defines PI, PID"),
    ("takahashi", M, "PI", "--ts"),
    ("zn-step", from_plant(parse_process("exp(-0.2*s)/(2*s-1)")), "PI", "unstable"),
    ("direct-synthesis-unstable", M, "PID", "stable"),
    ("no-such-rule", M, "PI", "unknown rule"),
])
def test_rules_refuse_what_they_do_not_define(rule, data, controller, words):
    with pytest.raises(RuleError, match=words.replace("(", r"\(").replace(".", r"\.")):
        tune(rule, data, controller)


def test_registry_lists_every_rule_of_the_issue():
    assert set(RULES) == {"zn-step", "kappa-tau", "zn-frequency", "astrom-hagglund", "chr-regulation",
                          "chr-servo", "cohen-coon", "takahashi", "amigo", "itae-integral", "itae-optimal",
                          "direct-synthesis-unstable", "robust"}


# -- against the batch's independent reference figures ----------------------------

BATCH_ROWS = load_batch(default_batch())[::9]


@pytest.mark.parametrize("row", BATCH_ROWS, ids=[r["id"] for r in BATCH_ROWS])
def test_zn_frequency_pi_matches_the_batch_reference_ms(row):
    # The batch file (Åström–Hägglund's test batch) gives, for every process, the Ms of
    # Ziegler–Nichols frequency-response PI (0.45 Ku, Tu/1.2) on the exact ultimate point,
    # computed independently of this project.
    process = parse_process(row["expr"])
    gains = tune("zn-frequency", from_plant(process), "PI").gains
    w = log_grid(float(row["w135"]))
    ms = check_loop(process.freqresp, lambda x: pid_frequency_response(x, gains.k, gains.ti), w,
                    integrators=process.integrator_count + 1).ms
    if row["zn_pi_ms"] == "unstable":
        assert math.isinf(ms)
    else:
        assert ms == pytest.approx(float(row["zn_pi_ms"]), rel=0.005)
