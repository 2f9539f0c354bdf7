"""The load fit (issue 13): a load step found in a relay-like record, and its fast step-time scan."""

from __future__ import annotations

import math

import numpy as np
import pytest

from autotuner.engine.design.process_data import exact_point
from autotuner.engine.experiment import load_fit
from autotuner.engine.experiment.load_fit import LoadFitter
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.simulation import PlantSim

PLANT = "exp(-s)/(s+1)"  # first order plus dead time: inside the fit's model family
PERIODS = 8.0


def _fitter(loads=(), bias: float = 0.2) -> tuple[LoadFitter, float, float]:
    """A biased square wave at the 135° frequency into the plant; (fitter, period in s, true |F|/K0)."""
    process = parse_process(PLANT)
    point = exact_point(process, 135.0)
    period = 2.0 * math.pi / point.omega
    ts = period / 100.0
    sim = PlantSim(process, ts, loads=[(k * period, size) for k, size in loads])
    t, y, u = [], [], []
    for k in range(int(PERIODS * 100)):
        t.append(sim.t)
        y.append(sim.measure())
        u.append(bias + (1.0 if math.sin(point.omega * sim.t) >= 0.0 else -1.0))
        sim.advance(u[-1])
    fitter = LoadFitter(np.array(t), np.array(y), np.array(u), 0.0, 0, point.omega, point.gain,
                        math.radians(135.0), point.gain)
    return fitter, period, point.gain / process.static_gain()


def test_a_load_step_is_found_with_its_time_and_size_and_the_static_gain_through_it() -> None:
    fitter, period, x_true = _fitter(loads=[(3.3, 0.25)])
    fit = fitter.fit()
    assert fit.x == pytest.approx(x_true, rel=0.01)
    assert fit.step_time == pytest.approx(3.3 * period, abs=0.02 * period)
    assert fit.step == pytest.approx(0.25, rel=0.02)
    assert fit.detected


def test_a_quiet_record_needs_no_disturbance_term() -> None:
    fitter, _, x_true = _fitter()
    fit = fitter.fit()
    assert fit.x == pytest.approx(x_true, rel=0.01)
    assert not fit.detected and fit.step_time is None


def test_a_stable_record_with_a_load_is_explained_better_by_a_stable_model() -> None:
    # What the relay asks when an early load makes the mean ratio look like an unstable process's.
    fitter, _, _ = _fitter(loads=[(1.5, 0.3)])
    assert fitter.fit(unstable=False).score < fitter.fit(unstable=True).score


@pytest.mark.parametrize("x", [0.2, 0.55, 0.9, -0.3])
def test_the_step_time_scan_equals_one_least_squares_fit_per_step_time(x: float) -> None:
    # The scan shifts one step response and solves all step times at once; here each step time
    # gets its own model run from a shifted unit step and its own least-squares solve.
    fitter, _, _ = _fitter(loads=[(3.3, 0.25)])
    ks = np.arange(0, len(fitter.t) - fitter.n, 37)
    scanned = fitter._scan_step(x, (), True, False, ks)
    for k, value in zip(ks, scanned):
        unit = np.zeros(len(fitter.t))
        unit[k:] = 1.0
        respond = lambda v: load_fit._respond(v, fitter.dt, x, fitter.gain, fitter.omega, fitter.lag)  # noqa: E731
        target = fitter.y - respond(fitter.u - fitter.u0)
        columns = np.stack((np.ones(len(unit)), respond(unit), respond(fitter.t - fitter.t[0])), axis=1)
        a, b = load_fit._average(columns, fitter.n), load_fit._average(target[:, None], fitter.n)[:, 0]
        coef, *_ = np.linalg.lstsq(a, b, rcond=None)
        r = b - a @ coef
        assert value == pytest.approx(float(r @ r), rel=1e-6, abs=1e-12 * float(b @ b))
