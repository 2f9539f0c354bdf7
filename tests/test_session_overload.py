"""A session's own lateness that the tolerance of its moment let pass, judged at the experiment's end
(link_session._Sampling.design_job, Overload.longest).

Early in a run the period is not known and the experiment tolerates a stall of a tenth of the period expected; once
the period is measured, a tenth of it. A session that stalled in between, by more than the experiment tolerates at
its end, may have caused a verdict about the process: that verdict is the tuner's (OVERLOADED). Driven without
clocks: the session's pieces built as tune_link builds them, its reads' due and start times chosen, the PV a
simulated plant's sampled at the times read.
"""

from __future__ import annotations

import math

import pytest

from autotuner.engine.experiment.relay import RelayConfig, RelayExperiment
from autotuner.engine.outcome import Code
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import phase_frequency
from autotuner.service.link_session import BLAMES_PROCESS, SessionHooks, SessionPlan, _Sampling
from drivers.simlink import SimLink
from drivers.simplc import SimulatedPlc

PLANT = "exp(-s)/(2*s+1)"
SPEED = 5.0  # plant seconds per wall second: the session judges its lateness in wall seconds
SAMPLES_PER_PERIOD = 100
# The stall comes this many samples into the relay, before its first switch: the period is not measured yet.
STALL_INTO_RELAY = 5


def stalled_session(stall: int) -> _Sampling:
    """A session on PLANT whose reads all start when due but one, early in the relay, which starts ``stall`` sample
    times late (the plant runs on meanwhile at the MV held; the samples due meanwhile, read back to back after
    it, bring nothing new and are left out). The operator's expected period is five times the real one, and the
    time limit of three periods leaves the cycle no time to settle: the experiment ends NOT_CONVERGED."""
    process = parse_process(PLANT)
    period = 2.0 * math.pi / phase_frequency(process, 135.0)
    ts = period / SAMPLES_PER_PERIOD
    relay = RelayConfig(amp=1.0, time_limit=3.0 * period, expected_period=5.0 * period)
    plan = SessionPlan(relay, ts, speed=SPEED)
    sim = PlantSim(process, ts)
    experiment = RelayExperiment(relay, sim.mv0)
    sampling = _Sampling(SimLink(SimulatedPlc(process, ts=ts)), experiment, plan, SessionHooks())
    stall_at = relay.noise_samples + STALL_INTO_RELAY
    k, mv = 0, sim.mv0
    while not experiment.done:
        due = k * ts / SPEED
        if k == stall_at:
            for _ in range(stall):
                sim.advance(mv)
            k += stall
        sampling.overload.sample(due, k * ts / SPEED, sampling.tolerance)
        mv = experiment.step(sim.t, sim.measure())
        sim.advance(mv)
        k += 1
        # (As _Sampling._catch_up: a period's analysis, then the experiment read outside it, while it runs.)
        if experiment.analysis_pending:
            experiment.analyse()
        if not experiment.done:
            sampling.observe()
    return sampling


def test_a_stall_the_wide_early_tolerance_let_pass_turns_a_verdict_on_the_process_into_overloaded() -> None:
    # 30 samples: 0.3 of the period, within the 0.5 tolerated before it is measured, beyond the tenth of the period
    # measured at the end (which the stall itself threw off: 0.066 of the real one).
    sampling = stalled_session(30)
    experiment, overload, ts = sampling.experiment, sampling.overload, sampling.plan.ts
    assert experiment.code is Code.NOT_CONVERGED and experiment.code in BLAMES_PROCESS, experiment.message
    assert overload.count == 0  # never beyond the tolerance of its moment
    assert overload.longest == pytest.approx(30 * ts / SPEED, rel=1e-9)
    assert overload.longest > 2.0 * sampling.tolerance
    job = sampling.design_job()
    assert job.code is Code.OVERLOADED and job.identification is None
    assert "by the tuner itself" in job.message and "not the link's delay" in job.message
    assert f"the longest {30 * ts:.3g} s late" in job.message  # plant seconds
    assert f"(the experiment had ended: {experiment.message})" in job.message


def test_a_stall_within_what_the_experiment_tolerates_at_its_end_keeps_the_verdict_on_the_process() -> None:
    # 5 samples: 0.05 of the period, within the 0.1 tolerated at the end.
    sampling = stalled_session(5)
    experiment, overload = sampling.experiment, sampling.overload
    assert experiment.code is Code.NOT_CONVERGED, experiment.message
    assert overload.count == 0
    assert overload.longest == pytest.approx(5 * sampling.plan.ts / SPEED, rel=1e-9)
    assert overload.longest < sampling.tolerance
    job = sampling.design_job()
    assert job.code is Code.NOT_CONVERGED and job.message == experiment.message
