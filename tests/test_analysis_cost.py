"""The experiment's work per period and per sample is bounded, whatever the record's length (issue 24).

Counted, never timed: the load fit's model runs and the size of the grid it runs them on, the samples
the Fourier estimates and the static ratio's lag read, the samples the runaway test reads per step.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from autotuner.engine.design.process_data import exact_point
from autotuner.engine.experiment import estimates, load_fit, model_rule, relay
from autotuner.engine.experiment.load_fit import NEAR_RUNS, SEARCH_RUNS, LoadFitter
from autotuner.engine.experiment.record import Record
from autotuner.engine.experiment.relay import RelayConfig, RelayExperiment
from autotuner.engine.experiment.runaway import Runaway
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.simulation import PlantSim

PLANT = "exp(-s)/(s+1)"  # first order plus dead time: inside the load fit's model family


def test_the_record_grows_in_place_and_keeps_every_sample() -> None:
    record = Record(capacity=4)
    for k in range(1000):
        record.add(0.1 * k, math.sin(k))
        record.hold(float(k % 7))
    record.applied(99.95)  # the latest MV reached the process late
    assert len(record) == record.held == 1000
    assert np.array_equal(record.t, 0.1 * np.arange(1000))
    assert np.array_equal(record.y, np.sin(np.arange(1000)))
    stretch = record.since(50.0)
    assert stretch.t[0] == pytest.approx(50.0) and len(stretch.t) == 500
    assert np.array_equal(stretch.u, np.arange(500, 1000) % 7)
    assert stretch.s[-1] == 99.95 and stretch.s[-2] == pytest.approx(99.8)
    assert record.time(-1) == pytest.approx(99.9) and record.pv(3) == math.sin(3) and record.mv(-1) == 999 % 7


def _relay_record(periods: float, step_at: float, per_period: int = 100):
    """A biased square wave at the 135° frequency into the plant with a load step of 0.25 at ``step_at``
    periods: (t, y, u, point, period, true |F|/K0)."""
    process = parse_process(PLANT)
    point = exact_point(process, 135.0)
    period = 2.0 * math.pi / point.omega
    sim = PlantSim(process, period / per_period, loads=[(step_at * period, 0.25)])
    t, y, u = [], [], []
    for _ in range(int(periods * per_period)):
        t.append(sim.t)
        y.append(sim.measure())
        u.append(0.2 + (1.0 if math.sin(point.omega * sim.t) >= 0.0 else -1.0))
        sim.advance(u[-1])
    return np.array(t), np.array(y), np.array(u), point, period, point.gain / process.static_gain()


def _fitter(t, y, u, point) -> LoadFitter:
    return LoadFitter(t, y, u, 0.0, 0, point.omega, point.gain, math.radians(135.0), point.gain)


@pytest.mark.parametrize("periods", [8.0, 60.0])
def test_a_fit_runs_a_bounded_number_of_models_on_a_bounded_grid(periods: float) -> None:
    # 60 periods of 100 samples are more than the grid holds: the model runs on a coarser one.
    t, y, u, point, period, x_true = _relay_record(periods, 3.3)
    fitter = _fitter(t, y, u, point)
    fit = fitter.fit()
    assert fitter.runs <= SEARCH_RUNS
    assert len(fitter.t) <= load_fit._GRID_MAX and len(load_fit._ends(fitter.n, len(fitter.t))) <= load_fit._ROWS_MAX
    assert fit.x == pytest.approx(x_true, rel=0.01)
    assert fit.step_time == pytest.approx(3.3 * period, abs=0.03 * period)
    assert fit.step == pytest.approx(0.25, rel=0.03)


def test_a_refit_near_the_earlier_fit_runs_few_models_and_finds_what_the_full_search_finds() -> None:
    t, y, u, point, period, x_true = _relay_record(10.0, 3.3)
    shorter = len(t) - 100  # a period less: the fit accepted at the period before
    earlier = _fitter(t[:shorter], y[:shorter], u[:shorter], point).fit()
    near = _fitter(t, y, u, point)
    refit = near.fit(near=earlier)
    full = _fitter(t, y, u, point).fit()
    assert near.runs <= NEAR_RUNS
    assert refit.x == pytest.approx(full.x, abs=max(full.x_std, 1e-3))
    assert refit.step_time == pytest.approx(full.step_time, abs=period / 12)
    # (The full search chooses its ramp before the step; the refit, with the step: as well explained or better.)
    assert refit.score <= full.score
    assert refit.x == pytest.approx(x_true, rel=0.01)


def test_a_refit_whose_record_moved_away_searches_it_all() -> None:
    # The earlier fit saw no step (a quiet start): the step now in the record is beyond what its terms explain.
    t, y, u, point, period, _ = _relay_record(10.0, 6.5)
    quiet = _fitter(t[:550], y[:550], u[:550], point).fit()
    assert quiet.step_time is None
    refit = _fitter(t, y, u, point).fit(near=quiet)
    assert refit.step_time == pytest.approx(6.5 * period, abs=0.03 * period)


class _Counts:
    """What each period's analysis did: the load fits' model runs, grids and scanned step times, the samples
    the Fourier coefficients and the static ratio's lag were given."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.runs: list[int] = []
        self.grid = 0
        self.fits = 0
        self.scanned = 0
        self.fourier = 0
        self.lagged = 0
        fit, scan, held, sampled, lagged = (LoadFitter.fit, LoadFitter._scan_step, estimates.held_coefficient,
                                            estimates.sampled_coefficient, load_fit._lagged_mean)

        def counted_fit(fitter: LoadFitter, *args, **kwargs):
            before = fitter.runs
            result = fit(fitter, *args, **kwargs)
            self.runs[-1] += fitter.runs - before
            self.fits += 1
            self.grid = max(self.grid, len(fitter.t))
            return result

        def reads(function, attribute: str):
            def counted(t, values, *args, **kwargs):
                setattr(self, attribute, max(getattr(self, attribute), len(t), len(values)))
                return function(t, values, *args, **kwargs)
            return counted

        def counted_scan(fitter: LoadFitter, x, steps, ramp, free, ks):
            self.scanned += len(ks)
            return scan(fitter, x, steps, ramp, free, ks)

        monkeypatch.setattr(LoadFitter, "fit", counted_fit)
        monkeypatch.setattr(LoadFitter, "_scan_step", counted_scan)
        monkeypatch.setattr(estimates, "held_coefficient", reads(held, "fourier"))
        monkeypatch.setattr(estimates, "sampled_coefficient", reads(sampled, "fourier"))
        monkeypatch.setattr(load_fit, "_lagged_mean", reads(lagged, "lagged"))

    def start(self) -> None:
        self.runs.append(0)
        self.fits = self.grid = self.scanned = self.fourier = self.lagged = 0


