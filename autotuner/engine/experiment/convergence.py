"""Convergence: which estimates the stopping rule (stopping.py) judges, and when.

At each rising switch, from ``MIN_PERIODS`` whole periods on, the estimates
since the latest disturbance, change of the levels or stall are judged; the
longer the experiment runs, the more of the latest may be averaged. On a
quiet, noise-free run the period between the latest falling crossings, which
overlaps the latest rising one by half, stops it half a period sooner when the
two agree within ``HALF_TOL`` of the tolerances — from the falling switch after the first estimate on, where
both transient models' sets must agree. When neither has happened by ``max_periods`` or the time limit,
:func:`unsettled` says why. Which rules judge depends on the noise: :func:`noisy`, a gate on one period's
expected scatter with hysteresis (QUIET_AGAIN), judged from every period's σ kept with its estimate.
"""

from __future__ import annotations

import math
from dataclasses import replace

from autotuner.engine.experiment import endings
from autotuner.engine.experiment.config import RelayConfig
from autotuner.engine.experiment.endings import Ended
from autotuner.engine.experiment.estimates import (GAP, STALL, Estimates, alt_point, drift, longest_gap, pairs,
                                                   period_point)
from autotuner.engine.experiment.load_fit import LoadFit
from autotuner.engine.experiment.loop import Loop
from autotuner.engine.experiment.stopping import MODEL_GATE_DEG, Tolerances, Verdict, judge
from autotuner.engine.experiment.switching import Switching
from autotuner.engine.experiment.transient import ALT_RATIO

# Minimum number of whole periods before convergence is judged: one for the
# start-up transient and the first filter correction, one per estimate.
MIN_PERIODS = 3
# A run is noisy when one period's estimate of F is expected to scatter by more than this share of gain_tol
# (scatter): then the quiet rules' agreement of two or three estimates could be the noise's, and the averaged
# rule judges. Below it the noise moves an estimate less than the quiet rules' tests can tell from a transient.
SCATTER_MAX = 0.25
# The gate's hysteresis: once noisy, a run turns quiet again only at a period whose σ puts the latest estimate's
# scatter below this share of the gate, and a followed load's share is taken out of the estimates
# (load_correction.py, built for noise-free runs) only on a run whose every period's σ does. One period's σ
# (cycle_noise over about 100 samples, or the noise stage's) scatters by 9–12 % about its run's median on the field
# bench's noisy runs; 2 of their 2822 periods fell a third below it, 5 % a quarter: a run whose noise lies on the
# gate (2 % noise: 1.13 of it) comes back by chance in fewer than 1 in 1000 periods. (Without it the gate flipped
# from period to period at 2 % noise, 187 times in 78 of 133 runs, and each quiet spell let the load correction
# act on a noisy record: docs/experiment.md, "A gate with hysteresis".)
QUIET_AGAIN = 2.0 / 3.0
# The share of gain_tol and static_tol within which a period between falling crossings must agree with the
# latest rising one: a transient decaying by ρ per period leaves the latest estimate off by ρ/(1 − ρ) × the
# difference of disjoint windows, but by √ρ/(1 − √ρ) × that of windows half a period apart — 2.4–2.9 times
# more for ρ = 0.5–0.3.
HALF_TOL = 1.0 / 3.0
# The falling switch after the first estimate is judged only when that estimate lags the target by at most this
# much (degrees): the estimate of the period ending there is most of an analysis's cost, and on the batch every
# run that stopped there had its first estimate within 0.6° (at 4° or at this gate, the same runs stopped).
FIRST_GATE_DEG = MODEL_GATE_DEG


def tolerances(config: RelayConfig) -> Tolerances:
    """The stopping rule's tolerances from the experiment's ``config``."""
    return Tolerances(config.phase_tol_deg, config.gain_tol, config.static_tol, config.noise_tol)


def scatter(noise: float, swing: float, samples: float) -> float:
    """The expected relative standard error of each of the real and imaginary parts of one period's estimate of
    F, from white noise of σ ``noise`` (PV units) over ``samples`` samples of a cycle whose fundamental is
    ``swing`` (PV units; |F|·amp for the relay's MV, whose fundamental is about amp at bias 0.2).

    A Fourier coefficient over N samples of white noise has each part's standard error σ·sqrt(2/N).
    """
    if noise <= 0.0:
        return 0.0
    return noise * math.sqrt(2.0 / max(samples, 1.0)) / swing if swing > 0.0 else math.inf


def sigma(loop: Loop, estimates: Estimates, pending: float | None = None) -> float:
    """The measurement noise's σ the stopping rule judges by (PV units): the larger of the ``loop``'s noise
    stage's and the latest period's — ``pending`` (PV units), that of a period whose estimate is being made,
    else the latest of the ``estimates``' (loop.cycle_noise; none before an estimate)."""
    if pending is None:
        pending = estimates.latest.cycle_noise if estimates.items else 0.0
    return max(loop.noise, pending)


