"""How long the experiment takes on fixed processes of the benchmark batch (issue 28), at the bench's conditions.

Ten processes of four families (dead time with one or two lags, two lags with dead time, an inverse
response) that the experiment before issue 28 (main at 3d1cec4) tuned in 4.2–4.3 periods each: each now
tunes within FOUR periods, and its point and static gain are as accurate as the bench requires, against
closed-form responses. Four more, whose first estimate is exact or nearly (a first-order process with dead
time, a lag and dead time, an inverse response), within THREE_AND_A_HALF: the falling switch after it may stop
the run (convergence.at_falling; 3.75–3.80 periods on main at 2c861d0). Ten of the model rule's family within
TWO_AND_A_HALF, exactly; and the rule leaves alone the runs whose record its model does not explain.
"""

from __future__ import annotations

import cmath
import math

import pytest

from autotuner.engine.experiment import model_rule
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


def _assert_as_accurate_as_the_bench_requires(result: Identification, f, k0: float) -> None:
    """The point within 0.2 % of ``f`` (closed form) and 0.5° of 135°, the static gain within 2 % of ``k0``."""
    true = complex(f(1j * result.point.omega))
    assert abs(result.point.value - true) / abs(true) <= 0.002
    assert abs(result.point.phase_deg + 135.0) <= 0.5
    assert result.static_gain == pytest.approx(k0, rel=0.02)


@pytest.mark.parametrize("expr, f, k0", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_tunes_within_four_periods_as_accurately_as_the_bench_requires(expr, f, k0) -> None:
    result = identified(expr)
    assert result.periods <= FOUR
    _assert_as_accurate_as_the_bench_requires(result, f, k0)


THREE_AND_A_HALF = 3.5

SHORTER = [  # batch id, expression, the same F(s) in closed form, static gain, periods at most
    # A first-order process with dead time, a lag and dead time, an inverse response: main at 2c861d0 took
    # 3.75–3.80 periods; the first estimate and the half period after it now pass the model rule.
    ("P1-006", "exp(-s)/(0.5*s+1)", lambda s: cmath.exp(-s) / (0.5 * s + 1), 1.0, THREE_AND_A_HALF),
    ("P1-008", "exp(-s)/(1*s+1)", lambda s: cmath.exp(-s) / (s + 1), 1.0, THREE_AND_A_HALF),
    ("P7-084", "1*exp(-0.9*s)/((1*s+1)*(0.1*s+1))", lambda s: cmath.exp(-0.9 * s) / ((s + 1) * (0.1 * s + 1)), 1.0,
     THREE_AND_A_HALF),
    ("P8-121", "(1-0.9*s)/(s+1)^3", lambda s: (1 - 0.9 * s) / (s + 1) ** 3, 1.0, THREE_AND_A_HALF),
]


@pytest.mark.parametrize("expr, f, k0, most", [c[1:] for c in SHORTER], ids=[c[0] for c in SHORTER])
def test_tunes_sooner_where_the_first_estimate_sufficed(expr, f, k0, most) -> None:
    result = identified(expr)
    assert result.periods <= most
    _assert_as_accurate_as_the_bench_requires(result, f, k0)


TWO_AND_A_HALF = 2.5

MODELLED = [  # batch id, expression, the same F(s) in closed form, static gain (inf: an integrator)
    # The model rule's family (model_rule.py: two lags and a dead time) and the integrators with a lag and dead
    # time it holds within its misfit, from nearly pure dead time to a lag 100 times the dead time: 3.0–7.5
    # periods each before the rule (main at 236c558), 1.5–2.3 with it.
    ("P1-002", "exp(-s)/(0.05*s+1)", lambda s: cmath.exp(-s) / (0.05 * s + 1), 1.0),
    ("P1-009", "exp(-s)/(1.3*s+1)", lambda s: cmath.exp(-s) / (1.3 * s + 1), 1.0),
    ("P1-017", "exp(-s)/(50*s+1)", lambda s: cmath.exp(-s) / (50 * s + 1), 1.0),
    ("P2-028", "exp(-s)/(0.5*s+1)^2", lambda s: cmath.exp(-s) / (0.5 * s + 1) ** 2, 1.0),
    ("P2-037", "exp(-s)/(10*s+1)^2", lambda s: cmath.exp(-s) / (10 * s + 1) ** 2, 1.0),
    ("P2-040", "exp(-s)/(100*s+1)^2", lambda s: cmath.exp(-s) / (100 * s + 1) ** 2, 1.0),
    ("P6-073", "exp(-0.5*s)/(s*(0.5*s+1))", lambda s: cmath.exp(-0.5 * s) / (s * (0.5 * s + 1)), math.inf),
    ("P7-077", "1*exp(-0.01*s)/((1*s+1)*(0.99*s+1))",
     lambda s: cmath.exp(-0.01 * s) / ((s + 1) * (0.99 * s + 1)), 1.0),
    ("P7-094", "2*exp(-1*s)/(2*s+1)", lambda s: 2 * cmath.exp(-s) / (2 * s + 1), 2.0),
    ("P7-105", "10*exp(-0.02*s)/((10*s+1)*(0.98*s+1))",
     lambda s: 10 * cmath.exp(-0.02 * s) / ((10 * s + 1) * (0.98 * s + 1)), 10.0),
]


@pytest.mark.parametrize("expr, f, k0", [c[1:] for c in MODELLED], ids=[c[0] for c in MODELLED])
def test_a_process_the_model_holds_tunes_within_two_and_a_half_periods(expr, f, k0) -> None:
    result = identified(expr)
    assert result.periods <= TWO_AND_A_HALF
    # Tighter than the bench asks (0.2 %, 0.5°, 2 %): the model's point is exact where the model is the process.
    true = complex(f(1j * result.point.omega))
    assert abs(result.point.value - true) / abs(true) <= 0.0005
    assert abs(result.point.phase_deg + 135.0) <= 0.1
    if math.isinf(k0):
        assert math.isinf(result.static_gain)
    else:
        assert result.static_gain == pytest.approx(k0, rel=0.005)


@pytest.mark.parametrize("expr", ["1/(s+1)^3", "1/((s+1)*(0.5*s+1)^2)", "1/((s+1)*(0.36*s^2+0.84*s+1))",
                                  "exp(-s)/(2*s+1)"])
def test_the_model_rule_stops_only_a_record_its_model_explains(expr: str, monkeypatch: pytest.MonkeyPatch) -> None:
    # Three lags and more misfit the model by 1.5–3 % of the swing: the rule leaves their runs as they were
    # without it. With 1 % noise no record is explained within 3e-4 of its swing: not even a first-order process.
    noise = 0.01 if expr == "exp(-s)/(2*s+1)" else 0.0
    with_rule = identified(expr, noise)
    monkeypatch.setattr(model_rule, "PERIODS", -1)
    assert identified(expr, noise) == with_rule
