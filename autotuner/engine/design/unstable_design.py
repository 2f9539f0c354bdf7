"""Stabilising PI/PID for an open-loop unstable process with dead time, from one point and a negative static gain.

A relay experiment on an unstable process ``K·e^{−Ds}/(Ts − 1)`` measures a
static gain ``F(0) = −K`` (negative) and a point ``F(jω*) = r·e^{−jφ}``. With
``|F(jω)| = K/sqrt(1 + ω²T²)`` and ``arg F = −(π − atan(ωT)) − ωD`` they fix the
model exactly:

    T = sqrt((K/r)² − 1)/ω*,   D = (φ − π + atan(ω*T))/ω*.

This is the unstable counterpart of the stable FOPDT model of
:mod:`autotuner.engine.design.point_design` (the reasoning of methods.md §4.10:
the unstable first-order model with dead time as the design basis).

What a PI or PID can do on it depends on the normalised dead time ``D/T``
alone. The smallest Ms any PI reaches grows from 1.54 at ``D/T = 0.2`` to
1.74 at 0.25 and 2.6 at 0.4; a PID (``N = 10``) reaches 1.41 at 0.25, 1.77 at
0.4 and 2.07 at 0.5 (Nelder–Mead over ``k, ti, td`` on the model; with
integral action of any use the figures rise). So the design accepts PI up to
``D/T = 0.25`` and PID up to ``0.5``; beyond, it refuses with
``UNSTABLE_DEAD_TIME_TOO_LONG`` (suggesting PID where PID can do it).

The gains are MIGO on the model (largest ``ki`` subject to a stable loop
with ``Ms ≤ target``, the Nyquist test counting the unstable pole). The usual
target 1.4 is out of reach of every unstable process with real dead time, so
the target is raised: to the smallest Ms on a ladder of steps of
:data:`MS_STEP` at which any stabilising PI/PID exists, plus
:data:`MS_HEADROOM` (at the feasibility edge ``ki`` is zero), and never above
:data:`MS_CAP`. A design whose target had to be raised says so (the caller
reports ``ROBUSTNESS_MISSED``); when no target up to the cap admits a
stabilising controller the process is refused with ``NOT_STABILISABLE``.
"""

from __future__ import annotations

import math

import numpy as np

from autotuner.engine.outcome import Code
from autotuner.engine.plant.process import Process
from autotuner.engine.design.robustness import MigoResult, Plant, log_grid, migo

# Largest normalised dead time D/T each controller is designed for (see the module docstring).
PI_DEAD_TIME_RATIO = 0.25
PID_DEAD_TIME_RATIO = 0.5
# Raised Ms targets: ladder step, headroom above the feasibility edge, and the cap (2.15 leaves
# room under the 2.2 a loop on the true plant must keep with a slightly misidentified point).
MS_STEP = 0.05
MS_HEADROOM = 0.2
MS_CAP = 2.15
# td/ti ratios tried for PID: the unstable pole wants derivative action with slow integral action,
# so smaller ratios than the stable design's (at most 1/4 keeps a series form).
TD_RATIOS = (0.005, 0.01, 0.02, 0.05, 0.1, 0.15, 0.25)
# Relative tolerance of the dead-time limits (a model fitted to an exact point lands a few ulps off).
_RATIO_TOL = 1e-3
# A dead time this much (in radians of phase at ω*) below zero is taken as zero: rounding of a
# point whose lag the pole alone explains.
_PHASE_SLACK = 0.05


class Refusal(ValueError):
    """No PI/PID design for this process; ``code`` says why (an outcome code), ``message`` what was found."""

    def __init__(self, code: Code, message: str) -> None:
        super().__init__(message)
        self.code = code


def fit_unstable(omega: float, gain: float, lag: float, static_gain: float) -> Process:
    """``K·e^{−Ds}/(Ts − 1)`` through ``F(jω) = gain·e^{−j·lag}`` (rad/s, rad) with ``F(0) = static_gain < 0``.

    Raises :class:`Refusal` (``NOT_STABILISABLE``) when no such model fits: a
    gain at ω as large as ``|F(0)|``, or more phase lead than the pole gives.

    ``omega``: the point's frequency.
    """
    k = -static_gain
    if not k > gain:
        raise Refusal(Code.NOT_STABILISABLE, (
            f"the point (|F| = {gain:.4g} at {omega:.4g} rad/s) and the negative static gain {static_gain:.4g} fit "
            "no unstable first-order model with dead time (|F(jω)| must be below |F(0)|): more than one unstable "
            "pole or a resonance, which no PI/PID stabilises robustly"))
    t = math.sqrt((k / gain) ** 2 - 1.0) / omega
    phase_left = lag - math.pi + math.atan(omega * t)
    if phase_left < -_PHASE_SLACK:
        raise Refusal(Code.NOT_STABILISABLE, (
            f"the point lags {math.degrees(lag):.1f}°, less than an unstable pole alone "
            f"({math.degrees(math.pi - math.atan(omega * t)):.1f}°): no unstable first-order model with dead time "
            "fits, so no PI/PID design can be trusted"))
    return Process.from_tf((k,), (t, -1.0), max(phase_left, 0.0) / omega, text="unstable FOPDT model")


