"""The loop-health benchmark's parts: its PI at a gain margin, its cases, its tables."""

from __future__ import annotations

import math

import numpy as np
import pytest

from autotuner.benchmarks.health_bench import (FAULTS, HEALTHY, Case, Outcome, cases, margin_gains, run_case,
                                               table)
from autotuner.engine.health.scales import ultimate_period
from autotuner.engine.plant.expression import parse_process


@pytest.mark.parametrize("expr", ["1.5*exp(-0.7*s)/(4*s+1)^2", "0.2*exp(-1*s)/(s*(2*s+1))"])
def test_margin_gains_leave_the_gain_margin_asked_for(expr: str) -> None:
    process = parse_process(expr)
    tu = ultimate_period(process)
    gains = margin_gains(process, tu, 1.3)
    w = np.linspace(0.3, 1.2, 200_001) * 2 * math.pi / tu
    loop = gains.k * (1 + 1 / (1j * w * gains.ti)) * process.freqresp(w)
    # where the loop's phase passes -180° (its imaginary part changes sign with a negative real part)
    k = np.flatnonzero((np.sign(loop.imag[1:]) != np.sign(loop.imag[:-1])) & (loop.real[1:] < 0))[0]
    assert 1.0 / abs(loop[k]) == pytest.approx(1.3, rel=1e-3)
    assert gains.ti == pytest.approx(tu / 1.2)


def test_every_case_has_a_seed_of_its_own_and_healthy_loops_are_three_times_as_many() -> None:
    todo = cases(2)
    assert len({c.seed for c in todo}) == len(todo)
    healthy = [c for c in todo if not c.expected]
    assert len(healthy) == len(HEALTHY) * 3 * 2 * 3
    assert len(todo) - len(healthy) == (len(FAULTS) + 1) * 3 * 3 * 2  # faults and the deadband


def test_a_sticky_valve_case_is_flagged() -> None:
    case = next(c for c in cases(1) if c.scenario == FAULTS[0].name and c.severity == "severe")
    outcome = run_case(case)
    assert {"oscillating", "stiction"} <= outcome.flags and outcome.recommendation == "check_valve"


def test_the_tables_count_detections_and_false_alarms() -> None:
    sticky, aggressive = FAULTS[0], FAULTS[1]
    outcomes = [
        Outcome(Case(sticky.name, "moderate", "stable", "", 1, sticky.expected),
                frozenset({"oscillating", "stiction"}), "check_valve", 3.3, 0.5, 0.6),
        Outcome(Case(sticky.name, "moderate", "stable", "", 2, sticky.expected), frozenset(), "none", None, None,
                None),
        Outcome(Case(aggressive.name, "moderate", "stable", "", 3, aggressive.expected),
                frozenset({"oscillating"}), "retune", None, 0.98, 0.2),
        Outcome(Case(HEALTHY[0].name, "", "stable", "", 4), frozenset({"sluggish"}), "retune", None, None, None),
        Outcome(Case(HEALTHY[0].name, "", "stable", "", 5), frozenset(), "none", None, None, None),
    ]
    text = table(outcomes)
    assert f"| {sticky.name} | `stiction` | – | 50 % (1/2) | – |" in text
    assert "| `sluggish` | 50 % (1/2) |" in text and "| any | 50 % (1/2) |" in text
    assert "stiction told apart from aggressive tuning in 100 % (2/2)" in text
    assert "median 1.10, from 1.10 to 1.10" in text  # 3.3 against S = 3
    assert f"| {aggressive.name} | stable | 0.98–0.98 | 0.20–0.20 |" in text
