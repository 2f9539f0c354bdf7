"""How long the experiment takes on fixed processes of the benchmark batch (issue 28), at the bench's conditions.

Ten processes of four families (dead time with one or two lags, two lags with dead time, an inverse
response) that the experiment before issue 28 (main at 3d1cec4) tuned in 4.2–4.3 periods each: each now
tunes within FOUR periods, and its point and static gain are as accurate as the bench requires, against
closed-form responses.
"""

from __future__ import annotations

import cmath
import math

import pytest

from autotuner.engine.experiment.relay import Identification, RelayConfig
from autotuner.engine.outcome import Code
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import EXPERIMENT_SAMPLES_PER_PERIOD, phase_frequency, run_experiment

FOUR = 4.0

CASES = [  # batch id, expression, the same F(s) in closed form, static gain
    ("P1-002", "exp(-s)/(0.05*s+1)", lambda s: cmath.exp(-s) / (0.05 * s + 1), 1.0),
    ("P1-004", "exp(-s)/(0.2*s+1)", lambda s: cmath.exp(-s) / (0.2 * s + 1), 1.0),
    ("P1-009", "exp(-s)/(1.3*s+1)", lambda s: cmath.exp(-s) / (1.3 * s + 1), 1.0),
    ("P2-024", "exp(-s)/(0.05*s+1)^2", lambda s: cmath.exp(-s) / (0.05 * s + 1) ** 2, 1.0),
    ("P2-028", "exp(-s)/(0.5*s+1)^2", lambda s: cmath.exp(-s) / (0.5 * s + 1) ** 2, 1.0),
    ("P7-084", "1*exp(-0.9*s)/((1*s+1)*(0.1*s+1))", lambda s: cmath.exp(-0.9 * s) / ((s + 1) * (0.1 * s + 1)), 1.0),
    ("P7-094", "2*exp(-1*s)/(2*s+1)", lambda s: 2 * cmath.exp(-s) / (2 * s + 1), 2.0),
    ("P8-120", "(1-0.8*s)/(s+1)^3", lambda s: (1 - 0.8 * s) / (s + 1) ** 3, 1.0),
    ("P8-121", "(1-0.9*s)/(s+1)^3", lambda s: (1 - 0.9 * s) / (s + 1) ** 3, 1.0),
    ("P8-123", "(1-1.1*s)/(s+1)^3", lambda s: (1 - 1.1 * s) / (s + 1) ** 3, 1.0),
]


def identified(expr: str, noise: float = 0.0, seed: int = 1) -> Identification:
    """The experiment's result on ``expr`` at the bench's conditions, with white noise of σ ``noise`` × |F(jω135)|
    (amp 1) from ``seed``; it must end "ok"."""
    process = parse_process(expr)
    w135 = phase_frequency(process, 135.0)
    period = 2.0 * math.pi / w135
    sigma = noise * abs(complex(process.freqresp(w135)))
    sim = PlantSim(process, period / EXPERIMENT_SAMPLES_PER_PERIOD, noise_std=sigma, seed=seed)
    experiment, _ = run_experiment(sim, RelayConfig(amp=1.0, time_limit=200 * period))
    assert experiment.code is Code.OK, experiment.message
    return experiment.result


@pytest.mark.parametrize("expr, f, k0", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_tunes_within_four_periods_as_accurately_as_the_bench_requires(expr, f, k0) -> None:
    result = identified(expr)
    assert result.periods <= FOUR
    true = complex(f(1j * result.point.omega))
    assert abs(result.point.value - true) / abs(true) <= 0.002
    assert abs(result.point.phase_deg + 135.0) <= 0.5
    assert result.static_gain == pytest.approx(k0, rel=0.02)


THREE_AND_A_HALF = 3.5

SHORTER = [  # batch id, expression, the same F(s) in closed form, static gain, periods at most
    # A first-order process with dead time, a lag and dead time, an inverse response: main at 2c861d0 took
    # 3.76–3.80 periods; the first estimate and the half period after it now pass the model rule.
    ("P1-006", "exp(-s)/(0.5*s+1)", lambda s: cmath.exp(-s) / (0.5 * s + 1), 1.0, THREE_AND_A_HALF),
    ("P1-008", "exp(-s)/(1*s+1)", lambda s: cmath.exp(-s) / (s + 1), 1.0, THREE_AND_A_HALF),
    ("P7-084", "1*exp(-0.9*s)/((1*s+1)*(0.1*s+1))", lambda s: cmath.exp(-0.9 * s) / ((s + 1) * (0.1 * s + 1)), 1.0,
     THREE_AND_A_HALF),
    ("P8-121", "(1-0.9*s)/(s+1)^3", lambda s: (1 - 0.9 * s) / (s + 1) ** 3, 1.0, THREE_AND_A_HALF),
    # A slow mode whose first |F|/K0 read negative (the PV's mean had not answered the relay's yet): the root of
    # settled_x through it, 4.56 periods on main.
    ("P1-019", "exp(-s)/(200*s+1)", lambda s: cmath.exp(-s) / (200 * s + 1), 1.0, FOUR),
]


@pytest.mark.parametrize("expr, f, k0, most", [c[1:] for c in SHORTER], ids=[c[0] for c in SHORTER])
def test_tunes_sooner_where_the_first_estimates_sufficed(expr, f, k0, most) -> None:
    process = parse_process(expr)
    w135 = phase_frequency(process, 135.0)
    period = 2.0 * math.pi / w135
    sim = PlantSim(process, period / EXPERIMENT_SAMPLES_PER_PERIOD)
    experiment, _ = run_experiment(sim, RelayConfig(amp=1.0, time_limit=200 * period))
    assert experiment.code is Code.OK, experiment.message
    result = experiment.result
    assert result.periods <= most
    true = complex(f(1j * result.point.omega))
    assert abs(result.point.value - true) / abs(true) <= 0.002
    assert abs(result.point.phase_deg + 135.0) <= 0.5
    assert result.static_gain == pytest.approx(k0, rel=0.02)
