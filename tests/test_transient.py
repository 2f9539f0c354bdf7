"""The transient's share of an estimate (experiment/transient.py) against closed-form responses (issue 28)."""

from __future__ import annotations

import cmath
import math

import numpy as np
import pytest

from autotuner.engine.experiment import estimates, model_rule
from autotuner.engine.experiment.record import Samples
from autotuner.engine.experiment.relay import RelayConfig
from autotuner.engine.experiment.transient import model_output
from autotuner.engine.outcome import Code
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import phase_frequency, run_experiment

# First order plus dead time: the model the correction uses is the process itself.
PLANT = "1.5*exp(-0.73*s)/(4*s+1)"


def exact(s: complex) -> complex:
    return 1.5 * cmath.exp(-0.73 * s) / (4 * s + 1)


def _first_estimate_error(monkeypatch: pytest.MonkeyPatch, corrections: int) -> float:
    monkeypatch.setattr(estimates, "CORRECTIONS", corrections)
    # (The model rule, model_rule.py, stops a first-order process with dead time before its first estimate: these
    # tests judge the estimates, so the rule tries no fit.)
    monkeypatch.setattr(model_rule, "PERIODS", 0)
    process = parse_process(PLANT)
    w = phase_frequency(process, 135.0)
    sim = PlantSim(process, 2.0 * math.pi / w / 100)
    experiment, _ = run_experiment(sim, RelayConfig(amp=1.0, time_limit=300 * 2.0 * math.pi / w))
    assert experiment.code is Code.OK, experiment.message
    first = experiment._estimates.items[0].point
    true = exact(1j * first.omega)
    return abs(first.value - true) / abs(true)


def test_the_first_estimate_of_a_first_order_process_is_exact_once_its_transient_is_taken_out(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # The first period after the filter's first correction: the cycle is not periodic yet.
    corrections = estimates.CORRECTIONS
    assert _first_estimate_error(monkeypatch, 0) > 0.01
    assert _first_estimate_error(monkeypatch, corrections) < 2e-4


def test_the_model_runs_exactly_on_uneven_samples() -> None:
    # A step of 2 MV units at 1.05 s (held from an uneven sample), read at uneven times.
    s = np.array([0.0, 0.4, 1.05, 1.3, 2.9, 3.0])
    u = np.array([0.0, 0.0, 2.0, 2.0, 2.0, 2.0])
    history = Samples(t=s, y=np.zeros(len(s)), u=u, s=s)
    times = np.array([0.5, 1.5, 1.8, 2.45, 3.7, 9.0])
    k0, tc, delay = 1.5, 4.0, 0.73
    lagged = model_output(history, times, 0.0, k0, tc, delay, 0.0)
    since = np.maximum(times - 1.05 - delay, 0.0)
    assert lagged == pytest.approx(2.0 * k0 * (1.0 - np.exp(-since / tc)), rel=1e-12, abs=1e-15)
    integrated = model_output(history, times, 0.0, math.inf, math.inf, delay, 0.3)
    assert integrated == pytest.approx(2.0 * 0.3 * since, rel=1e-12, abs=1e-15)
