"""The relay + adaptive phase filter experiment against analytic frequency responses."""

from __future__ import annotations

import cmath
import gc
import math
import pickle
import weakref

import numpy as np
import pytest

from autotuner.engine.plant.expression import parse_process
from autotuner.engine.outcome import Code
from autotuner.engine.experiment.relay import RelayConfig, RelayExperiment, Stage
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import phase_frequency, run_experiment


def analytic(expr_fn, w: float) -> complex:
    """Evaluate an independent closed-form F(jω)."""
    return complex(expr_fn(1j * w))


def identify(expr: str, *, phase: float = 135.0, noise: float = 0.0, loads=(), per_period: int = 100, **cfg):
    process = parse_process(expr)
    w = phase_frequency(process, phase)
    ts = 2 * math.pi / w / per_period
    sim = PlantSim(process, ts, noise_std=noise, seed=3, loads=loads)
    config = RelayConfig(amp=1.0, phase_deg=phase, time_limit=300 * 2 * math.pi / w, **cfg)
    experiment, trace = run_experiment(sim, config)
    return experiment, trace, w


CASES = [
    # expression, independent F(s), static gain
    ("1.5*exp(-0.73*s)/(4*s+1)", lambda s: 1.5 * cmath.exp(-0.73 * s) / (4 * s + 1), 1.5),
    ("1/((s+1)*(4*s+1))", lambda s: 1 / ((s + 1) * (4 * s + 1)), 1.0),  # never reaches 180°
    ("(1-0.6*s)/(2*s+1)^3", lambda s: (1 - 0.6 * s) / (2 * s + 1) ** 3, 1.0),  # non-minimum phase
    ("exp(-0.5*s)/(s*(s+1))", lambda s: cmath.exp(-0.5 * s) / (s * (s + 1)), math.inf),  # integrating
    ("100*exp(-20*s)/(300*s+1)", lambda s: 100 * cmath.exp(-20 * s) / (300 * s + 1), 100.0),  # slow
]


@pytest.mark.parametrize("expr, f, k0", CASES, ids=[c[0] for c in CASES])
def test_point_matches_analytic_response(expr, f, k0):
    experiment, _, _ = identify(expr)
    assert experiment.code is Code.OK, experiment.message
    result = experiment.result
    true = analytic(f, result.point.omega)
    assert abs(result.point.value - true) / abs(true) < 0.01
    assert abs(result.point.phase_deg + 135.0) < 1.0
    if math.isinf(k0):
        assert math.isinf(result.static_gain)
    else:
        assert result.static_gain == pytest.approx(k0, rel=0.05)
    assert result.periods < 15


@pytest.mark.parametrize("phase", [90.0, 110.0, 150.0, 170.0])
def test_any_phase_between_90_and_170(phase):
    f = CASES[0][1]
    experiment, _, _ = identify(CASES[0][0], phase=phase)
    assert experiment.code is Code.OK, experiment.message
    point = experiment.result.point
    true = analytic(f, point.omega)
    assert abs(point.value - true) / abs(true) < 0.01
    assert abs(point.phase_deg + phase) < 1.0


@pytest.mark.parametrize("expr, f, _k0", CASES[:4], ids=[c[0] for c in CASES[:4]])
def test_measurement_noise_of_one_percent(expr, f, _k0):
    process = parse_process(expr)
    w = phase_frequency(process, 135.0)
    # Noise of 1 % of the PV oscillation amplitude (≈ 4/π·amp·|F| for a relay).
    sigma = 0.01 * 4 / math.pi * abs(process.freqresp(w))
    experiment, _, _ = identify(expr, noise=sigma)
    assert experiment.code is Code.OK, experiment.message
    result = experiment.result
    true = analytic(f, result.point.omega)
    assert abs(result.point.value - true) / abs(true) < 0.03
    assert result.hysteresis > 0.0  # measured from the noise, not left at zero
    assert result.noise_std == pytest.approx(sigma, rel=0.5)


