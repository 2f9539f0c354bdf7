"""The sampling timing's histogram: percentiles within a bucket's width of numpy's, counts exact."""

from __future__ import annotations

import numpy as np
import pytest

from autotuner.service.config import DaemonConfig, TuneRequest
from autotuner.service.daemon.capacity import DEFAULT_READING_COST, DEFAULT_SAMPLE_COST, MIN_SAMPLES, Cost, Rates
from autotuner.service.daemon.field import nominal_rate
from autotuner.service.daemon.settings import plan_of, settings_of
from autotuner.service.daemon.timing import PER_DECADE, Histogram, Timings


def test_quantiles_are_within_a_buckets_width_of_the_samples_own():
    values = np.random.default_rng(7).lognormal(-5.0, 1.5, 20000)
    h = Histogram()
    for v in values:
        h.add(float(v))
    width = 10.0 ** (1.0 / PER_DECADE)
    for q in (0.01, 0.5, 0.9, 0.99, 0.999):
        exact = float(np.quantile(values, q))
        assert exact / width <= h.quantile(q) <= exact * width, q
    assert h.largest == values.max() and h.count == len(values)
    assert h.total == pytest.approx(values.sum())
    assert h.cumulative([1e-3, 1e-2, float("inf")]) == [int((values <= 1e-3).sum()), int((values <= 1e-2).sum()),
                                                         len(values)]


def test_merged_histograms_count_every_value_and_an_empty_one_has_no_quantile():
    a, b = Histogram(), Histogram()
    for v in (0.001, 0.002):
        a.add(v)
    b.add(0.5)
    a.merge(b)
    assert a.count == 3 and a.largest == 0.5 and a.quantile(1.0) == 0.5
    assert np.isnan(Histogram().quantile(0.5))


def test_timings_name_the_loops_late_by_the_fields_own_fault_and_hand_over_once():
    t = Timings()
    t.add("A", 0.004, 0.001, tolerance=0.02)
    t.add("B", 0.090, 0.050, tolerance=0.02)
    t.add("B", 0.060, 0.030, tolerance=0.02)
    t.analysed(0.002, elsewhere=False)
    t.analysed(0.5, elsewhere=True)  # in a worker process: not in this process's CPU time
    batch = t.take()
    assert batch.late.count == 3 and batch.analysis.count == 2
    assert batch.overloaded == 2 and batch.worst == {"B": 0.050}
    assert 0.5 <= batch.cpu < 0.5 + 1.0  # the worker's half second, and this process's own (a thread's is in it)
    again = t.take()  # handed over: nothing new since, but the process's CPU meanwhile
    assert again.late.count == 0 and again.overloaded == 0 and 0.0 <= again.cpu < 0.5


def test_a_sessions_sample_and_a_monitor_reading_are_costed_apart_and_a_load_is_costs_times_rates():
    cost = Cost()
    cost.update(0.5, MIN_SAMPLES - 1, 0)  # too few samples to say anything
    assert (cost.sample, cost.reading) == (DEFAULT_SAMPLE_COST, DEFAULT_READING_COST)
    for _ in range(60):
        cost.update(0.05, 0, 1000)  # an idle field: 50 µs per reading, again and again
    assert cost.reading == pytest.approx(50e-6, rel=1e-4)
    assert cost.sample == DEFAULT_SAMPLE_COST  # readings alone say nothing of what a session's sample costs
    cost.update(0.9, 10, 1000)  # a few samples among many readings: neither cost is certain
    assert cost.reading == pytest.approx(50e-6, rel=1e-4) and cost.sample == DEFAULT_SAMPLE_COST
    for _ in range(60):
        cost.update(0.2 + 0.05, 1000, 1000)  # 200 µs per sample beside the readings' 50 µs
    assert cost.sample == pytest.approx(200e-6, rel=1e-3)
    assert cost.load(Rates(samples=1500.0, readings=400.0)) == pytest.approx(1500 * 200e-6 + 400 * 50e-6, rel=1e-3)


def test_the_nominal_rate_counts_sessions_by_their_plan_and_idle_loops_by_their_monitor():
    config = DaemonConfig.model_validate({"history": ":memory:", "loops": [
        {"id": f"L{k}", "link": f"modbus://10.0.0.1:502/{k}", "ts": 0.1, "monitor_period": 2.0} for k in range(4)]})
    plan = plan_of(config.loops[0], settings_of(config.loops[0], TuneRequest()))
    assert nominal_rate(config.loops, {}) == Rates(samples=0.0, readings=pytest.approx(4 * 0.5))
    assert nominal_rate(config.loops, {"L0": plan, "L1": plan}) == Rates(samples=pytest.approx(2 * 10.0),
                                                                         readings=pytest.approx(2 * 0.5))
