import math

import numpy as np
import pytest

from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.simulation import PlantSim, simulate_open_loop


def step(text, ts, n):
    return simulate_open_loop(parse_process(text), np.ones(n), ts), np.arange(n + 1) * ts


def fopdt_step(t, k, tau, delay):
    """Analytic unit-step response of k*exp(-delay*s)/(tau*s+1)."""
    tt = t - delay
    return np.where(tt > 0, k * (1 - np.exp(-np.maximum(tt, 0) / tau)), 0.0)


def second_order_step(t, t1, t2, delay):
    """Analytic unit-step response of exp(-delay*s)/((t1*s+1)(t2*s+1)), t1 != t2."""
    tt = np.maximum(t - delay, 0)
    y = 1 - (t1 * np.exp(-tt / t1) - t2 * np.exp(-tt / t2)) / (t1 - t2)
    return np.where(t - delay > 0, y, 0.0)


def test_fopdt_with_fractional_delay_matches_analytic_step():
    y, t = step("2*exp(-0.73*s)/(3*s+1)", 0.1, 200)
    np.testing.assert_allclose(y, fopdt_step(t, 2, 3, 0.73), rtol=0, atol=1e-9)
    assert y[7] == 0 and y[8] > 0  # the step arrives at 0.73 s, between samples 7 and 8


def test_arbitrary_staircase_equals_superposed_analytic_steps():
    rng = np.random.default_rng(3)
    ts, n = 0.2, 150
    u = rng.uniform(-1, 1, n)
    t = np.arange(n + 1) * ts
    increments = np.diff(u, prepend=0.0)
    for text, response in [
        ("1.7*exp(-0.37*s)/(2.5*s+1)", lambda tt: fopdt_step(tt, 1.7, 2.5, 0.37)),
        ("exp(-0.9*s)/((2*s+1)*(0.5*s+1))", lambda tt: second_order_step(tt, 2, 0.5, 0.9)),
    ]:
        expected = sum(du * response(t - k * ts) for k, du in enumerate(increments))
        y = simulate_open_loop(parse_process(text), u, ts)
        np.testing.assert_allclose(y, expected, rtol=0, atol=1e-9)


def test_second_order_step():
    y, t = step("exp(-0.25*s)/((2*s+1)*(0.5*s+1))", 0.1, 300)
    np.testing.assert_allclose(y, second_order_step(t, 2, 0.5, 0.25), rtol=0, atol=1e-9)


def test_integrating_process_ramps():
    y, t = step("exp(-0.5*s)/(s*(3*s+1))", 0.1, 1000)
    tt = np.maximum(t - 0.5, 0)
    expected = tt - 3 * (1 - np.exp(-tt / 3))
    np.testing.assert_allclose(y, expected, rtol=1e-11, atol=1e-9)
    assert y[-1] - y[-2] == pytest.approx(0.1, rel=1e-9)  # final slope 1/s


def test_unstable_process_grows_exponentially():
    # 1/(2s-1) = 0.5/(s-0.5): step response e^{(t-L)/2} - 1
    y, t = step("exp(-0.2*s)/(2*s-1)", 0.1, 400)
    tt = np.maximum(t - 0.2, 0)
    np.testing.assert_allclose(y, np.exp(tt / 2) - 1, rtol=1e-9, atol=1e-12)
    assert y[-1] > 1e8


def test_stiff_processes_step_exactly():
    y, t = step("1/(s+1)^8", 0.05, 600)
    expected = 1 - np.exp(-t) * sum(t**k / math.factorial(k) for k in range(8))
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-12)

    taus = [1, 0.1, 0.01, 0.001]
    y, t = step("1/((1+s)*(1+0.1*s)*(1+0.01*s)*(1+0.001*s))", 0.01, 800)
    expected = np.ones_like(t)
    for i, ti in enumerate(taus):
        residue = ti ** 3 / math.prod(ti - tj for j, tj in enumerate(taus) if j != i)
        expected -= residue * np.exp(-t / ti)
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-12)


