"""The filter aimed by a process model fitted to the record (issue 28): the fit, the relay cycle it predicts, and
the shorter runs it gives.

* process_fit.fit recovers a two-lag process with dead time from a relay record it could hold exactly;
* relay_cycle.filter_phase's cycle is the one a relay behind that filter settles to, simulated here sample by
  sample with the experiment's own switching (sub-sample crossing, the MV blended over the switch's interval);
* fixed processes of the batch that main (8c2ed09) tuned in 4.0–4.6 periods tune within AIMED (3.6) each,
  with their points within 0.25 % of F(jω) written out and their static gains within 2 %.
"""

from __future__ import annotations

import cmath
import math

import numpy as np
import pytest

from autotuner.engine.experiment import process_fit, relay_cycle
from autotuner.engine.experiment.phase_filter import PhaseFilter
from autotuner.engine.experiment.record import Samples
from autotuner.engine.experiment.relay import Identification, RelayConfig
from autotuner.engine.outcome import Code
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import EXPERIMENT_SAMPLES_PER_PERIOD, phase_frequency, run_experiment


def _relay_record(expr: str, theta: float, omega: float, dt: float, periods: float, high: float = 1.0,
                  low: float = -0.6) -> tuple[Samples, list[float]]:
    """A relay (levels ``high``/``low`` about 0, no hysteresis) behind the filter of phase ``theta`` at ``omega``
    on ``expr`` from rest, sampled every ``dt`` s for ``periods`` × 2π/``omega``: the record (as held) and the
    sub-sample times of its rising crossings. The switching is the experiment's (switching.py): the crossing
    interpolated between samples, the switch's sample holding the MV that keeps the area of a switch there."""
    sim = PlantSim(parse_process(expr), dt)
    phase_filter = PhaseFilter()
    phase_filter.set_phase(theta, omega)
    relay, before, mv = 1, 0.0, high
    t, y, u, rising = [], [], [], []
    for _ in range(int(periods * 2.0 * math.pi / omega / dt)):
        pv = sim.measure()
        e = phase_filter.step(-pv, dt)
        now = high if relay > 0 else low
        if relay > 0 and e < 0.0 or relay < 0 and e > 0.0:
            crossing = sim.t - dt + (0.0 - before) / (e - before) * dt
            relay = -relay
            late = (crossing - (sim.t - dt)) / dt
            now = mv * late + (high if relay > 0 else low) * (1.0 - late)
            if relay > 0:
                rising.append(crossing)
        before = e
        mv = now if now in (high, low) else (high if relay > 0 else low)
        t.append(sim.t)
        y.append(pv)
        u.append(now)
        sim.advance(now)
    times = np.asarray(t)
    return Samples(t=times, y=np.asarray(y), u=np.asarray(u), s=times), rising


def test_fit_recovers_a_two_lag_process_with_dead_time() -> None:
    # 2·e^{−0.7s}/((3s + 1)(1.2s + 1)): a record of a relay's start, a period and a half, as the fit gets it.
    omega = 0.45
    record, rising = _relay_record("2*exp(-0.7*s)/((3*s+1)*(1.2*s+1))", 0.3, omega, 0.05, 2.0)
    model = process_fit.fit(record, 0.0, rising[1] - rising[0])
    assert model is not None
    assert model.k0 == pytest.approx(2.0, rel=1e-3)
    assert model.t1 == pytest.approx(3.0, rel=1e-3)
    assert model.t2 == pytest.approx(1.2, rel=2e-3)
    assert model.delay == pytest.approx(0.7, abs=2e-3)
    assert model.misfit < 1e-4
    # Its lag at ω, written out: atan(3ω) + atan(1.2ω) + 0.7ω.
    assert model.lag(0.5) == pytest.approx(math.atan(1.5) + math.atan(0.6) + 0.35, abs=1e-3)
    assert model.frequency(model.lag(0.5)) == pytest.approx(0.5, rel=1e-9)


@pytest.mark.parametrize("expr, f", [
    ("exp(-s)/(10*s+1)", lambda s: cmath.exp(-s) / (10 * s + 1)),
    ("exp(-0.3*s)/((s+1)*(0.5*s+1))", lambda s: cmath.exp(-0.3 * s) / ((s + 1) * (0.5 * s + 1))),
    ("exp(-s)/(0.05*s+1)", lambda s: cmath.exp(-s) / (0.05 * s + 1)),
])
def test_the_predicted_filter_puts_the_simulated_cycle_at_the_chosen_frequency(expr, f) -> None:
    process = parse_process(expr)
    omega = phase_frequency(process, 135.0)
    dt = 2.0 * math.pi / omega / EXPERIMENT_SAMPLES_PER_PERIOD
    response = np.array([f(1j * n * omega) for n in range(1, relay_cycle.HARMONICS + 1)])
    theta = relay_cycle.filter_phase(response, omega, f(0.0).real, 1.0, -0.6, 0.0, 0.5 * dt, 0.6)
    assert theta is not None
    _, rising = _relay_record(expr, theta, omega, dt, 40.0)
    settled = 2.0 * math.pi / (rising[-1] - rising[-2])
    # The describing function's balance (θ = π − 135° − ωdt/2) puts these cycles 2.0–4.9 % off ω.
    assert settled == pytest.approx(omega, rel=2e-3)


AIMED = 3.6

CASES = [  # batch id, expression, the same F(s) in closed form, static gain; periods on main (8c2ed09)
    ("P1-019", "exp(-s)/(200*s+1)", lambda s: cmath.exp(-s) / (200 * s + 1), 1.0),  # 4.56
    ("P2-035", "exp(-s)/(6*s+1)^2", lambda s: cmath.exp(-s) / (6 * s + 1) ** 2, 1.0),  # 4.4
    ("P4-056", "1/(s+1)^6", lambda s: 1 / (s + 1) ** 6, 1.0),  # 4.0
    ("P5-063", "1/((s+1)*(0.5*s+1)*(0.25*s+1)*(0.125*s+1))",
     lambda s: 1 / ((s + 1) * (0.5 * s + 1) * (0.25 * s + 1) * (0.125 * s + 1)), 1.0),  # 4.0
]


def identified(expr: str) -> Identification:
    """The experiment's result on ``expr`` at the bench's conditions (amp 1, noise-free); it must end "ok"."""
    process = parse_process(expr)
    period = 2.0 * math.pi / phase_frequency(process, 135.0)
    sim = PlantSim(process, period / EXPERIMENT_SAMPLES_PER_PERIOD)
    experiment, _ = run_experiment(sim, RelayConfig(amp=1.0, time_limit=200 * period))
    assert experiment.code is Code.OK, experiment.message
    return experiment.result


@pytest.mark.parametrize("expr, f, k0", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_model_aimed_runs_are_shorter_and_as_accurate(expr, f, k0) -> None:
    result = identified(expr)
    assert result.periods <= AIMED
    true = complex(f(1j * result.point.omega))
    assert abs(result.point.value - true) / abs(true) <= 0.0025
    assert abs(result.point.phase_deg + 135.0) <= 0.5
    assert result.static_gain == pytest.approx(k0, rel=0.02)
