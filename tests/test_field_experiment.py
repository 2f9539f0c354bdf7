"""The experiment on a disturbed or noisy plant (issue 13): load steps, drift, noise, refusals, honest ite."""

from __future__ import annotations

import math

import numpy as np
import pytest

from autotuner.engine.design.process_data import exact_point
from autotuner.engine.experiment import model_rule
from autotuner.engine.experiment.relay import RelayConfig, RelayExperiment
from autotuner.engine.outcome import MESSAGES, Code
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import run_experiment
from autotuner.service.remote_tuning import field_config

PLANT = "exp(-s)/(s+1)"


def _run(expr: str, *, loads=(), drift_per_period: float = 0.0, noise: float = 0.0, seed: int = 1,
         on_status=None, **cfg):
    """Experiment on ``expr`` at 100 samples per period; loads in (periods, MV units), noise in |F|·amp."""
    process = parse_process(expr)
    point = exact_point(process, 135.0)
    period = 2.0 * math.pi / point.omega
    sim = PlantSim(process, period / 100.0, loads=[(k * period, size) for k, size in loads],
                   drift=drift_per_period / period, noise_std=noise * point.gain, seed=seed)
    config = RelayConfig(amp=1.0, time_limit=200.0 * period, **cfg)
    experiment, trace = run_experiment(sim, config, on_status=on_status, status_every=1)
    return experiment, trace, process


def _assert_accurate(experiment, process, static_rel: float) -> None:
    assert experiment.code is Code.OK, experiment.message
    ident = experiment.result
    true = complex(process.freqresp(ident.point.omega))
    assert abs(ident.point.value - true) / abs(true) < 0.01
    assert ident.static_gain == pytest.approx(process.static_gain(), rel=static_rel)


@pytest.mark.parametrize("size", [0.25, -0.3])
def test_a_load_step_part_way_is_estimated_through(size: float) -> None:
    # Before: "the static gain must be positive" (the step was read as static gain). At 1.2 periods: the quiet
    # run now ends at 1.8 (the model rule, model_rule.py), before a step at 2.5 reaches the PV.
    experiment, _, process = _run(PLANT, loads=[(1.2, size)])
    _assert_accurate(experiment, process, 0.1)
    ident = experiment.result
    assert ident.disturbance and ident.load_estimate == pytest.approx(size, abs=0.05)


def test_the_relays_centre_follows_a_large_load_and_stays_for_a_small_one(monkeypatch: pytest.MonkeyPatch) -> None:
    # A quiet run takes a followed load's share out of its estimates (load_correction.py): the centre moves only
    # for a load beyond half the weaker level's amplitude (0.3 × amp at bias 0.2); every move is a transient.
    # (The model rule, model_rule.py, ends the quiet run at 1.8 periods, before a step at 2.5 shows; earlier, a
    # large step is estimated through before the centre has moved. The rule tries no fit here: the steps come at
    # 2.5 periods, within the run the estimates' rules take.)
    monkeypatch.setattr(model_rule, "PERIODS", 0)
    small, small_trace, process = _run(PLANT, loads=[(2.5, 0.2)])
    _assert_accurate(small, process, 0.02)
    assert small.result.load_estimate == pytest.approx(0.2, abs=0.01)
    # The relay's own levels, mv0 + amp and mv0 − amp·(1 − 2·bias), the whole run long.
    assert small_trace.mv.max() <= 1.0 + 1e-9 and small_trace.mv.min() >= -0.6 - 1e-9
    large, large_trace, process = _run(PLANT, loads=[(2.5, 0.45)])
    _assert_accurate(large, process, 0.02)
    # The centre followed the load: the MV ends around mv0 − load, its low level beyond the relay's own.
    assert abs(large_trace.mv[-200:].mean() + 0.45) < 0.5 and large_trace.mv.min() < -1.0