def _run(config: RelayConfig, counts: _Counts, noise: float, loads: list[tuple[float, float]]):
    """The experiment on the plant at 100 samples per period: per analysis, (runs, fits, grid, Fourier and
    lag inputs, samples so far); and the experiment."""
    process = parse_process(PLANT)
    point = exact_point(process, 135.0)
    period = 2.0 * math.pi / point.omega
    sim = PlantSim(process, period / 100, noise_std=noise * point.gain, seed=4,
                   loads=[(at * period, size) for at, size in loads])
    experiment = RelayExperiment(config, mv0=sim.mv0)
    analyses = []
    while not experiment.done:
        mv = experiment.step(sim.t, sim.measure())
        if experiment.analysis_pending:
            counts.start()
            experiment.analyse()
            analyses.append((counts.runs[-1], counts.fits, counts.grid, counts.fourier, counts.lagged,
                             len(experiment._loop.record), counts.scanned))
        sim.advance(mv)
    return analyses, experiment


def test_a_disturbed_run_of_40_periods_does_bounded_work_in_each_period(monkeypatch: pytest.MonkeyPatch) -> None:
    # A load step early on, then refits every period; tolerances out of reach keep it running to max_periods.
    counts = _Counts(monkeypatch)
    config = RelayConfig(amp=1.0, max_periods=40, gain_tol=1e-6, noise_tol=1e-6, static_tol=1e-6)
    analyses, experiment = _run(config, counts, 0.01, [(3.5, 0.2)])
    assert len(experiment._loop.record) >= 39 * 100 and experiment._load.fit is not None
    refits = [a for a in analyses if a[1] > 0]
    assert len(refits) >= 30  # the fit ran in most periods, on records of up to 4 000 samples
    for runs, fits, grid, fourier, *_ in analyses:
        assert fits <= 3 and runs <= fits * (SEARCH_RUNS + NEAR_RUNS)
        assert grid <= load_fit._GRID_MAX
        assert fourier <= 4 * 100  # the samples of the latest periods, not of the record
    # Near the accepted fit, a refit scans the step time near the accepted one (twice ± a quarter period,
    # 25 samples here) instead of every 1/12 period of the record at 11 values of x: at 30 periods that
    # would be 11 × 360 step times.
    assert np.median([a[6] for a in refits[-20:]]) <= 2 * (2 * 25 + 1)