def test_load_step_during_the_experiment():
    expr, f, _ = CASES[0]
    experiment, trace, w = identify(expr, loads=[(3 * 2 * math.pi / 0.5, 0.3)])
    assert experiment.code is Code.OK, experiment.message
    true = analytic(f, experiment.result.point.omega)
    assert abs(experiment.result.point.value - true) / abs(true) < 0.01


def test_integrating_process_with_constant_load_oscillates_asymmetrically():
    # The load must be balanced by the mean MV: the relay's duty cycle becomes uneven.
    expr, f, _ = CASES[3]
    experiment, trace, _ = identify(expr, loads=[(0.0, 0.25)])
    assert experiment.code is Code.OK, experiment.message
    true = analytic(f, experiment.result.point.omega)
    assert abs(experiment.result.point.value - true) / abs(true) < 0.01
    tail = trace.mv[len(trace.mv) // 2 :]
    high = np.mean(tail > 0.5)
    assert high < 0.3  # u = +1 for < 30 % of the time, against 37.5 % without the load


def test_reverse_acting_loop_identifies_the_direct_equivalent():
    f = lambda s: -cmath.exp(-s) / (2 * s + 1)  # noqa: E731
    process = parse_process("-exp(-s)/(2*s+1)")
    w = phase_frequency(parse_process("exp(-s)/(2*s+1)"), 135.0)
    sim = PlantSim(process, 2 * math.pi / w / 100)
    experiment, _ = run_experiment(sim, RelayConfig(amp=1.0, reverse=True, time_limit=1000.0))
    assert experiment.code is Code.OK, experiment.message
    point = experiment.result.point
    assert abs(point.value + analytic(f, point.omega)) / abs(point.value) < 0.01
    assert experiment.result.static_gain == pytest.approx(1.0, rel=0.05)


def test_mv_stays_within_amp_of_the_start_and_returns_to_it():
    experiment, trace, _ = identify(CASES[0][0])
    mv0 = experiment.mv0
    assert np.all(trace.mv <= mv0 + 1.0 + 1e-12)
    assert np.all(trace.mv >= mv0 - 1.0 - 1e-12)
    assert experiment.step(trace.t[-1] + 1.0, 0.0) == mv0


def test_status_counts_down_and_reports_the_code_at_the_end():
    process = parse_process(CASES[0][0])
    w = phase_frequency(process, 135.0)
    sim = PlantSim(process, 2 * math.pi / w / 100)
    experiment = RelayExperiment(RelayConfig(amp=1.0), mv0=0.0)
    lefts, progress = [], []
    while not experiment.done:
        sim.advance(experiment.step(sim.t, sim.measure()))
        status = experiment.status()
        if status.stage is Stage.RELAY and status.periods >= 1:
            lefts.append(status.ite)
        progress.append(status.progress)
    assert all(0.0 <= p <= 1.0 for p in progress)
    # Once the period is known, the estimate falls as the experiment proceeds.
    assert lefts[-1] < lefts[0]
    end = experiment.status()
    assert end.stage is Stage.DONE and end.ite == 0 and end.code is Code.OK


def test_deterministic_for_the_same_samples():
    a, ta, _ = identify(CASES[2][0], noise=0.001)
    b, tb, _ = identify(CASES[2][0], noise=0.001)
    assert a.result == b.result
    assert np.array_equal(ta.mv, tb.mv)


# -- each error path -----------------------------------------------------------


def run_until_done(experiment: RelayExperiment, sim: PlantSim, limit: int = 200000) -> None:
    for _ in range(limit):
        mv = experiment.step(sim.t, sim.measure())
        if experiment.done:
            return
        sim.advance(mv)
    raise AssertionError("experiment did not end")


def test_abort_ends_with_code_1_and_restores_the_mv():
    sim = PlantSim(parse_process("exp(-s)/(2*s+1)"), 0.05, mv0=3.0)
    experiment = RelayExperiment(RelayConfig(amp=1.0), mv0=3.0)
    for _ in range(200):
        sim.advance(experiment.step(sim.t, sim.measure()))
    assert experiment.stage is Stage.RELAY
    experiment.abort()
    assert experiment.code is Code.ABORTED and experiment.status().ite == 1
    assert experiment.step(sim.t, sim.measure()) == 3.0
    assert experiment.result is None


def test_pv_out_of_limits():
    sim = PlantSim(parse_process("exp(-s)/(2*s+1)"), 0.05)
    experiment = RelayExperiment(RelayConfig(amp=1.0, pv_limits=(-0.2, 0.2)), mv0=0.0)
    run_until_done(experiment, sim)
    assert experiment.code is Code.PV_OUT_OF_LIMITS
    assert "limits" in experiment.message


def test_no_oscillation_when_the_hysteresis_is_never_crossed():
    sim = PlantSim(parse_process("exp(-s)/(2*s+1)"), 0.05)
    experiment = RelayExperiment(RelayConfig(amp=0.1, hysteresis=5.0, time_limit=100.0), mv0=0.0)
    run_until_done(experiment, sim)
    assert experiment.code is Code.NO_OSCILLATION


def test_not_converged_when_the_phase_is_out_of_reach():
    # An integrator never lags less than 90°: the cycle drifts to ever lower frequencies.
    sim = PlantSim(parse_process("exp(-0.5*s)/(s*(s+1))"), 0.08)
    experiment = RelayExperiment(RelayConfig(amp=1.0, phase_deg=90.0, time_limit=3000.0), mv0=0.0)
    run_until_done(experiment, sim)
    assert experiment.code is Code.NOT_CONVERGED
    assert "90° was requested" in experiment.message


def test_not_converged_after_max_periods():
    # Lag-dominant and of third order (two lags and a dead time, the model rule's, would stop it within two
    # periods): its first estimates are still converging after 3 periods.
    sim = PlantSim(parse_process("10*exp(-0.3*s)/((10*s+1)*(0.7*s+1)*(0.3*s+1))"), 0.05)
    experiment = RelayExperiment(RelayConfig(amp=1.0, max_periods=3), mv0=0.0)
    run_until_done(experiment, sim)
    assert experiment.code is Code.NOT_CONVERGED


@pytest.mark.parametrize("t, pv", [(1.0, math.nan), (1.0, math.inf), (math.nan, 0.0)])
def test_bad_sample(t, pv):
    experiment = RelayExperiment(RelayConfig(amp=1.0), mv0=2.0)
    experiment.step(0.0, 0.0)
    assert experiment.step(t, pv) == 2.0
    assert experiment.code is Code.BAD_SAMPLE


def test_timestamps_must_increase():
    experiment = RelayExperiment(RelayConfig(amp=1.0), mv0=0.0)
    experiment.step(1.0, 0.0)
    experiment.step(1.0, 0.0)
    assert experiment.code is Code.BAD_SAMPLE
    assert "does not follow" in experiment.message


def test_mv_at_its_limit_cannot_be_moved():
    experiment = RelayExperiment(RelayConfig(amp=1.0, mv_limits=(0.0, 100.0)), mv0=100.0)
    assert experiment.done and experiment.code is Code.MV_RANGE


def test_relay_is_clipped_to_mv_limits():
    sim = PlantSim(parse_process("exp(-s)/(2*s+1)"), 0.05, mv0=99.5)
    experiment = RelayExperiment(RelayConfig(amp=1.0, mv_limits=(0.0, 100.0)), mv0=99.5)
    mvs = []
    for _ in range(2000):
        mv = experiment.step(sim.t, sim.measure())
        if experiment.done:
            break
        mvs.append(mv)
        sim.advance(mv)
    assert max(mvs) <= 100.0


@pytest.mark.parametrize(
    "kwargs, word",
    [
        ({"amp": 0.0}, "amp"),
        ({"amp": math.nan}, "amp"),
        ({"amp": 1.0, "phase_deg": 80.0}, "phase"),
        ({"amp": 1.0, "phase_deg": 175.0}, "phase"),
        ({"amp": 1.0, "hysteresis": -1.0}, "hysteresis"),
        ({"amp": 1.0, "bias": 0.5}, "bias"),
        ({"amp": 1.0, "time_limit": 0.0}, "time limit"),
        ({"amp": 1.0, "pv_limits": (1.0, 0.0)}, "pv_limits"),
        ({"amp": 1.0, "phase_tol_deg": 0.0}, "phase_tol_deg"),  # was a ZeroDivisionError in ite, samples later
        ({"amp": 1.0, "gain_tol": -0.01}, "gain_tol"),
        ({"amp": 1.0, "static_tol": math.inf}, "static_tol"),
        ({"amp": 1.0, "noise_tol": math.nan}, "noise_tol"),
        ({"amp": 1.0, "max_periods": 0}, "max_periods"),
    ],
)
def test_config_errors_name_the_setting(kwargs, word):
    with pytest.raises(ValueError, match=word):
        RelayConfig(**kwargs)


def test_a_fault_reported_from_outside_ends_the_experiment():
    sim = PlantSim(parse_process("exp(-s)/(2*s+1)"), 0.05, mv0=1.0)
    experiment = RelayExperiment(RelayConfig(amp=1.0), mv0=1.0)
    for _ in range(100):
        sim.advance(experiment.step(sim.t, sim.measure()))
    experiment.fail(Code.LINK_FAULT, "Modbus timeout")
    assert experiment.code is Code.LINK_FAULT and experiment.message == "Modbus timeout"
    assert experiment.status().ite == int(Code.LINK_FAULT)
    assert experiment.step(sim.t, sim.measure()) == 1.0
    experiment.abort()  # a later TBRK does not overwrite the first outcome
    assert experiment.code is Code.LINK_FAULT


def test_mv_rate_limit_is_respected_and_the_point_still_exact():
    expr, f, _ = CASES[0]
    process = parse_process(expr)
    w = phase_frequency(process, 135.0)
    ts = 2 * math.pi / w / 100
    rate = 2.0 / (0.05 * 2 * math.pi / w)  # a full relay swing takes 5 % of a period
    sim = PlantSim(process, ts)
    experiment, trace = run_experiment(sim, RelayConfig(amp=1.0, mv_rate=rate, time_limit=1000.0))
    assert experiment.code is Code.OK, experiment.message
    steps = np.abs(np.diff(trace.mv[:-1]))
    assert steps.max() <= rate * ts * (1 + 1e-9)
    assert steps.max() > 0.9 * rate * ts  # the limit was active
    point = experiment.result.point
    true = analytic(f, point.omega)
    assert abs(point.value - true) / abs(true) < 0.01


def test_an_experiment_holds_no_reference_cycle_so_a_replaced_copy_is_freed_at_once():
    """A daemon's sampler sends each period's analysis to a worker and goes on with the analysed copy; the copy it
    replaces must be freed by reference counting. Held in a cycle (its pending analysis was a bound method of
    itself), every such copy waited for a full collection: at 100 loops those walked ~57 000 dead objects each,
    70 ms with the sampler's event loop stopped."""
    sim = PlantSim(parse_process("exp(-s)/(10*s+1)"), 0.1, noise_std=0.002, seed=3)
    experiment = RelayExperiment(RelayConfig(amp=1.0), mv0=0.0)
    t, mv, copies = 0.0, 0.0, 0
    gc.collect()
    gc.disable()
    try:
        while not experiment.done:
            mv = experiment.step(t, sim.measure())
            if experiment.analysis_pending:
                replaced = weakref.ref(experiment)
                experiment = pickle.loads(pickle.dumps(experiment))  # as a worker's analysis returns it
                experiment.analyse()
                assert replaced() is None, f"the copy replaced at t={t:.1f} s is still alive"
                copies += 1
            sim.advance(mv)
            t += 0.1
        assert experiment.code == Code.OK and experiment.result is not None and copies >= 4
        finished = weakref.ref(experiment)
        del experiment
        assert finished() is None
    finally:
        gc.enable()