@pytest.mark.parametrize("expr", ["exp(-s)/(2*s+1)", "exp(-s)/(50*s+1)^2"])
def test_a_small_load_step_against_the_bias_is_not_taken_for_a_resonance(expr: str,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    # −0.1 × amp at 3.5 periods made the period ratio |F|/K0 read 1.4–1.5 (1.0–1.09 on the slow
    # one): the fit that had found the step was then skipped as "a resonance", and the runs ended
    # "ok" with K0 0.26 and 0.15 (true 1) and Ms 1.78 and 5.99 on the true plant. The quiet run of the
    # first now ends at 3.7 periods, before a step at 3.5 shows: the step comes at 2.5, where a
    # one-period ratio read 1.3–1.5 from the next estimate on and only the first (0.39) below 1.
    # (The model rule, model_rule.py, ends the quiet run of the first at 2.2 periods, before a step at 2.5 shows: it
    # tries no fit here.)
    monkeypatch.setattr(model_rule, "PERIODS", 0)
    experiment, _, process = _run(expr, loads=[(2.5, -0.1)])
    _assert_accurate(experiment, process, 0.1)  # as for the other load steps
    assert experiment.result.disturbance


@pytest.mark.parametrize(("expr", "at"), [("exp(-s)/(2*s+1)", 0.8), ("exp(-s)/(2*s+1)", 1.2),
                                         ("exp(-s)/(2*s+1)", 1.5), ("exp(-s)/(s+1)^2", 1.2),
                                         ("(1-0.6*s)/(s+1)^3", 1.2)])
def test_an_early_small_load_step_against_the_bias_is_estimated_through(expr: str, at: float) -> None:
    # −0.1 × amp before the first estimate: every estimate's |F|/K0 read 1.4–1.8, none below 1, the fit that
    # had found the step (|F|/K0 0.391 ± 0.008 at 1.2 on the first) was skipped as "a resonance", and the runs
    # ended "ok" after 4.6–6.7 periods with K0 0.26–0.32 (true 1) and no disturbance. On the first at 0.8 the
    # step time, between the search's grid points, was refined apart from |F|/K0: 0.83 periods and K0 0.947.
    # On the others the fit is unsure (± 0.04–0.05): a resonance's model tells the load from a resonance.
    experiment, _, process = _run(expr, loads=[(at, -0.1)])
    _assert_accurate(experiment, process, 0.05)
    assert experiment.result.disturbance and experiment.result.load_estimate == pytest.approx(-0.1, abs=0.01)


def test_a_resonance_is_not_taken_for_a_load() -> None:
    # |F|/K0 1.68 at the 135° point: the estimates read above 1 as under a load against the bias, and the fit
    # invents one (|F|/K0 0.33–0.59 ± 0.10–0.23), which the resonance's own model, with no load, explains better.
    experiment, _, process = _run("exp(-0.1*s)/(s^2+0.4*s+1)")
    _assert_accurate(experiment, process, 0.01)
    assert not experiment.result.disturbance


def test_a_load_that_cancels_the_bias_on_a_dead_time_process_is_not_taken_for_a_resonance() -> None:
    # −0.2 × amp cancels the relay's mean: |F|/K0 ran away above 1 (1.1, 1.8, 2.9, 5.9, …) with |F|
    # unchanged, the load fit was skipped as "a resonance" and the run ended with ite 11. At 2.8 periods: the
    # quiet run ended at 3.31, before a step at 3.3 reached the PV; since the model rule (model_rule.py), at 1.8: the
    # step comes at 1.2.
    experiment, _, process = _run("exp(-s)/(0.05*s+1)^2", loads=[(1.2, -0.2)])
    _assert_accurate(experiment, process, 0.05)
    assert experiment.result.disturbance


@pytest.mark.parametrize("expr", ["exp(-s)/(2*s+1)", "2*exp(-0.5*s)/((2*s+1)*(0.5*s+1))"])
def test_an_early_load_step_is_not_taken_for_an_unstable_process(expr: str) -> None:
    # +0.2 × amp at 1.5 periods makes the first mean ratios negative, as an unstable process's are;
    # the process was then treated as unstable (phase target moved to 150–160°) and the run ended
    # with 11 or 17.
    experiment, _, process = _run(expr, loads=[(1.5, 0.2)])
    _assert_accurate(experiment, process, 0.1)
    assert experiment.result.disturbance and not experiment.result.phase_moved


def test_an_integrating_process_with_an_early_load_is_not_taken_for_an_unstable_one() -> None:
    # Both load fits (stable and unstable x ranges) share the integrator x = 0 and tie; it was run as
    # unstable (phase target 160°, K0 −2.7) and ended "ok" with Ms 1.97 on the true plant.
    experiment, _, process = _run("exp(-0.02*s)/(s*(0.98*s+1))", loads=[(1.5, 0.2)])
    assert experiment.code is Code.OK, experiment.message
    ident = experiment.result
    true = complex(process.freqresp(ident.point.omega))
    assert abs(ident.point.value - true) / abs(true) < 0.01
    assert math.isinf(ident.static_gain) and not ident.phase_moved and ident.disturbance


def test_a_drift_is_followed_and_estimated_through() -> None:
    # 0.3 × amp over 10 periods at the process input.
    experiment, _, process = _run("1/(s+1)^4", drift_per_period=0.03)
    _assert_accurate(experiment, process, 0.1)
    assert experiment.result.disturbance


def test_a_drift_beyond_amp_is_refused_with_the_disturbance_code() -> None:
    experiment, _, _ = _run(PLANT, drift_per_period=0.2)
    assert experiment.code is Code.DISTURBANCE
    assert experiment.message.startswith(MESSAGES[Code.DISTURBANCE])
    assert "× amp" in experiment.message or "larger than amp" in experiment.message


def test_a_quiet_run_reports_no_disturbance() -> None:
    experiment, _, process = _run(PLANT)
    _assert_accurate(experiment, process, 0.02)
    assert not experiment.result.disturbance and experiment.result.periods_discarded == 0


@pytest.mark.parametrize("seed", [1, 2])
def test_five_percent_noise_converges(seed: int) -> None:
    # Before: 4 of 35 runs converged at 5 % noise (σ over |F(jω)|·amp).
    experiment, _, process = _run("exp(-5*s)/(s+1)", noise=0.05, seed=seed)
    _assert_accurate(experiment, process, 0.1)


@pytest.mark.parametrize("expr", ["exp(-s)/(8*s+1)", "exp(-s)/(100*s+1)"])
@pytest.mark.parametrize("seed", [1, 2])
def test_five_percent_noise_converges_on_lag_dominant_processes(expr: str, seed: int) -> None:
    # At noise_tol 0.25 % the second refused with NOISE_TOO_HIGH after 25 periods (seed 2).
    experiment, _, process = _run(expr, noise=0.05, seed=seed)
    assert experiment.code is Code.OK, experiment.message
    ident = experiment.result
    true = complex(process.freqresp(ident.point.omega))
    assert abs(ident.point.value - true) / abs(true) < 0.015
    assert ident.static_gain == pytest.approx(process.static_gain(), rel=0.05)


@pytest.mark.parametrize("expr", [PLANT, "exp(-s)/(0.5*s+1)", "5*exp(-0.7*s)/((5*s+1)*(0.3*s+1))",
                                  "1/((s+1)*(0.81*s^2+1.26*s+1))"])
def test_a_quiet_run_ends_within_five_periods_with_its_point_and_static_gain_exact(expr: str) -> None:
    # The third and fourth took 5.5 periods before the settled static ratio, the slope rule and the
    # half-period check; a half-period check at the full tolerances stopped the third at 3.95 periods
    # with 1.2 % point error.
    experiment, _, process = _run(expr)
    assert experiment.code is Code.OK, experiment.message
    ident = experiment.result
    true = complex(process.freqresp(ident.point.omega))
    assert ident.periods <= 5.0
    assert abs(ident.point.value - true) / abs(true) < 0.005
    assert ident.static_gain == pytest.approx(process.static_gain(), rel=0.01)


@pytest.mark.parametrize("expr", ["exp(-s)/(2*s+1)", "2*exp(-0.5*s)/((2*s+1)*(0.5*s+1))"])
def test_a_start_while_the_pv_still_settles_gives_the_static_gain_and_says_so(expr: str) -> None:
    # A load step of 0.2 × amp half a period before TUNE: the plain ratio of the means read K0 3.8
    # (first process) and 96 (second, true 2) — the settling PV added to the relay's response.
    process = parse_process(expr)
    point = exact_point(process, 135.0)
    period = 2.0 * math.pi / point.omega
    sim = PlantSim(process, period / 100.0, loads=[(0.0, 0.2)])
    for _ in range(50):
        sim.advance(sim.mv0)
    experiment, _ = run_experiment(sim, RelayConfig(amp=1.0, time_limit=200.0 * period))
    assert experiment.code is Code.OK, experiment.message
    ident = experiment.result
    assert ident.disturbance
    assert ident.static_gain == pytest.approx(process.static_gain(), rel=0.15)


def test_noise_out_of_reach_is_refused_saying_how_much_to_raise_amp() -> None:
    experiment, _, _ = _run("exp(-5*s)/(s+1)", noise=0.05, seed=1, max_periods=8, noise_tol=0.0005)
    assert experiment.code is Code.NOISE_TOO_HIGH
    assert "raise amp to at least" in experiment.message and "× " in experiment.message


def test_ite_is_positive_from_the_first_sample_and_progress_never_goes_back() -> None:
    statuses = []
    experiment, trace, _ = _run(PLANT, on_status=statuses.append)
    assert experiment.code is Code.OK
    running = [s for s in statuses if s.code is None]
    assert running and all(s.ite > 0.0 for s in running)
    progress = [s.progress for s in statuses]
    assert all(b >= a for a, b in zip(progress, progress[1:]))
    # The first estimate is within a factor of two of the real length.
    assert 0.5 * trace.t[-1] < running[0].ite < 2.0 * trace.t[-1]


def _stalling_session(expr: str, seed: int, loads=(), stalls=(0.01, 2, 6), sub: int = 10):
    """The experiment as a field session runs it: 50 samples per period taken with ±30 % jitter, and at
    a share of the samples a stall (``stalls``: share, shortest and longest in samples) between the PV's
    read and the MV's write (a busy machine, a slow link) — the process holds the previous MV meanwhile,
    and the session says when the write landed (``applied``). Loads in (periods, MV units). The plant
    runs ``sub`` ticks per sample."""
    process = parse_process(expr)
    period = 2.0 * math.pi / exact_point(process, 135.0).omega
    ts = period / 50.0
    sim = PlantSim(process, ts / sub, loads=[(k * period, size) for k, size in loads])
    rng = np.random.default_rng(seed)
    config = field_config(RelayConfig(amp=1.0, time_limit=200.0 * period))
    experiment = RelayExperiment(config, mv0=0.0)
    mv = 0.0
    while not experiment.done:
        new = experiment.step(sim.t, sim.measure())
        share, shortest, longest = stalls
        stall = int(rng.integers(shortest * sub, longest * sub)) if rng.random() < share else 0
        for _ in range(stall):
            sim.advance(mv)
        mv = new
        experiment.applied(sim.t)
        for _ in range(sub + int(rng.integers(-3, 4))):
            sim.advance(mv)
    return experiment, process


@pytest.mark.parametrize(("expr", "seed", "stalls"), [
    ("exp(-s)/(2*s+1)", 0, (0.01, 2, 6)), ("exp(-s)/(2*s+1)", 1, (0.01, 2, 6)), ("exp(-s)/(2*s+1)", 2, (0.01, 2, 6)),
    # Stalls of 20–50 % of a period: recorded as if the writes had landed on time, this record made the
    # fit find a load of −0.19 and K0 3.9 times too small, reported "ok".
    ("exp(-0.3*s)/(2*s+1)^2", 3, (0.006, 10, 25)),
    # An estimate whose windows held such a stall was judged like any other: this one ended "ok" with K0 18 %
    # low (no load fitted). Such estimates are left out now.
    ("exp(-0.3*s)/(2*s+1)^2", 1, (0.006, 10, 25)),
])
def test_a_stalling_session_invents_no_load(expr: str, seed: int, stalls: tuple[float, int, int]) -> None:
    # A write held up by a stall looks, in a record that says it landed on time, like a load step (why load
    # following was off over links). With the writes' times the record is what the process got.
    experiment, process = _stalling_session(expr, seed, stalls=stalls)
    assert experiment.code is Code.OK, experiment.message
    assert not experiment.result.disturbance
    assert experiment.result.static_gain == pytest.approx(process.static_gain(), rel=0.03)


@pytest.mark.parametrize(("seed", "size"), [(0, 0.2), (1, 0.2), (2, -0.3)])
def test_a_load_step_is_estimated_through_while_the_session_stalls(seed: int, size: float) -> None:
    # Load following on over a link: the step is found and followed, K0 comes through it. Without load
    # following (as over links before) the +0.2 records ended "ok" with K0 −2.3 and −2.1 (true 1), the
    # −0.3 one with code 4.
    experiment, process = _stalling_session("exp(-s)/(2*s+1)", seed, loads=[(3.5, size)])
    assert experiment.code is Code.OK, experiment.message
    ident = experiment.result
    assert ident.disturbance and ident.load_estimate == pytest.approx(size, abs=0.03)
    assert ident.static_gain == pytest.approx(process.static_gain(), rel=0.05)


def test_a_session_that_stalls_every_period_is_refused_saying_so() -> None:
    # Stalls of 16–24 % of a period at 5 % of the samples: hardly an estimate without one. The refusal names
    # the stalls, not the process ("out of reach of this process?" was the message).
    experiment, _ = _stalling_session("exp(-s)/(2*s+1)", 0, stalls=(0.05, 8, 12))
    assert experiment.code is Code.NOT_CONVERGED
    assert "without samples" in experiment.message and "too slow for this sample time" in experiment.message
    assert "out of reach" not in experiment.message
