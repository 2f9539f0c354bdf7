"""Closed-loop figures of a controller on a plant: Ms, margins, and simulated IAE/ITAE.

The time responses are simulated with the exact ZOH plant simulator
(:class:`autotuner.engine.plant.simulation.PlantSim`) in feedback with the engine's PID unit
(:class:`autotuner.engine.control.pid.PidUnit`, the same discrete law the tuner runs:
Tustin integral, filtered backward-difference derivative). The sample time is
``T135/STEP_SAMPLES_PER_PERIOD`` (``T135 = 2π/ω135``, the period of the 135° point),
and the integrals are rectangle sums over the samples:
``IAE = Σ|e|·ts``, ``ITAE = Σ t·|e|·ts`` with ``e = sp − pv``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autotuner.engine.control.gains import Gains
from autotuner.engine.design.process_data import exact_point
from autotuner.engine.control.pid import PidUnit
from autotuner.engine.plant.process import Process
from autotuner.engine.design.robustness import LoopCheck, check_loop, closed_loop_stable, log_grid, max_sensitivity, pid_frequency_response
from autotuner.engine.plant.simulation import PlantSim

# Samples per 135° period of the simulated step responses (not the experiment's sampling).
STEP_SAMPLES_PER_PERIOD = 50
HORIZON_PERIODS = 30.0
# An error this large means the loop has diverged; the simulation stops.
DIVERGED = 1e6


def reference_period(process: Process) -> float:
    """Period ``2π/ω135`` (s) of the 135° point; for a plant that never lags 135°, 2π·slowest time scale.

    ``process``: the process.
    """
    point = exact_point(process, 135.0)
    if point is not None:
        return 2.0 * math.pi / point.omega
    scales = [1.0 / abs(p.real) for p in process.poles if abs(p.real) > 1e-12] + [process.delay, 1e-6]
    return 2.0 * math.pi * max(scales)


def check_gains(process: Process, gains: Gains, w: np.ndarray) -> LoopCheck:
    """Ms and stability of ``gains`` (standard form) on ``process`` over the grid ``w`` (rad/s)."""
    return check_loop(process.freqresp, lambda x: controller_response(gains, x), w,
                      process.integrator_count + (1 if gains.has_integral else 0), process.rhp_pole_count)


def controller_response(gains: Gains, w: np.ndarray) -> np.ndarray:
    """C(jω) of ``gains`` (standard form) at the frequencies ``w`` (rad/s)."""
    return pid_frequency_response(w, gains.k, gains.ti, gains.td, gains.nd)


@dataclass(frozen=True)
class Margins:
    """Robustness of a loop: ``stable``, ``ms`` (inf if unstable), ``gain_margin`` (factor), ``phase_margin_deg``
    (degrees)."""

    stable: bool
    ms: float
    gain_margin: float
    phase_margin_deg: float


def _crossings(x: np.ndarray) -> np.ndarray:
    """Indices i where x changes sign between i and i+1."""
    return np.nonzero(np.signbit(x[:-1]) != np.signbit(x[1:]))[0]


def margins(process: Process, gains: Gains, w_ref: float) -> Margins:
    """Ms, gain margin and phase margin of ``C·F`` on a log grid around ``w_ref`` (rad/s).

    Gain margin: the smallest ``1/|L|`` where the Nyquist curve crosses the
    negative real axis inside the unit circle (inf if it never does).
    Phase margin: the smallest ``180° + arg L`` where ``|L| = 1`` (inf if never).

    ``process``: the process; ``gains``: the controller.
    """
    w = log_grid(w_ref, 1e-5, 1e3, 6000)
    loop = controller_response(gains, w) * process.freqresp(w)
    stable = closed_loop_stable(loop, w, process.integrator_count + (1 if gains.has_integral else 0),
                                process.rhp_pole_count)
    ms = max_sensitivity(loop) if stable else math.inf
    gm = [1.0 / abs(loop[i]) for i in _crossings(loop.imag) if loop[i].real < 0 and abs(loop[i]) < 1.0]
    pm = [math.degrees(np.angle(-loop[i])) for i in _crossings(np.abs(loop) - 1.0)]
    return Margins(stable, ms, min(gm, default=math.inf), min(pm, default=math.inf))


def closed_loop_step(process: Process, gains: Gains, step: str, ts: float,
                     samples: int) -> tuple[np.ndarray, np.ndarray]:
    """(PV, MV) at the samples (``ts`` seconds apart) after a unit step at t = 0, from rest at 0.

    ``step`` is "load" (unit load step at the process input, set point 0)
    or "setpoint" (unit set-point step). The controller kind follows the gains
    (P, PI, PD, PID) and applies ``b`` and ``c``. PV at sample k is taken just
    before the MV of sample k is applied. The arrays are cut short after the
    first error beyond :data:`DIVERGED` if the loop diverges.

    ``process``: the process; ``gains``: the controller; ``step``: ``"setpoint"`` or ``"load"``; ``samples``: how
    many.
    """
    sim = PlantSim(process, ts, loads=[(0.0, 1.0)] if step == "load" else ())
    pid = PidUnit(gains, kind=gains.controller_type)
    sp = 1.0 if step == "setpoint" else 0.0
    pv, mv = np.empty(samples), np.empty(samples)
    for k in range(samples):
        pv[k] = sim.true_pv()
        mv[k] = pid.step(k * ts, sp, pv[k])
        if abs(sp - pv[k]) > DIVERGED:
            return pv[: k + 1], mv[: k + 1]
        sim.advance(mv[k])
    return pv, mv


def integrated_error(process: Process, gains: Gains, step: str, period: float,
                     samples_per_period: int = STEP_SAMPLES_PER_PERIOD,
                     horizon_periods: float = HORIZON_PERIODS) -> tuple[float, float]:
    """(IAE, ITAE) of the unit step response over ``horizon_periods·period`` seconds.

    inf when the loop diverges or, for a controller without integral action,
    when a load step leaves an offset.

    ``process``: the process; ``gains``: the controller; ``step``: ``"setpoint"`` or ``"load"``; ``period``: the
    time scale (s); ``samples_per_period``: the simulation's resolution.
    """
    ts = period / samples_per_period
    samples = int(round(horizon_periods * samples_per_period))
    pv, _ = closed_loop_step(process, gains, step, ts, samples)
    errors = (1.0 if step == "setpoint" else 0.0) - pv
    if len(errors) < samples:
        return math.inf, math.inf
    t = ts * np.arange(samples)
    return float(np.sum(np.abs(errors)) * ts), float(np.sum(t * np.abs(errors)) * ts)