def unstable_time_constant(model: Process) -> float:
    """``T`` (s) of ``K·e^{−Ds}/(Ts − 1)``: the inverse of the unstable pole.

    ``model``: the process.
    """
    return 1.0 / float(np.max(model.poles.real))


def check_dead_time(model: Process, controller: str) -> float:
    """Normalised dead time ``D/T`` of the model; raises :class:`Refusal` beyond the controller's limit.

    ``model``: the unstable process; ``controller``: ``"PI"`` or ``"PID"``.
    """
    ratio = model.delay / unstable_time_constant(model)
    limit = PI_DEAD_TIME_RATIO if controller == "PI" else PID_DEAD_TIME_RATIO
    if ratio > limit + _RATIO_TOL:
        hint = (f"; PID handles up to {PID_DEAD_TIME_RATIO:g}: tune with --controller PID"
                if controller == "PI" and ratio <= PID_DEAD_TIME_RATIO else
                "; beyond what any PI/PID stabilises robustly (a model-based controller with dead-time "
                "compensation is needed)")
        raise Refusal(Code.UNSTABLE_DEAD_TIME_TOO_LONG, (
            f"dead time {model.delay:.4g} s is {ratio:.2f} × the unstable time constant "
            f"{unstable_time_constant(model):.4g} s; {controller} is designed up to {limit:g}{hint}"))
    return ratio


def _best(plant: Plant, omega: float, ms: float, ratios: tuple[float, ...], nd: float,
          w: np.ndarray) -> MigoResult:
    return max((migo([plant], omega, ms, r, nd, w) for r in ratios), key=lambda m: m.ki)


def _finite(best: MigoResult, model: Process) -> MigoResult:
    if not (math.isfinite(best.k) and math.isfinite(best.ti)):
        raise Refusal(Code.NOT_STABILISABLE, f"no finite gains bound the loop's robustness on the model {model} "
                      "(a dead time too short to be identified?)")
    return best


def design_gains(model: Process, omega: float, controller: str, ms: float, nd: float) -> tuple[MigoResult, float]:
    """MIGO gains on the unstable model and the Ms target they were designed for (``ms`` or raised).

    Raises :class:`Refusal` (``NOT_STABILISABLE``) when no target up to
    :data:`MS_CAP` admits a stabilising controller with integral action.

    ``model``: the unstable process; ``omega``: the point's frequency (rad/s); ``controller``: ``"PI"`` or
    ``"PID"``; ``nd``: the derivative filter's N.
    """
    plant = Plant(model.freqresp, integrators=model.integrator_count, rhp_poles=model.rhp_pole_count)
    # The grid must reach where the dead time turns the loop round (ωD ≈ π) even for a short dead time:
    # a high gain is admissible until there.
    above = max(1e2, 30.0 / (omega * model.delay)) if model.delay > 0.0 else 1e3
    w = log_grid(omega, above=above, n=3000 + int(300 * math.log10(above / 1e2)))
    coarse = log_grid(omega, above=above, n=1000)  # enough to tell whether a target is feasible
    ratios = TD_RATIOS if controller == "PID" else (0.0,)
    first = _best(plant, omega, ms, ratios, nd, w)
    if first.ki > 0.0:
        return _finite(first, model), ms
    # Feasibility grows with the target: bisect the ladder for its first feasible step.
    ladder = [min(ms + MS_STEP * i, MS_CAP) for i in range(1, int(math.ceil((MS_CAP - ms) / MS_STEP)) + 1)]
    if ladder and _best(plant, omega, ladder[-1], ratios, nd, coarse).ki > 0.0:
        lo, hi = -1, len(ladder) - 1  # ladder[hi] feasible; ladder[lo] (or ms) not
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if _best(plant, omega, ladder[mid], ratios, nd, coarse).ki > 0.0:
                hi = mid
            else:
                lo = mid
        target = min(ladder[hi] + MS_HEADROOM, MS_CAP)
        return _finite(_best(plant, omega, target, ratios, nd, w), model), target
    raise Refusal(Code.NOT_STABILISABLE, (
        f"no {controller} with integral action keeps Ms ≤ {MS_CAP:g} on the model {model}"
        + ("; PID may: tune with --controller PID" if controller == "PI" else "")))
