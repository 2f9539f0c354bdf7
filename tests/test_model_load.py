"""The model rule through a load at the process input (issue 28): a drift from TUNE or an early load step.

Where the two-lag-and-dead-time model misfits the record, the fit adds the model's response to a load at the
process input (process_fit.fit_load: a ramp from the record's start, or a step at a time of its own). On two
processes of the model's family the run then ends within THREE periods with the model's point, its static gain
within 2 % and the load it reports within 0.01 × amp of the simulated one, all against the true simulation; on
three lags (outside the family) the load terms change nothing, run for run.
"""

from __future__ import annotations

import cmath
import math

import numpy as np
import pytest

from autotuner.engine.experiment import process_fit
from autotuner.engine.experiment.relay import Identification, RelayConfig
from autotuner.engine.outcome import Code
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import EXPERIMENT_SAMPLES_PER_PERIOD, phase_frequency, run_experiment

THREE = 3.0  # periods (measured: 1.5–2.5 on these cases; the plain rule's clean runs take 1.8–2.2)

PROCESSES = [  # expression, the same F(s) in closed form, static gain
    ("exp(-s)/(2*s+1)", lambda s: cmath.exp(-s) / (2 * s + 1), 1.0),
    # P7-108: main ends a +0.1 step at 1.2 periods "ok" with K0 −3.88 (field-benchmark.md).
    ("10*exp(-0.3*s)/((10*s+1)*(0.7*s+1))", lambda s: 10 * cmath.exp(-0.3 * s) / ((10 * s + 1) * (0.7 * s + 1)),
     10.0),
]
LOADS = [  # (step time in periods, step size × amp) or None, drift × amp per period
    (None, 0.03),
    (None, -0.03),
    ((1.2, 0.1), 0.0),
    ((0.8, -0.3), 0.0),
]


def _run(expr: str, step: tuple[float, float] | None, drift: float) -> tuple[Identification, float]:
    """The result on ``expr`` at the bench's conditions (amp 1) with the load ``step`` (periods, MV units) and
    ``drift`` (MV units per period), and the simulated load at its last sample (MV units); it must end "ok"."""
    process = parse_process(expr)
    period = 2.0 * math.pi / phase_frequency(process, 135.0)
    loads = [] if step is None else [(step[0] * period, step[1])]
    sim = PlantSim(process, period / EXPERIMENT_SAMPLES_PER_PERIOD, loads=loads, drift=drift / period)
    experiment, trace = run_experiment(sim, RelayConfig(amp=1.0, time_limit=200 * period))
    assert experiment.code is Code.OK, experiment.message
    # (The load held from the last sample on, as the plant applies it: simulation.PlantSim.advance.)
    load = (0.0 if step is None else step[1]) + sim.drift * float(trace.t[-1])
    return experiment.result, load


@pytest.mark.parametrize(("expr", "f", "k0"), PROCESSES)
@pytest.mark.parametrize(("step", "drift"), LOADS)
def test_a_drift_or_an_early_step_ends_soon_with_the_model_and_the_load(expr, f, k0, step, drift) -> None:
    result, load = _run(expr, step, drift)
    assert result.periods <= THREE
    true = complex(f(1j * result.point.omega))
    assert abs(result.point.value - true) / abs(true) <= 0.002
    assert result.static_gain == pytest.approx(k0, rel=0.02)
    assert result.disturbance
    assert result.load_estimate == pytest.approx(load, abs=0.01)


@pytest.mark.parametrize(("step", "drift"), [((1.2, 0.2), 0.0), (None, 0.03)])
def test_the_load_terms_leave_a_record_outside_the_models_family_alone(step, drift,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    # Three lags misfit the model by 2–4 % of the swing, with the load terms by 2–3 % (the rule's bound is 3e-4):
    # the rule stops none of these runs, whose result is the same without the load terms.
    with_terms = _run("1/(s+1)^3", step, drift)
    # (A load fit that finds nothing better than the plain model: the rule as it was before the load terms.)
    monkeypatch.setattr(process_fit, "fit_load", lambda history, mv0, period, plain, *args: plain)
    assert _run("1/(s+1)^3", step, drift) == with_terms


@pytest.mark.parametrize(("t1", "t2"), [(2.0, 0.0), (2.0, 2.0), (2.0, 0.5)])
def test_the_ramp_response_is_the_integral_of_the_step_response(t1: float, t2: float) -> None:
    t = np.linspace(-1.0, 20.0, 200001)
    integral = np.concatenate(([0.0], np.cumsum(0.5 * np.diff(t) * (process_fit.step_response(t, t1, t2)[1:]
                                                                      + process_fit.step_response(t, t1, t2)[:-1]))))
    assert np.max(np.abs(process_fit.ramp_response(t, t1, t2) - integral)) < 1e-6


# Three lags and more with a load step of 0.1 × amp with the relay's bias before the first estimate: the load
# following's fit finds nothing there, and the estimates' K0 came out −1.7 and 3.9–13.6 (the true 1), "ok", no
# disturbance reported. The load model's K0 (within 15 % on these: the model misfits them by 1–4 % of the swing)
# replaces a K0 more than twice off, and the load is reported.
@pytest.mark.parametrize("expr, at", [("1/(s+1)^5", 0.8), ("1/((s+1)*(10*s+1)^2)", 1.2),
                                      ("1/((s+1)*(0.6*s+1)*(0.36*s+1)*(0.216*s+1))", 0.8)])
def test_an_early_load_with_the_bias_on_three_lags_does_not_pass_for_a_wrong_static_gain(expr: str, at: float) -> None:
    process = parse_process(expr)
    w135 = phase_frequency(process, 135.0)
    period = 2.0 * math.pi / w135
    sim = PlantSim(process, period / EXPERIMENT_SAMPLES_PER_PERIOD, loads=[(at * period, 0.1)])
    experiment, _ = run_experiment(sim, RelayConfig(amp=1.0, time_limit=200 * period))
    assert experiment.code is Code.OK, experiment.message
    result = experiment.result
    assert result.static_gain == pytest.approx(1.0, rel=0.15)
    assert result.disturbance and result.load_estimate == pytest.approx(0.1, rel=0.25)
