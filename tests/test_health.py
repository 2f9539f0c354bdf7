"""The loop-health assessment end to end: simulated loops with and without faults, and what it says of them."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import scipy.optimize
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from autotuner.benchmarks.health_bench import healthy_gains, margin_gains
from autotuner.engine.health.assessment import Assessment, assess
from autotuner.engine.health.indices import Indices
from autotuner.engine.health.record import LoopRecord
from autotuner.engine.health.scales import LoopLimits, ultimate_period
from autotuner.engine.health.verdict import FLAGS, RECOMMENDATIONS
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.faults import Faults
from drivers.link import Mode
from drivers.sim_record import record_plc
from drivers.simplc import SimulatedPlc

STABLE = "1.5*exp(-0.7*s)/(4*s+1)^2"
INTEGRATING = "0.2*exp(-1*s)/(s*(2*s+1))"
LAG = "2*exp(-0.5*s)/((20*s+1)*(2*s+1))"
LIMITS = LoopLimits(mv=(0.0, 100.0), pv=(0.0, 100.0))


def _loop(expr: str, faults: Faults = Faults(), seed: int = 0, gains: object = None, samples: int = 3600,
          **kw: object) -> tuple[LoopRecord, object]:
    """An hour-long (180 Tu) record of a loop on ``expr`` tuned as the tuner would, with ``faults``."""
    process = parse_process(expr)
    tu = ultimate_period(process)
    plc = SimulatedPlc(process, ts=tu / 20, noise_std=0.05, seed=seed, faults=faults)
    plc.set_gains(gains if gains is not None else healthy_gains(process))
    return record_plc(plc, samples, **kw), process


@pytest.mark.parametrize("expr", [STABLE, INTEGRATING, LAG])
def test_a_sticky_valve_is_sent_to_the_valve_not_to_retuning(expr: str) -> None:
    tu = ultimate_period(parse_process(expr))
    record, process = _loop(expr, Faults(stiction_s=4.5, stiction_j=1.5, load_std=0.2, load_tau=3 * tu))
    result = assess(record, LIMITS, process)
    names = {f.name for f in result.flags}
    assert {"oscillating", "stiction"} <= names, result.to_json()
    assert result.recommendation == "check_valve"
    reason = dict((f.name, f.reason) for f in result.flags)["oscillating"]
    assert "sticking valve" in reason and "oscillates with period" in reason
    band = result.indices.stiction_band
    assert band is not None and 0.6 * 4.5 < band < 2.0 * 4.5  # the MV's swing per cycle, about S


@pytest.mark.parametrize("expr", [STABLE, INTEGRATING, LAG])
@pytest.mark.parametrize("seed", [1, 2])
def test_a_well_tuned_loop_under_noise_and_load_is_flagged_nothing(expr: str, seed: int) -> None:
    tu = ultimate_period(parse_process(expr))
    rng = np.random.default_rng(seed)
    loads = [(float(t), float(rng.choice((-4.0, 4.0)))) for t in np.sort(rng.uniform(0, 180 * tu, 5))]
    record, process = _loop(expr, Faults(load_std=1.0, load_tau=3 * tu), seed, load_steps=loads,
                            sp_steps=[(60 * tu, 60.0), (120 * tu, 50.0)])
    result = assess(record, LIMITS, process)
    assert result.flags == () and result.recommendation == "none", result.to_json()
    assert result.indices.setpoint_steps == 2 and result.indices.overshoot is not None


def test_an_aggressive_loop_oscillates_and_is_sent_to_retuning() -> None:
    process = parse_process(LAG)
    tu = ultimate_period(process)
    record, _ = _loop(LAG, Faults(load_std=0.5, load_tau=3 * tu), gains=margin_gains(process, tu, 1.3))
    result = assess(record, LIMITS, process)
    names = {f.name for f in result.flags}
    assert "oscillating" in names and "stiction" not in names, result.to_json()
    assert result.recommendation == "retune"
    assert result.indices.saturation == 0.0  # a linear oscillation, not a limit cycle through the limits
    # A loop at the limit of stability oscillates where it lags 180°: PI (Ti = Tu/1.2), the process and the
    # hold's half sample (its gain margin 1.3 is the continuous loop's; sampled, it is at the limit).
    ti, ts = tu / 1.2, record.ts

    def lag(w: float) -> float:
        return float(np.angle(-(1 + 1 / (1j * w * ti)) * process.freqresp(w) * np.exp(-0.5j * w * ts)))

    w180 = scipy.optimize.brentq(lag, 0.5 * 2 * math.pi / tu, 2 * math.pi / tu)
    assert result.indices.oscillation_period == pytest.approx(2 * math.pi / w180, rel=0.05)


def test_a_loop_held_in_manual_is_flagged_manual() -> None:
    process = parse_process(STABLE)
    tu = ultimate_period(process)
    plc = SimulatedPlc(process, ts=tu / 20, noise_std=0.05, faults=Faults(load_std=0.5, load_tau=3 * tu))
    plc.mode = Mode.MAN
    result = assess(record_plc(plc, 3600), LIMITS, process)
    assert [f.name for f in result.flags] == ["manual"] and result.recommendation == "put_in_auto"
    assert result.flags[0].severity.value == "high" and "100 %" in result.flags[0].reason
    assert result.indices.utilization == 0.0 and result.indices.oscillation_rate is None


def test_a_frozen_sensor_is_sent_to_the_sensor() -> None:
    tu = ultimate_period(parse_process(STABLE))
    record, process = _loop(STABLE, Faults(load_std=1.0, load_tau=3 * tu, frozen_at=90 * tu))
    result = assess(record, LIMITS, process)
    assert "frozen_pv" in {f.name for f in result.flags} and result.recommendation == "check_sensor"
    assert result.indices.frozen_share == pytest.approx(0.5, abs=0.01)


def test_a_sinusoidal_error_reports_its_period_and_amplitude() -> None:
    t = np.arange(3600) * 1.0
    pv = 50.0 + 1.8 * np.sin(2 * math.pi * t / 42.0)
    mv = 50.0 - 3.0 * np.sin(2 * math.pi * t / 42.0 + 0.3)
    result = assess(LoopRecord.of(t, np.full(3600, 50.0), pv, mv), LIMITS)
    assert result.indices.oscillation_period == pytest.approx(42.0, abs=0.5)
    assert result.indices.oscillation_amplitude == pytest.approx(1.8, rel=0.01)
    reason = dict((f.name, f.reason) for f in result.flags)["oscillating"]
    assert reason.startswith("oscillates with period 42 s and amplitude 1.8")


def test_only_the_window_is_assessed() -> None:
    process = parse_process(STABLE)
    tu = ultimate_period(process)
    plc = SimulatedPlc(process, ts=tu / 20, noise_std=0.05, seed=3)
    plc.set_gains(healthy_gains(process))
    plc.mode = Mode.MAN
    first = record_plc(plc, 1000)
    plc.mode = Mode.AUTO
    second = record_plc(plc, 2000)
    record = LoopRecord.of(*(np.concatenate((getattr(first, n), getattr(second, n)))
                             for n in ("t", "sp", "pv", "mv", "auto")))
    assert "manual" in {f.name for f in assess(record, LIMITS, process).flags}
    recent = assess(record, LIMITS, process, window=1500 * tu / 20)
    assert recent.samples == 1501 and recent.flags == ()


def test_the_dead_time_source_is_named() -> None:
    record, process = _loop(STABLE, samples=600)
    with_model = assess(record, LIMITS, process)
    without = assess(record, LIMITS)
    assert (with_model.dead_time_source, with_model.indices.dead_time) == ("model", 0.7)
    assert (without.dead_time_source, without.indices.dead_time) == ("one sample", pytest.approx(record.ts))


def test_the_assessment_as_json() -> None:
    tu = ultimate_period(parse_process(STABLE))
    record, process = _loop(STABLE, Faults(stiction_s=4.5, stiction_j=1.5, load_std=0.2, load_tau=3 * tu))
    out = json.loads(json.dumps(assess(record, LIMITS, process).to_json()))
    assert set(out) == {"flags", "recommendation", "reasons", "severities", "indices", "dead_time_source", "window"}
    assert set(out["flags"]) <= set(FLAGS) and out["recommendation"] in RECOMMENDATIONS
    assert set(out["reasons"]) == set(out["flags"]) == set(out["severities"])
    assert set(out["indices"]) == {f.name for f in dataclasses.fields(Indices)}
    assert out["window"]["samples"] == 3600


def test_every_field_says_what_it_holds() -> None:
    for cls in (Assessment, Indices):
        for f in dataclasses.fields(cls):
            assert f.metadata.get("description"), f"{cls.__name__}.{f.name}"


def test_too_short_a_window_is_refused() -> None:
    record = LoopRecord.of(np.arange(10.0), np.zeros(10), np.zeros(10), np.zeros(10))
    with pytest.raises(ValueError, match="10 samples in the window: an assessment needs at least 20"):
        assess(record)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(40, 400), st.integers(0, 2 ** 32 - 1), st.sampled_from(["noise", "steps", "constant", "mixed"]))
def test_any_valid_record_gets_an_assessment_in_strict_json(n: int, seed: int, kind: str) -> None:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.5, 1.5, n)) if kind == "mixed" else np.arange(n, dtype=float)
    signals = {
        "noise": lambda: 50 + rng.standard_normal(n),
        "steps": lambda: np.repeat(rng.uniform(0, 100, n // 10 + 1), 10)[:n],
        "constant": lambda: np.full(n, 42.0),
        "mixed": lambda: 50 + np.cumsum(rng.standard_normal(n)),
    }[kind]
    auto = rng.random(n) > 0.2 if kind == "mixed" else None
    model = parse_process(STABLE) if seed % 2 else None
    result = assess(LoopRecord.of(t, signals(), signals(), signals(), auto), LIMITS, model)
    out = json.loads(json.dumps(result.to_json(), allow_nan=False))
    assert set(out["flags"]) <= set(FLAGS) and out["recommendation"] in RECOMMENDATIONS