def noisy(loop: Loop, estimates: Estimates, pending: float | None = None) -> bool:
    """True when the measured noise of ``loop`` is expected to scatter one period's estimate of the ``estimates``
    by more than SCATTER_MAX of gain_tol, with hysteresis (``pending``: as for :func:`sigma`).

    From the first period whose σ (:func:`noise_ratios`) puts it above the gate until one whose σ puts it below
    QUIET_AGAIN of the gate; a pure function of the periods' σ, re-judged at the latest estimate's swing and length.
    """
    state = False
    for ratio in noise_ratios(loop, estimates, pending):
        state = ratio > (QUIET_AGAIN if state else 1.0)
    return state


def far_below(loop: Loop, estimates: Estimates) -> bool:
    """True when every period's σ of the ``loop`` puts the latest of the ``estimates`` below QUIET_AGAIN of the gate
    (:func:`noise_ratios`; true before an estimate): noise that no period's sampling brings near the gate."""
    return all(ratio < QUIET_AGAIN for ratio in noise_ratios(loop, estimates))


def noise_ratios(loop: Loop, estimates: Estimates, pending: float | None = None) -> list[float]:
    """Each whole period's σ of the ``loop`` (oldest first; ``pending``, PV units: a period's whose estimate is
    being made, last) as the scatter it gives the latest of the ``estimates`` (:func:`estimate_scatter`), over the
    gate SCATTER_MAX × gain_tol; none before an estimate."""
    if not estimates.items:
        return []
    latest = estimates.latest
    # (scatter is proportional to σ: one division per call, one product per period — the analysis asks several
    # times per period.)
    unit = period_scatter(loop, 1.0, latest.point.gain * loop.config.amp, latest.end - latest.start)
    unit /= SCATTER_MAX * loop.config.gain_tol
    noises = [max(loop.noise, e.cycle_noise) for e in estimates.items]
    if pending is not None:
        noises.append(max(loop.noise, pending))
    return [unit * noise if noise > 0.0 else 0.0 for noise in noises]


def estimate_scatter(loop: Loop, estimates: Estimates, pending: float | None = None) -> float:
    """:func:`scatter` of the latest of the ``estimates`` of the ``loop`` (0 before one; ``pending``: as for
    :func:`sigma`)."""
    if not estimates.items:
        return 0.0
    latest = estimates.latest
    return period_scatter(loop, sigma(loop, estimates, pending), latest.point.gain * loop.config.amp,
                          latest.end - latest.start)


def too_scattered(loop: Loop, estimates: Estimates, swing: float, period: float) -> bool:
    """True when the noise of ``loop`` (:func:`sigma` of its ``estimates``) scatters one ``period``'s (s) estimate
    of a cycle whose fundamental is ``swing`` (PV units) by more than SCATTER_MAX of gain_tol (:func:`scatter`)."""
    return swing_scatter(loop, estimates, swing, period) > SCATTER_MAX * loop.config.gain_tol


def swing_scatter(loop: Loop, estimates: Estimates, swing: float, period: float) -> float:
    """:func:`period_scatter` at the σ the stopping rule judges by (:func:`sigma` of the ``estimates`` of ``loop``):
    one ``period``'s (s) estimate of a cycle whose fundamental is ``swing`` (PV units)."""
    return period_scatter(loop, sigma(loop, estimates), swing, period)


def period_scatter(loop: Loop, noise: float, swing: float, period: float) -> float:
    """:func:`scatter` from noise of σ ``noise`` (PV units) of one ``period``'s (s) estimate of the ``loop``'s cycle
    whose fundamental is ``swing`` (PV units)."""
    samples = period / loop.dt if loop.dt > 0.0 else 1.0
    return scatter(noise, swing, samples)


def unsettled(when: str, loop: Loop, estimates: Estimates, since: float, fit: LoadFit | None,
              target_deg: float) -> Ended:
    """The ending of an experiment whose ``estimates`` of the ``loop`` did not settle ``when``: through a followed
    load ``fit``, for noise a larger amp would average out, or else (``since``, ``target_deg``: as for
    :func:`at_rising`)."""
    if fit is not None:
        return endings.unsettled_through_load(when, fit.step, fit.ramp)
    usable = estimates.usable(since)[2:]
    if noisy(loop, estimates) and usable:
        too_noisy = endings.noise_too_high(when, pairs(usable), tolerances(loop.config), loop.noise,
                                           loop.config.amp)
        if too_noisy is not None:
            return too_noisy
    latest = estimates.latest.point if estimates.items else None
    return endings.not_converged(when, estimates.stalls, STALL, latest, loop.config.phase_deg, target_deg)