def test_biproper_nonminimum_phase_output_is_sampled_before_new_mv():
    # (1-0.6s)/(2s+1) = -0.3 + 1.3/(2s+1): step response 1 - 1.3 e^{-t/2} for t > 0
    y, t = step("(1-0.6*s)/(2*s+1)", 0.1, 100)
    assert y[0] == 0.0  # the step applied at t=0 is not yet seen
    np.testing.assert_allclose(y[1:], 1 - 1.3 * np.exp(-t[1:] / 2), rtol=0, atol=1e-12)
    # dead time a whole number of samples: output at 0.3 s is taken just before the jump
    y, t = step("(1-0.6*s)*exp(-0.3*s)/(2*s+1)", 0.1, 100)
    assert y[3] == 0.0
    np.testing.assert_allclose(y[4:], 1 - 1.3 * np.exp(-(t[4:] - 0.3) / 2), atol=1e-12)
    # and with a fractional dead time
    y, t = step("(1-0.6*s)*exp(-0.25*s)/(2*s+1)", 0.1, 100)
    assert y[2] == 0.0
    np.testing.assert_allclose(y[3:], 1 - 1.3 * np.exp(-(t[3:] - 0.25) / 2), atol=1e-12)


def test_pure_gain_and_pure_delay():
    u = np.arange(1.0, 11.0)
    np.testing.assert_array_equal(simulate_open_loop(parse_process("2"), u, 0.1)[1:], 2 * u)
    y = simulate_open_loop(parse_process("2*exp(-0.25*s)"), u, 0.1)
    # u[k] starts at k*0.1 and is seen from k*0.1+0.25 on; samples read left limits
    np.testing.assert_allclose(y[3:], 2 * u[:-2], rtol=1e-15)
    np.testing.assert_array_equal(y[:3], 0.0)


def zoh_sampled_frequency_response(process, omega, ts, terms=200_000):
    """Exact steady-state gain from sampled cos input (ZOH) to the output at sample instants.

    The staircase of e^{jωkTs} contains e^{j(ω+mωs)t} with weight
    (1-e^{-jωTs})/(j(ω+mωs)Ts); the output samples see every alias as ω.
    """
    m = np.arange(-terms, terms + 1)
    big_omega = omega + m * 2 * np.pi / ts
    weights = (1 - np.exp(-1j * omega * ts)) / (1j * big_omega * ts)
    return np.sum(process.freqresp(big_omega) * weights)


@pytest.mark.parametrize("text", ["1.5*exp(-0.7*s)/(4*s+1)^2", "(1-0.6*s)*exp(-0.33*s)/(2*s+1)^3"])
def test_sinusoid_steady_state_matches_frequency_response(text):
    process = parse_process(text)
    omega, ts = 0.5, 0.3  # coarse sampling, dead time not a multiple of ts
    k = np.arange(1500)
    y = simulate_open_loop(process, np.cos(omega * k * ts), ts)
    h = zoh_sampled_frequency_response(process, omega, ts)
    tail = k[-100:]
    np.testing.assert_allclose(y[tail], (h * np.exp(1j * omega * tail * ts)).real, atol=1e-9)

    # with fine sampling the ZOH is just a half-sample delay: compare to F(jω) itself
    ts = 0.005
    k = np.arange(int(120 / ts))
    y = simulate_open_loop(process, np.cos(omega * k * ts), ts)
    f = complex(process.freqresp(omega)) * np.exp(-0.5j * omega * ts)
    tail = k[-2000:]
    np.testing.assert_allclose(y[tail], (f * np.exp(1j * omega * tail * ts)).real, atol=2e-5)


def test_noise_is_seeded_and_has_requested_std():
    process = parse_process("exp(-s)/(s+1)")

    def readings(seed):
        sim = PlantSim(process, 0.1, pv0=5.0, noise_std=0.2, seed=seed)
        return np.array([sim.measure() for _ in range(20000)])

    a, b = readings(7), readings(7)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, readings(8))
    assert a.std() == pytest.approx(0.2, rel=0.03)
    assert a.mean() == pytest.approx(5.0, abs=0.01)


def test_no_noise_measure_equals_true_pv():
    sim = PlantSim(parse_process("1/(s+1)"), 0.1, pv0=1.0)
    sim.advance(2.0)
    assert sim.measure() == sim.true_pv() == pytest.approx(1 + 2 * (1 - math.exp(-0.1)), rel=1e-14)


