"""The sampling timing's histogram: percentiles within a bucket's width of numpy's, counts exact."""

from __future__ import annotations

import numpy as np
import pytest

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
    t.add("A", 0.004, 0.001, overload=0.02)
    t.add("B", 0.090, 0.050, overload=0.02)
    t.add("B", 0.060, 0.030, overload=0.02)
    t.analysed(0.002)
    batch = t.take()
    assert batch.late.count == 3 and batch.analysis.count == 1
    assert batch.overloaded == 2 and batch.worst == {"B": 0.050}
    assert t.take() is None  # handed over: nothing new since
