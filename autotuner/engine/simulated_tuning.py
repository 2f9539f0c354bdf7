"""One tuning of a simulated loop: experiment, design, result — clocked by the simulation.

This is the session layer for simulation: it owns the (simulated) clock,
feeds the experiment its samples, and turns the outcome into the result that
the CLI prints and the daemon reports (design.md, the JSON of ``autotuner
tune``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from autotuner.engine.design.point_design import Design, design
from autotuner.engine.design.unstable_design import Refusal
from autotuner.engine.design.process_data import exact_point
from autotuner.engine.plant.process import Process
from autotuner.engine.outcome import MESSAGES, Code
from autotuner.engine.result import Trace, TuneResult
from autotuner.engine.experiment.relay import Identification, RelayConfig, RelayExperiment, Status
from autotuner.engine.plant.simulation import PlantSim

# Samples per oscillation period of the default sample time (default_sample_time).
EXPERIMENT_SAMPLES_PER_PERIOD = 100
# Time limit of a simulated experiment: this many expected periods of the
# oscillation, or this many samples when the plant never reaches the phase.
LIMIT_PERIODS = 200
LIMIT_SAMPLES = 20000


def phase_frequency(process: Process, phase_deg: float) -> float | None:
    """Lowest frequency (rad/s) where the process lags by ``phase_deg`` degrees, or None if it never does.

    ``process``: the process.
    """
    point = exact_point(process, phase_deg)
    return None if point is None else point.omega


def default_sample_time(process: Process, phase_deg: float = 135.0) -> float:
    """A sample time (s) giving about 100 samples per period of the oscillation at ``phase_deg``.

    A process that never reaches that lag gets 1/100 of its slowest time constant or dead time;
    one without either (``K/s``, ``K/s²``: integrators only, whose phase says nothing about time)
    1/100 of the period where its gain is 1, the natural scale of a relay loop around it.

    ``process``: the process.
    """
    w = phase_frequency(process, phase_deg)
    if w is not None:
        return 2.0 * math.pi / w / EXPERIMENT_SAMPLES_PER_PERIOD
    scales = [1.0 / abs(p) for p in process.poles if abs(p) > 1e-12] + [process.delay]
    if max(scales) > 0.0:
        return max(scales) / EXPERIMENT_SAMPLES_PER_PERIOD
    n = max(process.integrator_count, 1)
    gain = abs(process.num[-1] / process.den[-1 - n]) if process.den[-1 - n] else 1.0
    crossover = gain ** (1.0 / n)  # |K/(jω)^n| = 1
    return 2.0 * math.pi / crossover / EXPERIMENT_SAMPLES_PER_PERIOD


def default_time_limit(process: Process, phase_deg: float, ts: float) -> float:
    """Longest simulated experiment, s: ``LIMIT_PERIODS`` expected periods at ``phase_deg``, else
    ``LIMIT_SAMPLES`` samples of ``ts`` seconds.

    ``process``: the process.
    """
    w = phase_frequency(process, phase_deg)
    return LIMIT_PERIODS * 2.0 * math.pi / w if w is not None else LIMIT_SAMPLES * ts


def ramp_loads(rate: float, ts: float, until: float) -> list[tuple[float, float]]:
    """A load ramp of ``rate`` MV units per second from t = 0 as load steps at every sample up to ``until`` s.

    Sampled this way the load at sample ``k`` is ``rate·k·ts``, the ramp held over each sample interval.
    """
    if rate == 0.0:
        return []
    return [(k * ts, rate * ts) for k in range(1, int(math.ceil(until / ts)) + 2)]


@dataclass
class CallTimes:
    """The time each call into the experiment took, read from the caller's clock (the engine reads none).

    clock: returns seconds (the benchmarks pass ``time.process_time``: CPU time).
    step: seconds of each :meth:`RelayExperiment.step` call without the analysis it ran first;
    analyse: seconds of each period's analysis (one per switch of the relay).
    """

    clock: Callable[[], float]
    step: list[float] = field(default_factory=list)
    analyse: list[float] = field(default_factory=list)


class _TimedExperiment(RelayExperiment):
    """The experiment with each period's analysis timed where :meth:`RelayExperiment.step` runs it (at the
    next sample, first): the same calls in the same order as untimed, so the same results."""

    def __init__(self, config: RelayConfig, mv0: float, times: CallTimes) -> None:
        super().__init__(config, mv0)
        self._times = times

    def analyse(self) -> None:
        """:meth:`RelayExperiment.analyse`, its time recorded when there was a period to analyse."""
        if not self.analysis_pending:
            return
        start = self._times.clock()
        super().analyse()
        self._times.analyse.append(self._times.clock() - start)


def _timed_step(experiment: RelayExperiment, t: float, pv: float, times: CallTimes) -> float:
    """``experiment.step(t, pv)``, timed without the analysis it runs first (timed on its own)."""
    analyses = len(times.analyse)
    start = times.clock()
    mv = experiment.step(t, pv)
    times.step.append(times.clock() - start - sum(times.analyse[analyses:]))
    return mv


def run_experiment(
    sim: PlantSim,
    config: RelayConfig,
    on_status: Callable[[Status], None] | None = None,
    status_every: int = 50,
    times: CallTimes | None = None,
) -> tuple[RelayExperiment, Trace]:
    """Drive the experiment with ``config`` against the simulation ``sim`` until it ends; the MV starts at the
    plant's ``mv0``.

    ``on_status`` gets the status every ``status_every`` samples (and at the end); ``times``, when
    given, records how long each step and each period's analysis took.
    """
    experiment = RelayExperiment(config, mv0=sim.mv0) if times is None else _TimedExperiment(config, sim.mv0, times)
    ts, pvs, mvs = [], [], []
    n = 0
    while not experiment.done:
        t, pv = sim.t, sim.measure()
        mv = experiment.step(t, pv) if times is None else _timed_step(experiment, t, pv, times)
        ts.append(t)
        pvs.append(pv)
        mvs.append(mv)
        sim.advance(mv)
        n += 1
        if on_status is not None and n % status_every == 0:
            on_status(experiment.status())
    if on_status is not None:
        on_status(experiment.status())
    return experiment, Trace(np.asarray(ts), np.asarray(pvs), np.asarray(mvs))


@dataclass(frozen=True)
class DesignJob:
    """What the design needs from an ended experiment (all of it: under 1 KB pickled, for a design worker).

    ``identification``: what the experiment identified (None: nothing, no
    design); ``code`` and ``message``: how the experiment ended; ``controller``
    "PI" or "PID", designed for maximum sensitivity ``ms``; ``amp``: the relay
    amplitude, MV units (the PID's noise budget).
    """

    identification: Identification | None
    code: Code
    message: str
    controller: str
    ms: float
    amp: float

    @classmethod
    def of(cls, experiment: RelayExperiment, controller: str, ms: float) -> "DesignJob":
        """The job of an ended ``experiment``.

        ``controller``: ``"PI"`` or ``"PID"``; ``ms``: the maximum sensitivity designed for.
        """
        return cls(experiment.result, experiment.code or Code.OK, experiment.message, controller, ms,
                   experiment.config.amp)

    def run(self) -> tuple[Code, str, Design | None]:
        """The outcome: code and message, and the design (None: none).

        A design that missed something it was asked for (its notes) turns an OK
        experiment into that warning code: ``te`` stays false, the message names
        the miss. A refused design carries its own code (e.g. an unstable process
        with too long a dead time).
        """
        ident = self.identification
        code, message = self.code, self.message
        if ident is None:
            return code, message, None
        try:
            des = design(ident.point, ident.static_gain, self.controller, self.ms, noise_std=ident.noise_std,
                         amp=self.amp, static_gain_std=ident.static_gain_std)
        except Refusal as exc:
            return exc.code, f"{MESSAGES[exc.code]}: {exc}", None
        except ValueError as exc:
            return Code.NO_DESIGN, f"{MESSAGES[Code.NO_DESIGN]}: {exc}", None
        if code is Code.OK and des.warning is not Code.OK:
            code, message = des.warning, f"{MESSAGES[des.warning]}: " + "; ".join(des.notes)
        return code, message, des

    def result(self, trace: Trace) -> TuneResult:
        """The result of the experiment with its design (:meth:`run`) and ``trace``."""
        code, message, des = self.run()
        return TuneResult(code, message, self.controller, self.identification, des, trace)


def result_of(experiment: RelayExperiment, trace: Trace, controller: str, ms: float) -> TuneResult:
    """The outcome of an ended ``experiment`` and its ``trace``, with ``controller`` designed for ``ms`` on success
    (:class:`DesignJob`)."""
    return DesignJob.of(experiment, controller, ms).result(trace)


def tune(
    sim: PlantSim,
    config: RelayConfig,
    controller: str = "PI",
    ms: float = 1.4,
    on_status: Callable[[Status], None] | None = None,
    times: CallTimes | None = None,
) -> TuneResult:
    """Run the experiment on ``sim`` and design ``controller`` ("PI" or "PID") for maximum sensitivity ``ms``.

    ``on_status`` gets the experiment's status every 50 samples; ``times`` records each call's time
    (:func:`run_experiment`).

    ``config``: the experiment's settings.
    """
    experiment, trace = run_experiment(sim, config, on_status, times=times)
    return result_of(experiment, trace, controller, ms)