def test_a_quiet_run_of_40_periods_reads_a_bounded_stretch_of_its_record(monkeypatch: pytest.MonkeyPatch) -> None:
    # Noisy and quiet, tolerances out of reach: estimates, static ratios and load checks up to max_periods.
    counts = _Counts(monkeypatch)
    config = RelayConfig(amp=1.0, max_periods=40, gain_tol=1e-6, noise_tol=1e-6, static_tol=1e-6)
    analyses, experiment = _run(config, counts, 0.005, [])
    assert len(experiment._loop.record) >= 39 * 100 and experiment._load.fit is None
    for runs, fits, grid, fourier, lagged, *_ in analyses:
        assert fits <= 3 and runs <= fits * SEARCH_RUNS
        assert fourier <= 4 * 100
        # The static ratio's lag reads 36 of its time constants before the window (|F|/K0 = 0.58 here:
        # 36·T = 8 periods), not the whole record.
        assert lagged <= 11 * 100
    assert max(a[4] for a in analyses) > 0 and analyses[-1][5] > 3 * 11 * 100


def test_the_runaway_test_reads_a_few_samples_per_step_however_long_the_half_period(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # The long windows' means come from running sums since the switch (checked against the plain mean): a
    # step reads as many samples with 2 000 samples per period as with 100.
    reads, means = [0], [0]
    pv, y, mean_distance = Record.pv, Record.y, Runaway.mean_distance

    def counted_pv(record: Record, i: int) -> float:
        reads[0] += 1
        return pv(record, i)

    def counted_y(record: Record) -> np.ndarray:
        reads[0] += 1000  # every PV: a step that reads them all stands out
        return y.fget(record)

    def checked_mean(runaway: Runaway, i: int, m: int) -> float:
        means[0] += 1
        value = mean_distance(runaway, i, m)
        pvs = y.fget(runaway.loop.record)[i - m + 1:i + 1]
        assert value == pytest.approx(float(np.mean(pvs - runaway.loop.sp)), rel=1e-9, abs=1e-12)
        return value

    monkeypatch.setattr(Record, "pv", counted_pv)
    monkeypatch.setattr(Record, "y", property(counted_y))
    monkeypatch.setattr(Runaway, "mean_distance", checked_mean)
    process = parse_process("exp(-0.5*s)/(s+1)^2")
    point = exact_point(process, 135.0)
    # (The model rule, model_rule.py, would end this run in two periods: the test counts reads over four.)
    monkeypatch.setattr(model_rule, "PERIODS", -1)
    most = {}
    for per_period in (100, 2000):
        sim = PlantSim(process, 2.0 * math.pi / point.omega / per_period)
        experiment = RelayExperiment(RelayConfig(amp=1.0, max_periods=4, follow_loads=False), mv0=sim.mv0)
        most[per_period] = 0
        while not experiment.done:
            reads[0] = 0
            relaying = experiment.stage is relay.Stage.RELAY  # (the noise stage's last step fits a line to it)
            mv = experiment.step(sim.t, sim.measure())
            if relaying:
                most[per_period] = max(most[per_period], reads[0])
            experiment.analyse()
            sim.advance(mv)
        assert experiment.result is not None and len(experiment._loop.record) > 3 * per_period
    assert means[0] > 1000
    assert most[2000] == most[100] <= 8


def test_timing_the_calls_changes_nothing() -> None:
    # The bench times each step and each period's analysis where step() runs it: same samples, same result.
    from autotuner.engine.simulated_tuning import CallTimes, run_experiment

    process = parse_process(PLANT)
    period = 2.0 * math.pi / exact_point(process, 135.0).omega
    ticks = iter(range(10**7))
    times = CallTimes(lambda: float(next(ticks)))
    # (The load at 2.5 periods: at 3.5 this quiet run, σ 0.5 % of |F|·amp, ends at 3.8 periods as a noise-free one
    # does, before the load shows, and no load fit would be timed.)
    runs = [run_experiment(PlantSim(process, period / 100, noise_std=0.003, seed=2, loads=[(2.5 * period, 0.2)]),
                           RelayConfig(amp=1.0), times=timed) for timed in (None, times)]
    (plain, plain_trace), (timed, timed_trace) = runs
    assert np.array_equal(plain_trace.t, timed_trace.t) and np.array_equal(plain_trace.mv, timed_trace.mv)
    assert plain.result == timed.result and plain.result is not None and plain.result.disturbance
    assert len(times.step) == len(timed_trace.t) and 2 * plain.status().periods <= len(times.analyse)
    assert min(times.step) >= 1.0 and min(times.analyse) >= 1.0  # each call read the clock around itself
