"""One tuning of a simulated loop: experiment, design, result — clocked by the simulation.

This is the session layer for simulation: it owns the (simulated) clock,
feeds the experiment its samples, and turns the outcome into the result that
the CLI prints and the daemon reports (design.md, the JSON of ``autotuner
tune``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from autotuner.engine.design.point_design import Design, design
from autotuner.engine.design.process_data import exact_point
from autotuner.engine.plant.process import Process
from autotuner.engine.outcome import MESSAGES, Code
from autotuner.engine.experiment.relay import Identification, RelayConfig, RelayExperiment, Status
from autotuner.engine.plant.simulation import PlantSim

SAMPLES_PER_PERIOD = 100
# Time limit of a simulated experiment: this many expected periods of the
# oscillation, or this many samples when the plant never reaches the phase.
LIMIT_PERIODS = 200
LIMIT_SAMPLES = 20000


@dataclass(frozen=True)
class Trace:
    """Recorded samples: times (s), PV, and the MV held from each sample on."""

    t: np.ndarray
    pv: np.ndarray
    mv: np.ndarray


@dataclass(frozen=True)
class TuneResult:
    """Outcome of one tuning; ``code`` is 0 on success, otherwise the error code shown in ``ite``."""

    code: Code
    message: str
    controller: str
    identification: Identification | None
    design: Design | None
    trace: Trace

    @classmethod
    def failed(cls, code: Code, message: str, controller: str) -> TuneResult:
        """A tuning that ended before anything was identified (no point, no gains, no samples)."""
        return cls(code, message, controller, None, None, Trace(np.zeros(0), np.zeros(0), np.zeros(0)))

    @property
    def ok(self) -> bool:
        """True when the experiment succeeded and gains were computed."""
        return self.code is Code.OK and self.design is not None

    def as_json(self) -> dict[str, Any]:
        """The result object of design.md (``tbsy, te, ite, message, point, gains, ...``)."""
        ident, des = self.identification, self.design
        return {
            "tbsy": False,
            "te": not self.ok,
            "ite": int(self.code),
            "message": self.message,
            "controller": self.controller,
            "point": None
            if ident is None
            else {
                "omega": float(ident.point.omega),
                "gain": float(ident.point.gain),
                "phase_deg": float(ident.point.phase_deg),
            },
            "static_gain": None if ident is None or math.isinf(ident.static_gain) else float(ident.static_gain),
            "gains": None if des is None else des.gains.as_json(),
            "experiment": {
                "duration": float(self.trace.t[-1] - self.trace.t[0]) if len(self.trace.t) else 0.0,
                "periods": None if ident is None else round(ident.periods, 2),
                "samples": len(self.trace.t),
            },
        }


def phase_frequency(process: Process, phase_deg: float) -> float | None:
    """Lowest frequency (rad/s) where the process lags by ``phase_deg`` degrees, or None if it never does."""
    point = exact_point(process, phase_deg)
    return None if point is None else point.omega


def default_sample_time(process: Process, phase_deg: float = 135.0) -> float:
    """A sample time (s) giving about 100 samples per period of the oscillation at ``phase_deg``.

    A process that never reaches that lag gets 1/100 of its slowest time constant or dead time.
    """
    w = phase_frequency(process, phase_deg)
    if w is not None:
        return 2.0 * math.pi / w / SAMPLES_PER_PERIOD
    scales = [1.0 / abs(p) for p in process.poles if abs(p) > 1e-12] + [process.delay]
    return max(max(scales), 1e-3) / SAMPLES_PER_PERIOD


def default_time_limit(process: Process, phase_deg: float, ts: float) -> float:
    """Longest simulated experiment, s: ``LIMIT_PERIODS`` expected periods at ``phase_deg``, else
    ``LIMIT_SAMPLES`` samples of ``ts`` seconds."""
    w = phase_frequency(process, phase_deg)
    return LIMIT_PERIODS * 2.0 * math.pi / w if w is not None else LIMIT_SAMPLES * ts


def run_experiment(
    sim: PlantSim,
    config: RelayConfig,
    on_status: Callable[[Status], None] | None = None,
    status_every: int = 50,
) -> tuple[RelayExperiment, Trace]:
    """Drive the experiment against the simulation until it ends; the MV starts at the plant's ``mv0``."""
    experiment = RelayExperiment(config, mv0=sim.mv0)
    ts, pvs, mvs = [], [], []
    n = 0
    while not experiment.done:
        t, pv = sim.t, sim.measure()
        mv = experiment.step(t, pv)
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


def result_of(experiment: RelayExperiment, trace: Trace, controller: str, ms: float) -> TuneResult:
    """The outcome of an ended experiment, with ``controller`` designed for ``ms`` on success."""
    ident = experiment.result
    des = None
    code, message = experiment.code or Code.OK, experiment.message
    if ident is not None:
        try:
            des = design(ident.point, ident.static_gain, controller, ms)
        except ValueError as exc:
            code, message = Code.NO_DESIGN, f"{MESSAGES[Code.NO_DESIGN]}: {exc}"
    return TuneResult(code, message, controller, ident, des, trace)


def tune(
    sim: PlantSim,
    config: RelayConfig,
    controller: str = "PI",
    ms: float = 1.4,
    on_status: Callable[[Status], None] | None = None,
) -> TuneResult:
    """Run the experiment on ``sim`` and design ``controller`` ("PI" or "PID") for maximum sensitivity ``ms``."""
    experiment, trace = run_experiment(sim, config, on_status)
    return result_of(experiment, trace, controller, ms)