def test_quantisation():
    sim = PlantSim(parse_process("1/(s+1)"), 0.1, quantum=0.25)
    for _ in range(30):
        sim.advance(1.0)
        pv, true = sim.measure(), sim.true_pv()
        assert pv / 0.25 == round(pv / 0.25)
        assert abs(pv - true) <= 0.125 + 1e-15
    assert sim.measure() == 1.0  # true value ≈ 0.95


def test_mv_limits_clip_and_report_applied_value():
    process = parse_process("exp(-0.15*s)/(2*s+1)")
    sim = PlantSim(process, 0.1, mv_limits=(-1.0, 2.0))
    requested = [5.0, 1.5, -3.0, 0.0] * 10
    applied = []
    y = []
    for mv in requested:
        y.append(sim.true_pv())
        applied.append(sim.advance(mv))
    assert applied[:4] == [2.0, 1.5, -1.0, 0.0]
    np.testing.assert_allclose(y, simulate_open_loop(process, np.array(applied), 0.1)[:-1], atol=1e-15)


def test_operating_point_and_load_steps():
    process = parse_process("1.5*exp(-0.7*s)/(4*s+1)")
    ts = 0.1
    sim = PlantSim(process, ts, pv0=50.0, mv0=30.0, loads=[(1.0, 0.5), (2.05, -2.0)])
    y = []
    for _ in range(300):
        y.append(sim.true_pv())
        sim.advance(30.0)
    # equivalent MV deviation: +0.5 from sample 10, a further -2 from sample 21 (2.05 s rounded up)
    u = np.zeros(300)
    u[10:] += 0.5
    u[21:] -= 2.0
    np.testing.assert_allclose(np.array(y) - 50.0, simulate_open_loop(process, u, ts)[:-1], atol=1e-12)
    t = np.arange(300) * ts
    expected = 0.5 * fopdt_step(t - 1.0, 1.5, 4, 0.7) - 2.0 * fopdt_step(t - 2.1, 1.5, 4, 0.7)
    np.testing.assert_allclose(np.array(y) - 50.0, expected, atol=1e-9)


def test_starts_at_rest_and_tracks_time():
    sim = PlantSim(parse_process("exp(-0.5*s)/(s*(3*s+1))"), 0.25, pv0=3.0, mv0=10.0)
    for k in range(40):
        assert sim.t == pytest.approx(k * 0.25, abs=1e-12)
        assert sim.true_pv() == 3.0
        sim.advance(10.0)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_mv_is_rejected(bad):
    sim = PlantSim(parse_process("1/(s+1)"), 0.1)
    with pytest.raises(ValueError, match="finite"):
        sim.advance(bad)
    assert sim.t == 0.0


@pytest.mark.parametrize(
    "kwargs",
    [{"ts": 0.0}, {"ts": -1.0}, {"ts": math.nan}, {"ts": 0.1, "mv_limits": (1.0, 0.0)},
     {"ts": 0.1, "noise_std": -1.0}, {"ts": 0.1, "quantum": -0.1},
     {"ts": 0.1, "loads": [(math.nan, 1.0)]}],
)
def test_invalid_settings_are_rejected(kwargs):
    with pytest.raises(ValueError):
        PlantSim(parse_process("1/(s+1)"), **kwargs)


@pytest.mark.parametrize("expr", ["exp(-0.4*s)/(2*s-1)", "exp(-0.2*s)/(2*s-1)"])
def test_a_simulated_plc_holds_an_unstable_plant_in_auto(expr: str) -> None:
    # Its starting PI came from the 135° point, which an unstable process never reaches: k = 0.1 held the loop
    # only while it sat exactly at rest, and after `tune --config` handed it back the PV ran away (48 → −14 in 6 s).
    from drivers.simplc import SimulatedPlc

    plc = SimulatedPlc(parse_process(expr), ts=0.01)
    plc.sim.step_load(2.0)  # MV units at the process input
    pvs = []
    for _ in range(int(60.0 / plc.ts)):
        plc.tick()
        pvs.append(plc.pv)
    assert max(abs(pv - 50.0) for pv in pvs) < 10.0
    assert abs(pvs[-1] - 50.0) < 0.05
