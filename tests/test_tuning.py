"""End to end in simulation: experiment + design on one process of each batch family, judged on the true process."""

from __future__ import annotations

import json
import math

import pytest

from autotuner.benchmarks.design_bench import default_batch, load_batch
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.design.closed_loop import check_gains
from autotuner.engine.outcome import Code
from autotuner.engine.experiment.relay import RelayConfig
from autotuner.engine.design.robustness import Plant, check_loop, log_grid, migo, pid_frequency_response
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import default_sample_time, phase_frequency, tune

ROWS = {row["id"]: row for row in load_batch(default_batch())}
# One process per family, the lag-dominant and dead-time-dominant ends included.
SAMPLE = ["P1-003", "P1-019", "P2-040", "P3-050", "P4-056", "P5-060", "P6-070", "P7-086", "P8-123", "P9-130"]


def true_ms(process, gains, w) -> float:
    return check_loop(
        process.freqresp,
        lambda x: pid_frequency_response(x, gains.k, gains.ti, gains.td, gains.nd),
        w,
        integrators=process.integrator_count + 1,
    ).ms


@pytest.mark.parametrize("row_id", SAMPLE)
def test_pi_and_pid_are_robust_on_the_true_process(row_id):
    process = parse_process(ROWS[row_id]["expr"])
    w135 = phase_frequency(process, 135.0)
    config = RelayConfig(amp=1.0, time_limit=200 * 2 * math.pi / w135)
    ts = default_sample_time(process)
    limit = float(ROWS[row_id]["migo_pi_ki"])  # independent MIGO figure of the batch
    w = log_grid(w135)
    pi = tune(PlantSim(process, ts), config, "PI")
    pid = tune(PlantSim(process, ts), config, "PID")
    assert pi.ok and pid.ok, (pi.message, pid.message)
    point = pi.identification.point
    true = complex(process.freqresp(point.omega))
    assert abs(point.value - true) / abs(true) < 0.01
    for result in (pi, pid):
        ms = true_ms(process, result.design.gains, w)
        assert 1.3 < ms <= 1.6, (result.controller, ms)
    assert pi.design.gains.ki / limit > 0.8
    assert pid.design.gains.ki >= pi.design.gains.ki * 0.999


def test_pid_gains_integral_action_where_derivative_helps():
    # Lag-dominant, noise-free: derivative action buys integral gain at the same Ms.
    process = parse_process("exp(-s)/(10*s+1)^2")
    w135 = phase_frequency(process, 135.0)
    ts = default_sample_time(process)
    config = RelayConfig(amp=1.0, time_limit=200 * 2 * math.pi / w135)
    pi = tune(PlantSim(process, ts), config, "PI")
    pid = tune(PlantSim(process, ts), config, "PID")
    assert pid.design.gains.ki > 1.5 * pi.design.gains.ki
    assert pid.design.gains.td > 0.0
    plant = Plant(process.freqresp)
    assert pi.design.gains.ki <= 1.3 * migo([plant], w135, 1.4).ki


def test_ms_option_changes_the_robustness():
    process = parse_process("exp(-s)/(2*s+1)")
    w135 = phase_frequency(process, 135.0)
    ts = default_sample_time(process)
    config = RelayConfig(amp=1.0, time_limit=200 * 2 * math.pi / w135)
    w = log_grid(w135)
    tight = tune(PlantSim(process, ts), config, "PI", ms=1.2).design.gains
    loose = tune(PlantSim(process, ts), config, "PI", ms=2.0).design.gains
    assert true_ms(process, tight, w) == pytest.approx(1.2, abs=0.03)
    assert true_ms(process, loose, w) == pytest.approx(2.0, abs=0.1)
    assert loose.ki > tight.ki


def test_result_json_shape_on_success_and_failure():
    process = parse_process("exp(-s)/(2*s+1)")
    ts = default_sample_time(process)
    ok = tune(PlantSim(process, ts), RelayConfig(amp=1.0, time_limit=500.0)).as_json()
    text = json.dumps(ok, allow_nan=False)
    assert json.loads(text) == ok
    assert set(ok) == {"tbsy", "te", "ite", "message", "controller", "point", "static_gain", "gains", "design",
                       "forms", "experiment"}
    assert set(ok["forms"]) == {"parallel", "series"} and set(ok["forms"]["parallel"]) == {"kp", "ki", "kd"}
    assert set(ok["design"]) == {"model", "ms_model", "ms_target", "noise_gain", "notes"}
    assert ok["design"]["notes"] == [] and ok["design"]["ms_model"] == pytest.approx(1.4, abs=0.01)
    assert ok["te"] is False and ok["ite"] == 0 and ok["tbsy"] is False
    assert set(ok["gains"]) == {"pk", "pti", "ptd", "pnd", "pb", "pc"}
    assert set(ok["experiment"]) == {"duration", "periods", "samples", "phase_target_deg", "phase_moved",
                                      "disturbance", "load_estimate"}
    assert ok["experiment"]["samples"] > 0 and ok["experiment"]["duration"] > 0

    failed = tune(PlantSim(process, ts), RelayConfig(amp=1.0, pv_limits=(-0.1, 0.1))).as_json()
    assert failed["te"] is True and failed["ite"] == int(Code.PV_OUT_OF_LIMITS)
    assert failed["gains"] is None and failed["design"] is None and failed["forms"] is None
    assert failed["experiment"]["phase_target_deg"] is None and failed["experiment"]["phase_moved"] is None
    assert failed["experiment"]["disturbance"] is None and failed["experiment"]["load_estimate"] is None
    assert "limits" in failed["message"]


def test_unstable_process_is_stabilised_by_the_design():
    """The README's example: a negative static gain is an unstable process, not an error (design notes)."""
    process = parse_process("exp(-0.2*s)/(2*s-1)")
    result = tune(PlantSim(process, 0.02), RelayConfig(amp=1.0, time_limit=200.0))
    assert result.ok, result.message
    assert result.identification.static_gain == pytest.approx(-1.0, rel=0.02)
    assert result.design.model.rhp_pole_count == 1
    check = check_gains(process, result.design.gains, log_grid(result.identification.point.omega))
    assert check.stable and check.ms <= 1.45
