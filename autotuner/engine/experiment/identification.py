"""What a successful experiment found (:class:`Identification`), made from the accepted point and |F|/K0."""

from __future__ import annotations

import math
from dataclasses import dataclass

from autotuner.engine.described import described as _d
from autotuner.engine.experiment.load_fit import LoadFit
from autotuner.engine.experiment.load_following import LOAD_FRACTION
from autotuner.engine.experiment.loop import Loop
from autotuner.engine.experiment.point import Point
from autotuner.engine.experiment.stopping import slow_memory

# A static gain above this many times |F(jω)| is indistinguishable from an
# integrating process with the resolution of the mean MV shift; the design
# (point_design) models such a process as an integrator.
INTEGRATING_RATIO = 200.0


@dataclass(frozen=True)
class Identification:
    """What a successful experiment found (each field's description says its unit)."""

    point: Point = _d("the identified point F(jω) of the process, ω in rad/s")
    static_gain: float = _d("F(0) estimate, PV units per MV unit; inf when the data cannot tell it from an "
                            "integrating process (the mean MV shift is too small to measure); negative for an "
                            "open-loop unstable process")
    duration: float = _d("seconds from the first sample to the end")
    periods: float = _d("the duration in oscillation periods")
    samples: int = _d("samples taken")
    hysteresis: float = _d("the relay's hysteresis, PV units")
    noise_std: float = _d("standard deviation of the measurement noise estimated from the whole experiment, "
                          "PV units")
    phase_target_deg: float = _d("the process phase lag the phase filter aimed at, degrees: the requested one, "
                                 "or a reachable one when the requested phase was out of reach", 135.0)
    phase_moved: bool = _d("the target was moved from the requested phase (out of reach)", False)
    static_gain_std: float = _d("standard error of static_gain, PV units per MV unit (inf for an integrating "
                                "process or when unknown)", math.inf)
    disturbance: bool = _d("a load step, drift or non-steady start was detected and estimated through or "
                           "discarded", False)
    periods_discarded: int = _d("whole periods left out of the estimates because of a disturbance", 0)
    load_estimate: float = _d("the load at the process input at the end relative to the start, MV units", 0.0)


def identification(loop: Loop, point: Point, x: float, fit: LoadFit | None, periods_discarded: int,
                   hysteresis: float, target_deg: float) -> Identification:
    """The result for the ``loop`` from the accepted ``point`` and ``x`` = |F|/K0, the followed load ``fit`` (None
    while quiet), the ``periods_discarded`` before a load step, the relay's ``hysteresis`` (PV units) and
    the phase ``target_deg`` aimed at (degrees)."""
    # Within the resolution of the mean MV shift, a vanishing |F|/K0 is an
    # integrator, and so is a slightly negative one (within its estimate's
    # tolerance: an integrator seen through noise); a clearly negative one
    # (an open-loop unstable process) is reported as it is.
    integrating = x * INTEGRATING_RATIO <= 1.0 and x > -loop.config.static_tol
    static = math.inf if integrating else point.gain / x
    static_std = math.inf
    if fit is not None and not integrating and fit.x != 0.0:
        static_std = point.gain * fit.x_std / (fit.x * fit.x)
    time = loop.record.time
    duration = time(-1) - time(0)
    return Identification(
        point=point,
        static_gain=static,
        duration=duration,
        periods=duration * point.omega / (2.0 * math.pi),
        samples=len(loop.record),
        hysteresis=hysteresis,
        noise_std=loop.noise,
        phase_target_deg=target_deg,
        phase_moved=target_deg != loop.config.phase_deg,
        static_gain_std=static_std,
        disturbance=fit is not None or _unsettled_start(loop, point, x),
        periods_discarded=periods_discarded if fit is not None else 0,
        load_estimate=0.0 if fit is None else fit.load_at(time(-1), time(0)),
    )


def _unsettled_start(loop: Loop, point: Point, x: float) -> bool:
    """True when the PV was still settling at TUNE by more than a load worth following (LOAD_FRACTION).

    The free response the static ratio took out is ``slope·T`` at the start (T of the model ``x`` fixes).
    """
    slope = loop.settling[0]
    if slope == 0.0 or not 0.0 < x < 1.0:
        return False
    tc = slow_memory(x) * 2.0 * math.pi / point.omega
    return abs(slope) * tc >= LOAD_FRACTION * point.gain * loop.config.amp
