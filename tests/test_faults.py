"""The simulated loop's faults against hand computation: Choudhury's valve on a known MV sequence, the
deadband as the play operator, the stochastic load's statistics, the sinusoid, the frozen sensor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.faults import Faults, FaultyLoop
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.plant.valve import StickyValve
from drivers.simplc import SimulatedPlc

# S = 4, J = 2 (so (S − J)/2 = 1), worked by hand from Choudhury's rules:
U = [50, 51, 52, 53, 54, 55, 54, 53, 52, 51, 50, 50, 49, 48, 47, 48, 52]
X = [50, 50, 50, 52, 53, 54, 54, 54, 54, 54, 51, 51, 51, 51, 48, 48, 51]
# 50: at rest, in the middle of its band; 51, 52: within S/2 = 2 of the start; 53: slips, 53 − 1; 54, 55:
# moving, u − 1; 54 … 51: reversed at 55, within S = 4 of it; 50: 5 beyond, slips to 50 + 1; 50: stops (stuck
# at 50, moving down); 49, 48: on the same way, within J = 2; 47: slips to 47 + 1; 48: reversed at 47, within
# S; 52: 5 beyond 47, slips to 52 − 1.


def test_choudhury_valve_on_a_known_sequence() -> None:
    valve = StickyValve(4.0, 2.0)
    assert [valve.step(float(u)) for u in U] == [float(x) for x in X]


def test_a_valve_that_only_wanders_back_within_its_band_does_not_move_backwards() -> None:
    valve = StickyValve(4.0, 0.0)
    out = [valve.step(u) for u in (50.0, 53.0, 54.0, 52.0, 53.0, 53.5)]
    assert out == [50.0, 51.0, 52.0, 52.0, 52.0, 52.0]  # 53 and 53.5: back up, still short of 54


def test_deadband_is_the_play_operator() -> None:
    width = 3.0
    u = 50.0 + np.cumsum(np.random.default_rng(1).normal(0.0, 0.7, 2000))
    valve = StickyValve(width, 0.0)
    x = u[0]
    for value in u:
        x = min(max(x, value - width / 2), value + width / 2)  # the play (backlash) operator
        assert valve.step(float(value)) == pytest.approx(x, abs=1e-12)


def test_valve_parameters_are_checked() -> None:
    with pytest.raises(ValueError, match="valve j must be a finite number ≥ 0"):
        StickyValve(1.0, -1.0)


def _unity(faults: Faults, ts: float = 1.0, seed: int | None = 0) -> FaultyLoop:
    """The faults around the plant F(s) = 1 at 0: PV[k+1] − pv0 = what reached the process input over k."""
    return FaultyLoop(faults, PlantSim(parse_process("1"), ts), span=100.0, seed=seed)


def test_valve_inside_the_loop_drives_the_plant_with_its_position() -> None:
    loop = _unity(Faults(stiction_s=4.0, stiction_j=2.0))  # % of a 100 span: MV units
    seen = []
    for u in U:
        assert loop.advance(float(u)) == float(u)  # the controller output is what the PLC shows
        seen.append(loop.measure())
    assert seen == [float(x) for x in X]


def test_deadband_adds_to_the_stickband() -> None:
    assert Faults(stiction_s=2.0, deadband=1.5).valve_band == 3.5


def test_stochastic_load_is_first_order_filtered_noise_of_its_standard_deviation() -> None:
    ts, tau, sigma = 1.0, 20.0, 2.0
    loop = _unity(Faults(load_std=sigma, load_tau=tau), ts)
    load = []
    for _ in range(200_000):
        loop.advance(0.0)
        load.append(loop.measure())
    x = np.array(load[1000:])
    assert float(np.std(x)) == pytest.approx(sigma, rel=0.05)
    lag1 = float(np.corrcoef(x[:-1], x[1:])[0, 1])
    assert lag1 == pytest.approx(math.exp(-ts / tau), abs=0.01)


def test_sinusoidal_disturbance() -> None:
    ts, amplitude, period = 0.5, 3.0, 20.0
    loop = _unity(Faults(sine_amplitude=amplitude, sine_period=period), ts)
    for k in range(100):
        loop.advance(0.0)
        # held over [k·ts, (k+1)·ts), seen at (k+1)·ts
        assert loop.measure() == pytest.approx(amplitude * math.sin(2 * math.pi * k * ts / period), abs=1e-12)


def test_frozen_sensor_reads_the_same_value_from_its_time_on() -> None:
    loop = FaultyLoop(Faults(frozen_at=10.0), PlantSim(parse_process("1"), 1.0, noise_std=0.5, seed=3),
                      span=100.0, seed=0)
    readings = []
    for k in range(30):
        loop.advance(float(k))
        readings.append(loop.measure())
    assert len(set(readings[:9])) == 9  # live: the input and the noise move it
    assert readings[9:] == [readings[9]] * 21  # from t = 10 s on


@pytest.mark.parametrize("bad, message", [
    (dict(stiction_s=-1.0), "stiction_s must be a finite number ≥ 0"),
    (dict(load_std=1.0), "needs its time constant"),
    (dict(sine_amplitude=1.0), "needs its period"),
])
def test_fault_parameters_are_checked(bad: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Faults(**bad)


def test_plc_with_a_sticky_valve_shows_the_controller_output_and_limits_it() -> None:
    plc = SimulatedPlc(parse_process("exp(-1*s)/(5*s+1)"), ts=0.5, faults=Faults(stiction_s=5.0, stiction_j=1.0))
    plc.sp = 60.0
    outputs = []
    for _ in range(400):
        plc.tick()
        outputs.append(plc.mv)
    assert plc.pid.mv == plc.mv  # the PID unit's output, not the valve's position
    assert min(outputs) >= 0.0 and max(outputs) <= 100.0
    assert abs(plc.pv - 60.0) < 5.0  # the loop still controls, in its stick-slip way


def test_without_faults_the_plc_runs_as_before() -> None:
    a = SimulatedPlc(parse_process("exp(-1*s)/(5*s+1)"), ts=0.5, noise_std=0.1, seed=4)
    b = SimulatedPlc(parse_process("exp(-1*s)/(5*s+1)"), ts=0.5, noise_std=0.1, seed=4, faults=Faults())
    for plc in (a, b):
        plc.sp = 55.0
        for _ in range(200):
            plc.tick()
    assert (a.pv, a.mv) == (b.pv, b.mv)
