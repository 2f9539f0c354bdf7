"""The stopping rule: when the estimates of the point (and of |F|/K0) are good enough.

Each whole period gives one estimate of ``F(jω)`` over that period and one
of ``|F|/K0``. Four ways to be done:

* **settled** (a quiet plant): the latest ``k ≥ 2`` estimates agree — the
  standard error of their mean is within half of ``gain_tol`` (relative) and
  ``static_tol`` — and the phase is within ``phase_tol_deg`` of the target.
  The shortest such run from the end is taken, so a transient a few periods
  back (a filter correction, a shift of the relay) does not count. The
  result is the latest estimate (the estimates converge towards it as the
  filter's last correction dies out, so their mean would lag behind), or
  the mean of the last two when they alternate around it. Estimates that
  scatter *along* the Nyquist curve (the cycle's ω wandering with a link's
  timing) settle too when ``k ≥ CURVE_MIN`` of them lie on a line in ω
  within that standard error and their mean lags as asked: the result is
  then their mean, F at their mean ω.
* **on a line** (a quiet plant whose phase still converges from one side):
  the point at the target on the line in ln ω through the latest two
  estimates, when the one before lies on it within ``LINE_TOL`` of
  ``gain_tol``. Each estimate has shed the transient's share
  (transient.py), so they are points of the process's curve at their own
  ω; the line reaches the target a filter correction or two sooner than
  the cycle does.
* **on the model's curve** (the same, from two estimates, when neither
  rule above passes): the latest within ``MODEL_GATE_DEG`` of the target,
  the one before on the curve of the model through the latest (the one
  the estimates shed their transient through: first order, methods.md §6,
  or two lags, transient.py) within ``MODEL_TOL`` of ``gain_tol``; the
  point at the target on the line through the two. A first-order process
  with dead time has its estimates exact from the second (the model is the
  process): it need not wait for a third.
* **averaged** (measurement noise that makes single estimates scatter more
  than ``gain_tol``; the settled rule is then not used): the mean of at least ``NOISY_MIN`` estimates whose
  standard error is within ``noise_tol`` (relative |F|) and ``static_tol``
  (|F|/K0). Estimates over consecutive periods share no data: ``k`` of them
  are ``k`` independent ones.

When neither holds by ``max_periods`` (or the time limit) and the noise is
what keeps the averaged rule from passing, :func:`amp_factor` says how much
larger ``amp`` would have to be: every standard error scales as σ/amp.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from autotuner.engine.experiment.point import Point
from autotuner.engine.experiment.transient import model, model_response

# The settled rule judges |F|/K0 over at least this many estimates.
STATIC_MIN = 3

# The settled rule's three-estimate check of |F|/K0 applies to a slow mode remembering more than one period
# and at most this many; beyond (|F|/K0 < 0.053), K0 is resolved to static_tol of |F|/K0 only, as for
# an integrator: the design's model is nearly one then, whatever K0 is.
SLOW_MEMORY_MAX = 3.0

# Below this |F|/K0 the settled rule's static bound stops being relative (static_bound).
X_FLOOR = 0.25

# The averaged rule needs at least this many estimates (its standard error
# is itself estimated from them).
NOISY_MIN = 3

# The settled rule's along-the-curve check needs at least this many estimates (a line through them in ω
# leaves k − 2 degrees of freedom for their scatter). With 4, a quiet run's converging transient passed for
# a settled scatter (its estimates move along the curve as the filter's corrections die out): P5-059 of the
# batch stopped at 6.8 periods with a point error of 0.9 % instead of 7.7 and 0.08 %.
CURVE_MIN = 6

# The line rule (a quiet run whose phase is still moving): the point at the target read off the line in ln ω
# through the latest two estimates, at most this many of their spacings beyond the latest (a phase converging
# by 0.5 per period puts the target one spacing beyond; a falling switch's window, half a period on, about
# two)...
LINE_REACH = 3.0
# ...when the one before them lies on that line within this share of gain_tol (each estimate's transient is
# taken out, transient.py: what is left decays from one to the next, and shows as the oldest's distance from
# the line through the newer two)...
LINE_TOL = 1.0 / 3.0
# ...and their spacing is at least this much of ln ω (closer, the line's direction is their noise).
LINE_SPACING = 0.002

# The model rule (two estimates): the latest lags the target by at most this much (degrees)...
MODEL_GATE_DEG = 2.0
# ...and the one before lies on the model's curve through the latest within this share of gain_tol. The
# first-order model's curve is the process's only on a first-order process with dead time; elsewhere its
# slope differs, and a third of gain_tol let estimates with 0.3 % of transient left pass (1/(s+1)^6 of the
# batch: point error 0.14 → 0.35 %); a fifth passed only where the estimates had shed it (batch worst 0.22 %).
MODEL_TOL = 0.2

# A quiet run whose noise scatters each estimate's F by more than this share of gain_tol (the expected standard
# error of each part, convergence.scatter): its settled point is the mean of the latest two, not the latest (or
# the mean of two that straddle it). One estimate's noise is then as large as what is left of its transient: at
# 1 % noise (the batch) the points that stopped at a falling switch were 0.185 % off at the median as the latest,
# 0.145 % as the mean.
MEAN_SCATTER = 0.03


@dataclass(frozen=True)
class Tolerances:
    """phase_tol_deg: degrees; gain_tol, noise_tol: relative |F|; static_tol: |F|/K0."""

    phase_tol_deg: float
    gain_tol: float
    static_tol: float
    noise_tol: float


@dataclass(frozen=True)
class Verdict:
    """An accepted mean ``point`` and ``x`` = |F|/K0, from the latest ``count`` estimates."""

    point: Point
    x: float
    count: int


def static_bound(tol: Tolerances, x: float) -> float:
    """The settled rule's bound on the spread of |F|/K0 near ``x`` with the tolerances ``tol``: ``static_tol``
    relative to it (K0 to
    about ``static_tol``) from ``X_FLOOR`` up; below, where the design hardly depends on K0 (its model tends to
    an integrator's), ``static_tol`` of ``X_FLOOR``."""
    return tol.static_tol * max(abs(x), X_FLOOR)


def slow_memory(x: float) -> float:
    """The time constant of the first-order model with ``x`` = |F|/K0 at the point, in periods
    (methods.md §6: T = sqrt(1/x² − 1)/ω); inf for an integrator, 0 for a dead time."""
    size = min(abs(x), 1.0)
    return math.inf if size == 0.0 else math.sqrt(1.0 / (size * size) - 1.0) / (2.0 * math.pi)


def _stats(recent: list[tuple[Point, float]]) -> tuple[Point, float, float, float]:
    """(mean point, mean |F|/K0, relative spread of F, spread of |F|/K0), spreads as standard deviations."""
    k = len(recent)
    mean = Point(sum(p.omega for p, _ in recent) / k, sum(p.value for p, _ in recent) / k)
    x = sum(i for _, i in recent) / k
    spread = math.sqrt(sum(abs(p.value - mean.value) ** 2 for p, _ in recent) / k) / mean.gain
    x_spread = math.sqrt(sum((i - x) ** 2 for _, i in recent) / k)
    return mean, x, spread, x_spread


def _curve_spread(recent: list[tuple[Point, float]]) -> float:
    """Relative spread of F about a straight line in ω through the estimates (inf when ω does not vary).

    When the cycle's frequency wanders from period to period (a link's or a
    loaded machine's timing, a phase filter chasing scattered lags), each
    estimate is the process's F at its own ω: they scatter *along* the
    Nyquist curve, far more than about it, and their mean is F at their mean
    ω (to the curve's second order).
    """
    k = len(recent)
    w = [p.omega for p, _ in recent]
    mw = sum(w) / k
    mf = sum(p.value for p, _ in recent) / k
    sww = sum((omega - mw) ** 2 for omega in w)
    if sww == 0.0:
        return math.inf
    slope = sum((omega - mw) * (p.value - mf) for omega, (p, _) in zip(w, recent)) / sww
    residual = sum(abs(p.value - mf - slope * (omega - mw)) ** 2 for omega, (p, _) in zip(w, recent))
    return math.sqrt(residual / (k - 2)) / abs(mf)


def _settled(estimates: list[tuple[Point, float]]) -> tuple[Point, float]:
    """The settled value of converging estimates: the latest, or the mean of the last two if they straddle it.

    A filter correction dies out monotonically or alternating; in the second
    case the latest two lie on both sides of the limit.
    """
    (p1, i1), (p2, i2) = estimates[-2:]
    if len(estimates) < 3:
        return p2, i2
    p0, i0 = estimates[-3]
    point = p2
    if ((p2.value - p1.value) * (p1.value - p0.value).conjugate()).real < 0.0:
        point = Point(0.5 * (p1.omega + p2.omega), 0.5 * (p1.value + p2.value))
    x = 0.5 * (i1 + i2) if (i2 - i1) * (i1 - i0) < 0.0 else i2
    return point, x


def _on_line(recent: list[tuple[Point, float]], target_deg: float, tol: Tolerances) -> Verdict | None:
    """The point at ``target_deg`` (degrees of lag) on the line in ln ω through the latest two of the three
    ``recent`` estimates, when their phases converge to it from one side, the oldest lies on the line
    (LINE_TOL of ``tol.gain_tol``) and the target is within LINE_REACH of their spacing; else None. Its
    |F|/K0 is the latest's at the point's |F| (K0 as the latest estimate has it)."""
    (p0, _), (p1, _), (p2, _) = recent
    spacing = math.log(p2.omega) - math.log(p1.omega)
    if abs(spacing) < LINE_SPACING:
        return None
    if abs(p0.value - _line(p1, p2, math.log(p0.omega))) > LINE_TOL * tol.gain_tol * p2.gain:
        return None
    lags = _lags(recent, target_deg)
    if not (abs(lags[0]) > abs(lags[1]) > abs(lags[2]) and lags[0] * lags[2] > 0.0):
        # Only a phase that converges from one side, as a filter's corrections do: a cycle whose frequency
        # wanders (a link's timing) puts two estimates on a line through a third by chance.
        return None
    return _at_target(recent, recent, target_deg, tol)


def _on_model(estimates: list[tuple[Point, float]], target_deg: float, tol: Tolerances,
              ratio: float = 0.0) -> Verdict | None:
    """The point at ``target_deg`` (degrees of lag) on the line in ln ω through the latest two ``estimates``,
    when the latest lags within MODEL_GATE_DEG of it, their phases converge to it from one side, and the one
    before lies on the curve of the model through the latest (MODEL_TOL of ``tol.gain_tol``; two lags ``ratio``
    apart, or first order for 0: transient.model, the one the estimates shed their transient through); else
    None. An unstable process's (|F|/K0 below −``tol.static_tol``) has no such model."""
    (p1, _), (p2, x2) = recent = estimates[-2:]
    if x2 < -tol.static_tol or abs(math.log(p2.omega / p1.omega)) < LINE_SPACING:
        return None
    lags = _lags(recent, target_deg)
    if abs(math.degrees(lags[1])) > MODEL_GATE_DEG or not (abs(lags[0]) > abs(lags[1]) and lags[0] * lags[1] > 0.0):
        # (As the line rule: only a phase that converges from one side; a wandering ω puts two estimates on
        # both sides of the target, and a phase bias common to both would pass for the curve.)
        return None
    k0, tc, tc2, delay, rate = model(x2, p2.value, p2.omega, ratio)
    if abs(p1.value - model_response(k0, tc, delay, rate, p1.omega, tc2)) > MODEL_TOL * tol.gain_tol * p2.gain:
        return None
    return _at_target(estimates, recent, target_deg, tol)


def _lags(recent: list[tuple[Point, float]], target_deg: float) -> list[float]:
    """How far each of the ``recent`` estimates lags beyond ``target_deg`` (degrees), radians."""
    return [-math.radians(p.phase_deg) - math.radians(target_deg) for p, _ in recent]


def _line(p1: Point, p2: Point, at: float) -> complex:
    """The point at ``at`` (ln ω, ω in rad/s) on the line in ln ω through ``p1`` and ``p2``."""
    l1, l2 = math.log(p1.omega), math.log(p2.omega)
    return p2.value + (p2.value - p1.value) * (at - l2) / (l2 - l1)


def _at_target(estimates: list[tuple[Point, float]], recent: list[tuple[Point, float]], target_deg: float,
               tol: Tolerances) -> Verdict | None:
    """The point at ``target_deg`` (degrees of lag) on the line in ln ω through the latest two of ``recent``
    (the latest of ``estimates``), when it lies within LINE_REACH of their spacing beyond the latest and the
    |F|/K0 of ``recent``, each at the point's |F|, pass the settled rule's static test (``tol``); else None."""
    p1, p2 = recent[-2][0], recent[-1][0]
    l2 = math.log(p2.omega)
    spacing = l2 - math.log(p1.omega)
    lag1, lag2 = -math.radians(p1.phase_deg), -math.radians(p2.phase_deg)
    at = l2 + (math.radians(target_deg) - lag2) * spacing / (lag2 - lag1)
    if abs(at - l2) > LINE_REACH * abs(spacing):
        return None
    point = Point(math.exp(at), _line(p1, p2, at))
    if abs(-point.phase_deg - target_deg) > tol.phase_tol_deg:
        return None
    # |F|/K0 moves along the curve with |F|: each estimate's K0 read at the point's |F|, judged as the
    # settled rule judges the latest two (three on a slow mode).
    xs = [(point, x * point.gain / p.gain) for p, x in estimates]
    if not _static_settled(xs, xs[-2:], tol):
        return None
    return Verdict(point, xs[-1][1], len(recent))


def _static_settled(estimates: list[tuple[Point, float]], recent: list[tuple[Point, float]],
                    tol: Tolerances) -> bool:
    """True when the |F|/K0 of the ``recent`` (the latest of ``estimates``, (point, x) pairs) agree within
    half of ``tol.static_tol`` (standard error), and on a slow mode or an unstable process the latest
    STATIC_MIN each within half the static bound."""
    k = len(recent)
    _, x, _, x_spread = _stats(recent)
    static_ok = x_spread / math.sqrt(k) <= 0.5 * tol.static_tol
    if x < -tol.static_tol or 1.0 < slow_memory(x) <= SLOW_MEMORY_MAX:
        # A slow mode remembers the relay's means of earlier periods: its |F|/K0 estimates converge
        # more slowly than the point's, and two can agree by chance (100·e^{−20s}/(300s+1):
        # 0.0805, 0.0803, then 0.0768; true 0.0771): three must agree, each within the bound.
        # So must an unstable process's, whose design hangs on K0 (its pole is |F|/K0 of the
        # point's gain at high ω): after its target moved, exp(-0.5*s)/(2*s-1) read K0 −0.80,
        # −0.91, −0.965 (true −1), and two of them agreed within static_tol.
        last = estimates[-max(k, STATIC_MIN):]
        static_ok = static_ok and len(last) >= STATIC_MIN and _stats(last)[3] <= 0.5 * static_bound(tol, x)
    return static_ok


def judge(estimates: list[tuple[Point, float]], target_deg: float, tol: Tolerances, longest: int,
          noisy: bool, x_std: float | None = None, ratio: float = 0.0, scatter: float = 0.0) -> Verdict | None:
    """The accepted mean of the latest ``estimates`` ((point, x) pairs), or None to go on.

    ``target_deg``: the lag aimed at, degrees; ``tol``: the tolerances.
    ``longest`` bounds how many of the latest are averaged; ``noisy`` enables
    the averaged rule; ``x_std`` (from a load fit) replaces the spread
    of |F|/K0 by the fit's own standard error; ``ratio``: the model the
    estimates shed their transient through (transient.model), whose curve
    the model rule reads; ``scatter``: the expected relative standard error of
    each part of one estimate's F from the measured noise (convergence.scatter;
    beyond MEAN_SCATTER of gain_tol, the settled point is the mean of the latest two).
    """
    quiet = not noisy and x_std is None
    if quiet and len(estimates) >= 3:
        on_line = _on_line(estimates[-3:], target_deg, tol)
        if on_line is not None:
            return on_line
    for k in range(2, min(len(estimates), longest) + 1):
        recent = estimates[-k:]
        mean, x, spread, x_spread = _stats(recent)
        phase_ok = min(abs(-p.phase_deg - target_deg) for p in (mean, recent[-1][0])) <= tol.phase_tol_deg
        if not phase_ok:
            continue
        if x_std is not None:
            # One static_tol of the fit's standard error is accepted (a quiet
            # run gets about half of that from the scatter of its means).
            static_ok = x_std <= tol.static_tol
        else:
            static_ok = x_spread / math.sqrt(k) <= 0.5 * tol.static_tol
        if not noisy:
            if x_std is None:
                static_ok = _static_settled(estimates, recent, tol)
            if spread / math.sqrt(k) <= 0.5 * tol.gain_tol and static_ok:
                scattered = quiet and scatter > MEAN_SCATTER * tol.gain_tol
                point, x = _stats(recent[-2:])[:2] if scattered else _settled(estimates)
                return Verdict(point, x, k)
            # Scattered along the curve: their mean is the point, at the mean ω, if it lags as asked.
            if (k >= CURVE_MIN and static_ok and abs(-mean.phase_deg - target_deg) <= tol.phase_tol_deg
                    and _curve_spread(recent) / math.sqrt(k) <= 0.5 * tol.gain_tol):
                return Verdict(mean, x, k)
        elif k >= NOISY_MIN:
            static_ok = static_ok or (x_std is None and x_spread / math.sqrt(k) <= tol.static_tol)
            if spread / math.sqrt(k) <= tol.noise_tol and static_ok:
                return Verdict(mean, x, k)
    if quiet and len(estimates) >= 2:
        return _on_model(estimates, target_deg, tol, ratio)
    return None


def amp_factor(estimates: list[tuple[Point, float]], tol: Tolerances) -> float:
    """How many times larger amp would let the averaged rule pass on all of ``estimates`` ((point, x) pairs)
    with the tolerances ``tol`` (≥ 1)."""
    k = len(estimates)
    if k < NOISY_MIN:
        return math.inf
    _, _, spread, x_spread = _stats(estimates)
    need = max(spread / math.sqrt(k) / tol.noise_tol, x_spread / math.sqrt(k) / tol.static_tol)
    return max(need, 1.0)
