"""The model rule under noise (issue 28): how sure a fit's point is, and the runs it ends.

A model fitted to a noisy record has a point whose standard error the linearised least squares give
(process_fit.spread); it is checked here against the scatter of the point over many noise draws of the same
record, an independent measure. Where the model holds the process its residual is the noise, white; where it
does not, the residual is smooth (its lag-1 autocorrelation near 1) and the rule leaves the run to the
estimates' rules. The field bench's "noise 2 % + load +0.15 mid" took 12.5 periods at the median before the rule;
processes of the model's family now end within six, their points within the noise tolerance's reach.
"""

from __future__ import annotations

import cmath
import math

import numpy as np
import pytest

from autotuner.engine.design.closed_loop import check_gains
from autotuner.engine.design.robustness import log_grid
from autotuner.engine.experiment import model_rule, process_fit
from autotuner.engine.experiment.record import Samples
from autotuner.engine.experiment.relay import RelayConfig
from autotuner.engine.outcome import Code
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import (EXPERIMENT_SAMPLES_PER_PERIOD, phase_frequency, result_of,
                                               run_experiment)

LAG = math.radians(135.0)
NOISE = 0.02  # σ as a share of |F(jω135)|·amp, the field bench's "noise 2 % + load"


def _square_wave_record(expr: str, periods: float) -> tuple[Samples, float, float]:
    """The noise-free record of ``expr`` under an MV of ±1 switched every half period of its 135° point from
    rest (a tenth of a period of rest first), 100 samples a period: (record, period s, |F(jω135)|)."""
    process = parse_process(expr)
    w135 = phase_frequency(process, 135.0)
    period = 2.0 * math.pi / w135
    ts = period / EXPERIMENT_SAMPLES_PER_PERIOD
    sim = PlantSim(process, ts)
    n = int(periods * EXPERIMENT_SAMPLES_PER_PERIOD)
    t = np.arange(n) * ts
    u = np.where(t < 0.1 * period, 0.0, np.where(((t - 0.1 * period) // (0.5 * period)) % 2 == 0, 1.0, -1.0))
    y = np.empty(n)
    for k in range(n):
        y[k] = sim.measure()
        sim.advance(float(u[k]))
    # (The MV of each sample holds from that sample's time on.)
    return Samples(t, y, u, t.copy()), period, abs(complex(process.freqresp(w135)))


def _point(model: process_fit.ProcessModel) -> complex:
    omega = model.frequency(LAG)
    assert omega is not None
    return complex(model.response(np.array([omega]))[0])


# The linearised error against the scatter over draws, measured (2026-12-05): 1.06–1.18 times it where the lags are
# inside their bounds; on a first-order process with dead time the second lag sits at nought in a quarter to
# four fifths of the draws, where the least squares are not linear: exp(-s)/(8*s+1) 1.06, exp(-s)/(2*s+1) 0.71
# (the error's shortfall there is what the rule's results carry: on the batch at 1 % noise its points are
# 0.17 % off at the median, 0.37 % at worst, within noise_tol's 0.4 %).
@pytest.mark.parametrize("expr, low", [("exp(-s)/(8*s+1)", 0.8), ("exp(-s)/(2*s+1)", 0.65),
                                       ("exp(-s)/(2*s+1)^2", 0.8), ("exp(-0.2*s)/((10*s+1)*(s+1))", 0.8)])
def test_the_points_standard_error_is_its_scatter_over_noise_draws(expr: str, low: float) -> None:
    record, period, gain = _square_wave_record(expr, 3.0)
    rng = np.random.default_rng(11)
    points, spreads, correlations = [], [], []
    for _ in range(120):
        noisy = Samples(record.t, record.y + rng.normal(0.0, NOISE * gain, len(record.y)), record.u, record.s)
        model = process_fit.fit(noisy, 0.0, period, NOISE * gain)
        assert model is not None
        spread = process_fit.spread(noisy, 0.0, period, model, LAG)
        assert spread is not None
        points.append(_point(model))
        spreads.append(spread.point)
        correlations.append(spread.correlation)
    points = np.array(points)
    scatter = math.sqrt(float(np.mean(np.abs(points - points.mean()) ** 2))) / abs(points.mean())
    # 120 draws: the scatter's own standard error is about 7 %.
    assert low * scatter <= float(np.mean(spreads)) <= 1.25 * scatter
    # The residual of a model that holds the process is the noise: white (its lag-1 autocorrelation scatters by
    # 1/√samples about nought); it passes for it but in the few fits whose search settled in another minimum (3 of
    # 120 on exp(-s)/(2*s+1), misfit 1.4 times the others', correlation up to 0.48: the rule is right to leave them).
    correlations = np.array(correlations)
    typical = 1.4826 * float(np.median(np.abs(correlations - np.median(correlations))))
    assert abs(float(np.median(correlations))) <= 1.0 / math.sqrt(len(record.t))
    assert typical == pytest.approx(1.0 / math.sqrt(len(record.t)), rel=0.25)
    assert np.mean([model_rule.white(process_fit.Spread(0.0, r, len(record.t))) for r in correlations]) >= 0.97


@pytest.mark.parametrize("expr", ["1/(s+1)^3", "1/((s+1)*(0.5*s+1)^2)", "1/((s+1)*(0.64*s^2+1.12*s+1))"])
def test_a_residual_the_model_does_not_explain_is_smooth(expr: str) -> None:
    record, period, gain = _square_wave_record(expr, 3.0)
    rng = np.random.default_rng(5)
    noisy = Samples(record.t, record.y + rng.normal(0.0, NOISE * gain, len(record.y)), record.u, record.s)
    model = process_fit.fit(noisy, 0.0, period, NOISE * gain)
    assert model is not None
    spread = process_fit.spread(noisy, 0.0, period, model, LAG)
    assert spread is not None and spread.correlation > model_rule.CORRELATION


def _noisy_load_run(expr: str, noisy_rule: bool = True):
    """``expr`` under the field bench's "noise 2 % + load +0.15 mid": σ 2 % of |F(jω135)|·amp (seed 1), a load of
    0.15 × amp at the process input 3.5 periods of the 135° point after TUNE, 100 samples a period."""
    process = parse_process(expr)
    w135 = phase_frequency(process, 135.0)
    period = 2.0 * math.pi / w135
    sigma = NOISE * abs(complex(process.freqresp(w135)))
    sim = PlantSim(process, period / EXPERIMENT_SAMPLES_PER_PERIOD, noise_std=sigma, seed=1,
                   loads=[(3.5 * period, 0.15)])
    with pytest.MonkeyPatch.context() as patch:
        if not noisy_rule:
            patch.setattr(model_rule, "NOISY_PERIODS", -1)
        experiment, trace = run_experiment(sim, RelayConfig(amp=1.0, time_limit=200 * period))
    assert experiment.code is Code.OK, experiment.message
    return process, experiment.result, result_of(experiment, trace, "PI", 1.4)


# Processes of the model's family (dead time with one or two lags, two lags with dead time) that the field bench's
# "noise 2 % + load" took 10.6–13.5 periods on before the rule (main at 70ed25e).
FAMILY = [
    ("P1-004", "exp(-s)/(0.2*s+1)", lambda s: cmath.exp(-s) / (0.2 * s + 1)),
    ("P1-014", "exp(-s)/(8*s+1)", lambda s: cmath.exp(-s) / (8 * s + 1)),
    ("P2-027", "exp(-s)/(0.3*s+1)^2", lambda s: cmath.exp(-s) / (0.3 * s + 1) ** 2),
    ("P7-084", "1*exp(-0.9*s)/((1*s+1)*(0.1*s+1))", lambda s: cmath.exp(-0.9 * s) / ((s + 1) * (0.1 * s + 1))),
    ("P7-092", "2*exp(-0.7*s)/((2*s+1)*(0.3*s+1))", lambda s: 2 * cmath.exp(-0.7 * s) / ((2 * s + 1) * (0.3 * s + 1))),
]


@pytest.mark.parametrize("expr, f", [c[1:] for c in FAMILY], ids=[c[0] for c in FAMILY])
def test_a_noisy_run_with_a_load_ends_within_six_periods_as_the_noise_allows(expr: str, f) -> None:
    process, result, tuned = _noisy_load_run(expr)
    assert result.periods <= 6.0
    true = complex(f(1j * result.point.omega))
    # The rule's standard error is within noise_tol (0.4 %): within two and a half of it.
    assert abs(result.point.value - true) / abs(true) <= 0.01
    assert abs(cmath.phase(true) * 180.0 / math.pi + 135.0) <= 2.0
    assert tuned.ok and check_gains(process, tuned.design.gains, log_grid(result.point.omega)).ms <= 1.6


@pytest.mark.parametrize("expr", ["1/(s+1)^3", "(1-0.6*s)/(s+1)^3"])
def test_the_noisy_rule_leaves_a_run_its_model_does_not_explain_alone(expr: str) -> None:
    assert _noisy_load_run(expr)[1] == _noisy_load_run(expr, noisy_rule=False)[1]
