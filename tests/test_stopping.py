"""The stopping rule (stopping.judge): estimates scattered along the Nyquist curve settle, scattered about it not."""

from __future__ import annotations

import cmath
import math
from collections.abc import Callable

import numpy as np
import pytest

from autotuner.engine.design.process_data import exact_point
from autotuner.engine.experiment import stopping
from autotuner.engine.experiment.point import Point
from autotuner.engine.experiment.relay import RelayConfig
from autotuner.engine.experiment.stopping import Tolerances, judge
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import default_sample_time, default_time_limit, run_experiment
from autotuner.service.remote_tuning import FIELD_GAIN_TOL, FIELD_PHASE_TOL, FIELD_STATIC_TOL

PROCESS = parse_process("exp(-s)/(2*s+1)")
TOL = Tolerances(FIELD_PHASE_TOL, FIELD_GAIN_TOL, FIELD_STATIC_TOL, 0.004)
# The cycle's ω, period by period, as a loaded machine's timing made it wander (±5 %; measured over Modbus
# under two CPU burners: 1.11–1.23 rad/s about 1.186).
WANDER = [-1.0, 0.6, -0.3, 1.0, -0.8, 0.2, 0.5, -0.5, 0.9, -0.6]
X = 0.388  # |F|/K0 at the point


def _along(shift_deg: float = 0.0, seed: int = 3) -> list[tuple[Point, float]]:
    """F of the process at each wandering ω, with 0.1 % of leakage about the curve; lag shifted by ``shift_deg``."""
    w135 = exact_point(PROCESS, 135.0).omega
    rng = np.random.default_rng(seed)
    out = []
    for u in WANDER:
        w = w135 * (1.0 + 0.05 * u)
        f = complex(PROCESS.freqresp(w)) * cmath.exp(-1j * math.radians(shift_deg))
        f *= 1.0 + 0.001 * complex(*rng.normal(size=2))
        out.append((Point(w, f), X))
    return out


def test_estimates_along_the_curve_settle_at_their_mean() -> None:
    estimates = _along()
    # Their spread about the mean is far beyond the settled rule's (it alone never stops).
    for k in range(2, len(estimates) + 1):
        assert stopping._stats(estimates[-k:])[2] / math.sqrt(k) > 0.5 * TOL.gain_tol
    verdict = judge(estimates, 135.0, TOL, len(estimates), noisy=False)
    assert verdict is not None and verdict.count >= stopping.CURVE_MIN
    recent = estimates[-verdict.count:]
    mean_w = sum(p.omega for p, _ in recent) / len(recent)
    assert verdict.point.omega == pytest.approx(mean_w)
    true = complex(PROCESS.freqresp(mean_w))
    assert abs(verdict.point.value - true) / abs(true) < 0.003


def test_estimates_scattered_about_the_curve_do_not_settle() -> None:
    # The same spread, but at one ω and in every direction: no line in ω explains it.
    w135 = exact_point(PROCESS, 135.0).omega
    rng = np.random.default_rng(5)
    f = complex(PROCESS.freqresp(w135))
    estimates = [(Point(w135 * (1.0 + 1e-4 * u), f * (1.0 + 0.03 * complex(*rng.normal(size=2)))), X) for u in WANDER]
    assert judge(estimates, 135.0, TOL, len(estimates), noisy=False) is None


def test_estimates_along_the_curve_whose_mean_lags_off_target_do_not_settle() -> None:
    assert judge(_along(shift_deg=2.0), 135.0, TOL, len(WANDER), noisy=False) is None


def test_an_unstable_processs_static_ratio_must_settle_over_three_estimates() -> None:
    # exp(-0.5*s)/(2*s-1) after its phase target moved: the point had settled, |F|/K0 was still converging
    # (K0 read −0.91, −0.965; true −1). Two estimates agreed within static_tol and the run stopped with K0 3.5 %
    # off, which made the design read D/T 0.257 and refuse PI (limit 0.25).
    unstable = parse_process("exp(-0.5*s)/(2*s-1)")
    point = Point(1.894, complex(unstable.freqresp(1.894)))  # where its cycle settled, lagging 159°
    target = -point.phase_deg
    true_x = -point.gain / abs(unstable.static_gain())
    tol = Tolerances(1.0, 0.02, 0.02, 0.004)
    converging = [(point, true_x * f) for f in (1.18, 1.09, 1.037)]
    assert stopping._stats(converging[-2:])[3] / math.sqrt(2) <= 0.5 * tol.static_tol  # two agree: the old rule
    assert judge(converging, target, tol, 3, noisy=False) is None
    settled = [*converging, (point, true_x * 1.004), (point, true_x * 1.001), (point, true_x)]
    verdict = judge(settled, target, tol, 3, noisy=False)
    assert verdict is not None and verdict.x == pytest.approx(true_x, rel=0.005)
    # A stable process's ratio at the same size keeps the two-estimate rule (the plain bench's periods).
    assert judge([(p, -x) for p, x in converging], target, tol, 3, noisy=False) is not None


FOPDT = parse_process("exp(-s)/(4*s+1)")
QUIET = Tolerances(0.5, 0.01, 0.02, 0.004)  # RelayConfig's defaults