def at_rising(loop: Loop, estimates: Estimates, periods: int, since: float, target_deg: float,
              x_std: float | None, corrected: bool = False) -> Verdict | None:
    """The verdict on the ``estimates`` of the ``loop`` after ``periods`` whole periods, or None to go on.

    ``since``: estimates whose period starts earlier are left out (s); ``target_deg``: the lag aimed at,
    degrees; ``x_std``: a followed load fit's standard error of |F|/K0 (None while quiet); ``corrected``: the
    followed load's share is taken out of the estimates (load_correction.py).
    """
    if periods < MIN_PERIODS or len(estimates) < 2:
        return None
    usable = estimates.usable(since)
    if len(usable) < 2:
        return None
    # Estimates scatter with noise and sampling jitter; the longer the
    # experiment runs, the more of the latest may be averaged (stopping.py).
    scattered = noisy(loop, estimates)
    spread = estimate_scatter(loop, estimates)
    # With noise, all estimates since the last disturbance may be averaged but the first
    # (the period right after the filter's first correction).
    longest = len(usable) - 1 if scattered else 2 + (periods - MIN_PERIODS) // 2
    tol = tolerances(loop.config)
    if x_std is not None and corrected:
        # A followed load's estimates with its share taken out (load_correction.py): judged as quiet ones, each
        # |F|/K0 the fit's K0 at its |F| (the caller waits for the fit's K0 to be as sure as a quiet run's).
        x_std = None
    verdict = judge(pairs(usable), target_deg, tol, longest, scattered, x_std, scatter=spread)
    if verdict is None and not scattered and x_std is None:
        # Quiet: the estimates through the second model may have shed their transient where the first-order
        # model's have not (a process of higher order); each set is judged with its own model.
        verdict = judge(pairs(usable, alt=True), target_deg, tol, longest, False, None, ALT_RATIO, spread)
    return verdict


def at_falling(loop: Loop, switching: Switching, estimates: Estimates, since: float,
               target_deg: float) -> Verdict | None:
    """At a falling switch of a quiet, noise-free run: the verdict when the period ending here agrees with the
    latest ``estimates``, else None. ``loop``, ``switching``: the loop under test and the relay's crossings;
    ``since``, ``target_deg``: as for :func:`at_rising`.

    The period between two falling crossings overlaps the latest rising
    one by half; when the two agree the cycle has settled, half a period
    before the next rising crossing would say so. (With noise the
    overlapping windows are not independent estimates: only the rising
    ones are averaged.)
    """
    periods, falls, crossings = switching.periods, switching.falls, switching.crossings
    # From the falling switch after the first estimate on: that estimate and the period ending here may pass
    # the model rule (exp(-s)/(s+1) and its like: exact from the first estimate, 3.77 → 3.21 periods).
    if periods < MIN_PERIODS - 1 or len(falls) < 3 or noisy(loop, estimates):
        return None
    usable = estimates.usable(since)
    if falls[-2] < since or not usable:
        return None
    if periods < MIN_PERIODS and abs(-usable[-1].point.phase_deg - target_deg) > FIRST_GATE_DEG:
        # (One estimate, too far from the target for a stop half a period on.)
        return None
    raw = loop.record.since(min(falls[-3], crossings[-2]))
    # A sampling gap (a stalled link) in the overlap biases both windows alike, so they agree: only the
    # disjoint rising windows may judge such a record.
    if longest_gap(raw.t, crossings[-2], raw.t[-1]) > GAP * loop.dt:
        return None
    detrended = raw.y - drift(raw.t, raw.y, falls[-3:])
    longest = 2 + max(periods - MIN_PERIODS, 0) // 2
    c = loop.config
    tol = replace(tolerances(c), gain_tol=c.gain_tol * HALF_TOL, static_tol=c.static_tol * HALF_TOL)
    half = period_point(loop, raw, detrended, falls[-3:], None)
    spread = estimate_scatter(loop, estimates)
    verdict = judge([*pairs(usable), half], target_deg, tol, longest, False, scatter=spread)
    # One estimate so far, which the period ending here overlaps by half: both share what is left of the
    # transient, so both models' corrections must pass (alone, the first-order set stopped exp(-s)/(0.01*s+1)^2
    # at 3.31 periods with its point 0.37 % off; 0.06 % at 4.31 before).
    both = periods < MIN_PERIODS
    if verdict is None and both:
        return None
    if verdict is not None and not both:
        return verdict
    # (As at a rising switch: the estimates through the second model, judged with it.)
    alt = alt_point(loop, raw, detrended, falls[-3:], half)
    second = judge([*pairs(usable, alt=True), alt], target_deg, tol, longest, False, None, ALT_RATIO, spread)
    if both:
        return verdict if second is not None else None
    return second