def _fopdt_at(lag_deg: float, leak: float = 0.0) -> tuple[Point, float]:
    """The exact estimate of FOPDT where it lags ``lag_deg``, scaled by 1 + ``leak`` (a transient left in it)."""
    w = exact_point(FOPDT, lag_deg).omega
    f = cmath.exp(-1j * w) / (1.0 + 4j * w)  # e^{−s}/(4s + 1), written out
    return Point(w, f * (1.0 + leak)), abs(f)


def test_two_estimates_on_the_models_curve_give_the_point_at_the_target() -> None:
    # A first-order process with dead time: its estimates are exact once the transient's share is out, and the
    # phase still converges (1.4°, then 0.7° beyond the target): the settled and line rules cannot pass.
    estimates = [_fopdt_at(136.4), _fopdt_at(135.7)]
    verdict = judge(estimates, 135.0, QUIET, 2, noisy=False)
    assert verdict is not None and verdict.count == 2
    w = verdict.point.omega
    true = cmath.exp(-1j * w) / (1.0 + 4j * w)
    assert abs(-verdict.point.phase_deg - 135.0) < 0.05  # (the line in the complex plane, not in phase)
    # The line's chord in place of the curve: 0.016 % here, a tenth of the batch's median point error budget.
    assert abs(verdict.point.value - true) / abs(true) < 5e-4
    assert verdict.x == pytest.approx(abs(true), rel=5e-4)
    # Noisy estimates are averaged instead (three at least).
    assert judge(estimates, 135.0, QUIET, 2, noisy=True) is None


def test_an_estimate_off_the_models_curve_or_far_from_the_target_does_not_stop() -> None:
    # The one before carries 0.4 % of its transient (beyond MODEL_TOL of gain_tol): go on; 0.1 %: stop.
    assert judge([_fopdt_at(136.4, leak=0.004), _fopdt_at(135.7)], 135.0, QUIET, 2, noisy=False) is None
    assert judge([_fopdt_at(136.4, leak=0.001), _fopdt_at(135.7)], 135.0, QUIET, 2, noisy=False) is not None
    # The latest 2.5° beyond the target (MODEL_GATE_DEG 2°): go on, though both are exact.
    assert judge([_fopdt_at(139.0), _fopdt_at(137.5)], 135.0, QUIET, 2, noisy=False) is None
    # Phases that move away from the target are no convergence.
    assert judge([_fopdt_at(135.7), _fopdt_at(136.4)], 135.0, QUIET, 2, noisy=False) is None
    # Nor do phases on both sides of it (a cycle whose ω wanders with a link's timing).
    assert judge([_fopdt_at(133.6), _fopdt_at(136.4)], 135.0, QUIET, 2, noisy=False) is None


# Ten processes of the batch's families (shared/bench/amigo-batch.csv: P1-012, P1-016, P2-033, P2-034, P5-062,
# P5-063, P7-081, P7-101, P7-103, P9-126) that the model rule and the second transient model stop sooner: 3.5–4.03
# periods, 4.3–5.2 before. Each with its F(jω) written out, independently of the parser and Process.freqresp.
TEN: dict[str, Callable[[complex], complex]] = {
    "exp(-s)/(4*s+1)": lambda s: cmath.exp(-s) / (4 * s + 1),
    "exp(-s)/(20*s+1)": lambda s: cmath.exp(-s) / (20 * s + 1),
    "exp(-s)/(2*s+1)^2": lambda s: cmath.exp(-s) / (2 * s + 1) ** 2,
    "exp(-s)/(4*s+1)^2": lambda s: cmath.exp(-s) / (4 * s + 1) ** 2,
    "1/((s+1)*(0.4*s+1)*(0.16*s+1)*(0.064*s+1))":
        lambda s: 1 / ((s + 1) * (0.4 * s + 1) * (0.16 * s + 1) * (0.064 * s + 1)),
    "1/((s+1)*(0.5*s+1)*(0.25*s+1)*(0.125*s+1))":
        lambda s: 1 / ((s + 1) * (0.5 * s + 1) * (0.25 * s + 1) * (0.125 * s + 1)),
    "exp(-0.3*s)/((s+1)*(0.7*s+1))": lambda s: cmath.exp(-0.3 * s) / ((s + 1) * (0.7 * s + 1)),
    "5*exp(-0.7*s)/((5*s+1)*(0.3*s+1))": lambda s: 5 * cmath.exp(-0.7 * s) / ((5 * s + 1) * (0.3 * s + 1)),
    "5*exp(-1*s)/(5*s+1)": lambda s: 5 * cmath.exp(-s) / (5 * s + 1),
    "1/((s+1)*(0.09*s^2+0.42*s+1))": lambda s: 1 / ((s + 1) * (0.09 * s * s + 0.42 * s + 1)),
}


@pytest.mark.parametrize("expr", list(TEN))
def test_ten_processes_tune_within_four_periods_at_the_point(expr: str) -> None:
    process = parse_process(expr)
    ts = default_sample_time(process)
    config = RelayConfig(amp=1.0, time_limit=default_time_limit(process, 135.0, ts))
    experiment, _ = run_experiment(PlantSim(process, ts), config)
    result = experiment.result
    assert result is not None, experiment.message
    assert result.periods <= 4.1
    true = TEN[expr](1j * result.point.omega)
    assert abs(result.point.value - true) / abs(true) <= 0.002
    assert abs(result.point.phase_deg + 135.0) <= config.phase_tol_deg
    assert result.static_gain == pytest.approx(TEN[expr](0j).real, rel=config.static_tol)
