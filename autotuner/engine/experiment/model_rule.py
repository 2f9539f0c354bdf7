"""The model rule: a record that a fitted process model explains, and keeps explaining, stops the experiment.

At each switch of a quiet run's first ``PERIODS`` whole periods, two lags and
a dead time are fitted to the whole record (process_fit.py: the noise stage's
rest, the relay's first step from it and every switch since). The record
holds the start's transient, which tells the lags from the dead time and the
static gain from the cycle. When the fits at two consecutive switches each
reproduce the record to within ``MISFIT_SHARE`` of ``gain_tol`` (RMS residual
over the PV's swing) and agree on the point at the target (``AGREE`` of
``gain_tol``) and on ``|F|/K0`` (``AGREE`` of the settled rule's static bound),
and the cycle's latest whole period is within ``REACH`` of the model's at the
target, the point is the model's at the target and ``|F|/K0`` the model's. The
record is not looked through for a load before the result is accepted, as a
quiet estimate's is (load_following.py): a load would misfit the model.

A load at the process input (a drift from TUNE, a step at any time) misfits the
plain model; where it does beyond the bound, the fit adds the model's response
to the load (process_fit.fit_load: a ramp from the record's start, or a step at
a time of its own), and a record that model explains passes as above, the
result reporting the fitted load (``disturbance``, ``load_estimate``). The load
terms soak up little of what the model family misses: on the batch's three lags
and more they leave 0.5–4 % of the swing (the bound is 3e-4).

Why the misfit bounds the point: the PV of a relay cycle is mostly its
fundamental, so a relative error ε of the model's F at the cycle's frequency
leaves a residual of RMS about ε/(2√2)·(4/π) ≈ 0.45 ε of the swing. A misfit of
3e-4 (the default ``gain_tol`` of 1 %) holds F there to about 0.07 %; the two
fits' agreement, half a period apart with the cycle nearing the target, holds
the model's curve between the cycle and the target. Where the process is not of
the model's family (three lags and more, an integrator, a zero) the fit misfits
by 0.3–10 % of the swing and the estimates' rules (stopping.py) judge as before;
so do a load the load following took first on a quiet run (the rule fits no record
once it has), a PV still settling at TUNE, a changed relay level, an unstable process.

Under measurement noise whose σ alone misfits beyond the bound, the noisy rule
judges instead, at each rising switch of the first ``NOISY_PERIODS``: the same
fit (with the load's term where the plain model's residual is not white), its
residual's lag-1 autocorrelation within a few of white noise's (:func:`white`:
three lags and more leave 0.25–0.8), and its point's standard error from the
linearised least squares (process_fit.spread) within ``noise_tol``, the standard
error the estimates' averaged rule accepts; the previous rising switch's point
agrees within ``AGREE_SIGMAS`` of their errors (:func:`judge_noisy`). ite counts
the rising switch at which the error is expected within the tolerance
(:func:`noisy_end`, :func:`noisy_look`).

Measured on the 133-process batch (docs/experiment.md, "Three periods, the
model rule"): the families the model holds (P1, P2, P7: 78 processes) and the
integrators with a lag and dead time (P6, 9) stop at 1.4–2.9 periods with their
points within 0.04 % of the exact ones; no other process's fits pass. At 1 %
noise (docs/experiment.md, "The model rule under noise") the batch's median
falls from 4.4 to 3.2 periods, its points 0.18 % off at the median, 0.44 % at
worst; the field bench's "noise 2 % + load +0.15 mid" from 12.5 to 5.0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import Enum

import numpy as np

from autotuner.engine.experiment.point import Point
from autotuner.engine.experiment.process_fit import ProcessModel, Spread
from autotuner.engine.experiment.stopping import Tolerances, Verdict, static_bound

# The misfit a fit may leave, as a share of gain_tol (RMS residual over the PV's swing): 3e-4 at the default
# gain_tol. The batch's integrators with a lag and dead time (P6) misfit by 1.5–2.5e-4 and stop with their points
# 0.02–0.04 % off (0.007–0.19 % by the estimates, two periods later); 1e-3 let one of a slow two-lag process's early
# local minima pass, 0.46 % off (a single fit, before the REACH and agreement tests).
MISFIT_SHARE = 0.03
# Two consecutive fits agree on F at the target within this share of gain_tol, and on |F|/K0 within this share of
# the static bound (stopping.static_bound).
AGREE = 0.1
# The model is read at the target only once the cycle has come within this factor of it (its latest whole period
# against the model's at the target): a lag-dominant process's first periods are 3–5 times shorter, and the
# record's excitation there leaves the model's curve at the target an extrapolation (the integrators of P6 passed
# at 0.6 periods with their points 0.1 % off).
REACH = 1.5
# ite's first look (progress.py): a fit at the first rising switch (half a period known), and later ones, within
# this share of gain_tol say the rule will likely stop the run soon. (On the batch the families the model holds
# misfit by 1e-15–1e-2 at the first rising switch, most below 1e-3; three lags and more by 0.017–0.28; the
# integrators of P6 by 1e-4–7e-3. A simulated PLC over Modbus at ten times real time, whose ticks are not the
# samples' times, misfit by 3–5e-3 at every switch: at gain_tol, ite counted such a run as the rule's, then rose
# by 2–4 periods when the rule did not stop it — tests/test_handshake.py; a fit to the first half period can pass
# below that share all the same, and a rough fit's hint asks the record's noise too: first_look.)
EARLY_SHARE = 0.1
# Fits are tried at the switches of the first this many whole periods (a fit costs 2–3 ms of CPU; on the batch
# every run the rule stops, it stops within three).
PERIODS = 4
# Under noise (the rule's misfit bound below the noise's σ): the residual's lag-1 autocorrelation a fit may leave,
# CORRELATION_SIGMAS of its standard error for white noise (1/√samples) and at most CORRELATION. On the batch at 2 %
# noise with a load step, the two lags and dead time's fits leave 0.25–0.81 on three lags and more, 0.3–0.99
# without the load's term once the step is in the record; white noise 0.17 at 300 samples one fit in a thousand.
CORRELATION = 0.2
CORRELATION_SIGMAS = 3.0
# And the rising switches of the first this many whole periods it is tried at (a fit or two per period).
NOISY_PERIODS = 8
# ite's first look under noise: a fit at the first rising switch whose residual is the noise, whose point is known
# within FIRST_SPREAD (relative standard error) on a record whose noise is at most FIRST_NOISE of its swing says
# the noisy rule will likely stop the run at its first chances. (On the batch, every eighth process: the runs it
# stopped within 2.7 periods at 1 % noise, 0.5–2.5 % and 0.9–1.9 %; the slower ones at 1 % 9–60 % or 3–7 %; every
# run at 5 % noise, which the rule stops at 3.6 periods and later, 3.8–8.7 % of the swing.)
FIRST_SPREAD = 0.025
FIRST_NOISE = 0.025
# ite's hint under noise counts the standard error of the point falling by at most this factor a period (at 5 %
# noise, a slow lag's fell 4.4 times from its first whole period to its second, then 1.5 times).
SPREAD_FALL = 3.0
# Two consecutive fits of a noisy record agree where their F differ by at most this many of their standard errors
# together (each within the noise tolerance; the later one's record holds the earlier's).
AGREE_SIGMAS = 2.0


class Fit(Enum):
    """What the latest fit says of the run's length (ite, progress.py)."""

    UNKNOWN = "no fit yet"
    EXPLAINS = "the model explains the record (the first look, or a cycle not yet within REACH of the target)"
    NEXT = "the model explains the record near the target: the next switch's fit stops the run if it agrees"
    JUDGING = "that next switch has come, its analysis is pending"
    NOISY = "under noise, the first look's residual is the noise and its point near enough: the noisy rule's run"
    NO = "the model does not explain the record"


@dataclass(frozen=True)
class ModelPoint:
    """The ``point`` at the target of a fitted model, its ``x`` = |F|/K0 and, fitted to a noisy record, the
    ``spread``: the standard error of its F relative to |F| (process_fit.spread)."""

    point: Point
    x: float
    spread: float = 0.0


@dataclass
class NoisyFits:
    """The noisy rule's latest fits, at the latest rising switch it judged: the ``plain`` model and the ``loaded``
    one (with a load at the process input, process_fit.fit_load; None before one), whether the loaded one's
    residual was white (``loaded_white``), the ``point`` it read (:func:`noisy_point`, None where none) and when
    it expects to stop the run (``end``, s on the record's clock: :func:`noisy_end`)."""

    plain: ProcessModel | None = None
    loaded: ProcessModel | None = None
    loaded_white: bool = False
    point: ModelPoint | None = None
    end: float | None = None


def bound(tol: Tolerances) -> float:
    """The misfit the rule lets a fit leave with the tolerances ``tol`` (a share of the PV's swing)."""
    return MISFIT_SHARE * tol.gain_tol


def _rough(model: ProcessModel, tol: Tolerances) -> bool:
    """True when ``model`` misfits by at most EARLY_SHARE of ``tol.gain_tol``: near enough that the rule's bound may
    follow (ite's first look, and whether the rule fits again)."""
    return model.misfit <= EARLY_SHARE * tol.gain_tol


def could_explain(noise: float, swing: float, tol: Tolerances) -> bool:
    """True when a record of PV ``swing`` (PV units, its range) with measurement noise of σ ``noise`` (PV units)
    can be fitted within the rule's misfit (``tol``): the noise alone misfits by σ over the swing."""
    return swing > 0.0 and noise <= bound(tol) * swing


def first_look(model: ProcessModel | None, tol: Tolerances, noise: float) -> Fit:
    """ite's hint from a ``model`` fitted at the first rising switch, with the tolerances ``tol`` and the record's
    ``noise`` (its σ over the PV's swing, the sampling's timing spread included: relay.py): EXPLAINS where the
    run is likely one the rule stops at its first chances — the model misfits within the rule's bound, or by at
    most EARLY_SHARE of ``tol.gain_tol`` with the noise within the bound —, else NO.

    (The later fits, to longer records, misfit by about the noise at least — 0.5–1 of it on a simulated PLC's
    record —, and once the estimates measure it the rule's gate (:func:`could_explain`) shuts: a rough fit to a
    short record on a noisier one said EXPLAINS, the later hints NO, and ite rose by two periods
    (tests/test_handshake.py, whose sampling reads as 1–6e-3 of the swing). Within the bound the noise is not
    asked: over the first half period the cycle's own third difference reads up to 3.4e-4 of the swing on the
    noise-free batch, whose rough first looks read 1.5e-4 at most.)"""
    if model is None:
        return Fit.NO
    if model.misfit <= bound(tol) or _rough(model, tol) and noise <= bound(tol):
        return Fit.EXPLAINS
    return Fit.NO


def white(spread: Spread | None) -> bool:
    """True when the residual of the fit whose ``spread`` it is (process_fit.spread; None: no fit) is the noise, as
    far as its lag-1 autocorrelation tells: within CORRELATION_SIGMAS of white noise's and CORRELATION."""
    if spread is None:
        return False
    return spread.correlation <= min(CORRELATION, CORRELATION_SIGMAS / math.sqrt(max(spread.samples, 1)))


def noisy_look(spread: Spread | None, noise: float, swing: float) -> Fit:
    """ite's first look under noise, from the ``spread`` of a model fitted at the first rising switch
    (process_fit.spread; None where there is none) and the noise's σ ``noise`` (PV units) against the record's
    ``swing`` (PV units): NOISY where its residual is the noise (:func:`white`), its point known within FIRST_SPREAD
    and the noise at most FIRST_NOISE of the swing (the run is likely one the noisy rule stops at its first
    chances), else NO."""
    if white(spread) and spread.point <= FIRST_SPREAD and noise <= FIRST_NOISE * swing:
        return Fit.NOISY
    return Fit.NO


def worth_fitting(previous: ProcessModel | None, tol: Tolerances) -> bool:
    """True when the rule should fit the record at this switch: no fit yet, or the ``previous`` one misfits by at most
    EARLY_SHARE of ``tol.gain_tol`` (the batch's three lags and more misfit by 1.5–3 % at every switch: their fits
    are the filter's aim's only, at the first two rising switches)."""
    return previous is None or _rough(previous, tol)


def hint(model: ProcessModel | None, latest: ModelPoint | None, period: float, tol: Tolerances, noise: float,
         previous: Fit) -> Fit:
    """ite's hint from the ``model`` fitted at this switch, its point (``latest``, None where it misfits beyond the
    rule's bound) and the cycle's latest whole ``period`` (s), with the tolerances ``tol`` and the record's
    ``noise`` (as for :func:`first_look`): NEXT where the next switch's fit may stop the run, EXPLAINS where the
    model explains the record within the rule's bound, or as well as ite's first look asks (:func:`first_look`)
    unless the ``previous`` hint said NO, else NO.

    (After a NO, a fit between the rule's bound and the first look's share is the misfit or the noise wandering
    about that share — a sampling's timing spread near it, 1–2e-3 of the swing —: a hint that turned back to
    EXPLAINS lowered ite, and the next NO raised it by two periods. On the noise-free batch every hint that turns
    from NO to EXPLAINS does so within the rule's bound, 2e-4 at most.)"""
    if latest is not None and _reached(latest, period):
        return Fit.NEXT
    if latest is not None:
        return Fit.EXPLAINS
    return Fit.NO if previous is Fit.NO else first_look(model, tol, noise)


def _reached(latest: ModelPoint, period: float) -> bool:
    """True when the cycle's latest whole ``period`` (s) is within REACH of the ``latest`` model's at the target."""
    return abs(math.log(period * latest.point.omega / (2.0 * math.pi))) <= math.log(REACH)


def model_point(model: ProcessModel | None, sign: float, target_deg: float, tol: Tolerances) -> ModelPoint | None:
    """The point at ``target_deg`` (degrees of lag) of a ``model`` fitted within the rule's misfit (``tol``), the
    loop's ``sign`` (+1 direct, −1 reverse acting) applied; None where there is no model, it misfits, or it
    never lags that much."""
    if model is None or model.misfit > bound(tol):
        return None
    return _read(model, sign, target_deg)


def noisy_point(model: ProcessModel | None, spread: Spread | None, sign: float,
                target_deg: float) -> ModelPoint | None:
    """The point at ``target_deg`` (degrees of lag) of a ``model`` fitted to a noisy record, the loop's ``sign``
    applied, where its ``spread`` (process_fit.spread) says it holds the process (its residual is the noise:
    :func:`white`), with its standard error; None elsewhere."""
    if model is None or not white(spread):
        return None
    point = _read(model, sign, target_deg)
    return None if point is None else replace(point, spread=spread.point)


def _read(model: ProcessModel, sign: float, target_deg: float) -> ModelPoint | None:
    """The point at ``target_deg`` (degrees of lag) of ``model``, the loop's ``sign`` applied; None where its gain
    has the wrong sign or it never lags that much."""
    if sign * model.k0 <= 0.0:
        return None
    omega = model.frequency(math.radians(target_deg))
    if omega is None:
        return None
    value = sign * complex(model.response(np.array([omega]))[0])
    return ModelPoint(Point(omega, value), abs(value) / (sign * model.k0))


def judge(previous: ModelPoint | None, latest: ModelPoint | None, period: float, tol: Tolerances) -> Verdict | None:
    """The verdict of the model rule on the fits at two consecutive switches (``previous``, ``latest``; None where a
    switch had no fit within the misfit) with the tolerances ``tol``, the latest whole ``period`` of the cycle (s)
    within REACH of the latest model's at the target: the latest model's point when both agree."""
    if previous is None or latest is None:
        return None
    if not _reached(latest, period):
        return None
    gain = latest.point.gain
    if abs(latest.point.value - previous.point.value) > AGREE * tol.gain_tol * gain:
        return None
    if abs(latest.x - previous.x) > AGREE * static_bound(tol, latest.x):
        return None
    return Verdict(latest.point, latest.x, 2)


def judge_noisy(previous: ModelPoint | None, latest: ModelPoint | None, period: float,
                tol: Tolerances) -> Verdict | None:
    """The verdict of the model rule on a noisy record's fits at two consecutive rising switches (``previous``,
    ``latest``: :func:`noisy_point`'s, None where a fit's residual was not the noise) with the tolerances ``tol``,
    the latest whole ``period`` of the cycle (s) within REACH of the latest model's at the target: the latest
    model's point where its standard error is within ``tol.noise_tol`` (what the estimates' averaged rule
    accepts) and the previous one's F agrees within AGREE_SIGMAS of their standard errors together, |F|/K0
    within the static bound (a search that fell into another minimum jumps by more)."""
    if previous is None or latest is None or latest.spread > tol.noise_tol or not _reached(latest, period):
        return None
    gain = latest.point.gain
    if abs(latest.point.value - previous.point.value) > AGREE_SIGMAS * math.hypot(latest.spread, previous.spread) * gain:
        return None
    if abs(latest.x - previous.x) > static_bound(tol, latest.x):
        return None
    return Verdict(latest.point, latest.x, 2)


def noisy_end(previous: ModelPoint | None, latest: ModelPoint | None, now: float, ran: float, period: float,
              periods: int, tol: Tolerances) -> float | None:
    """ite's hint under noise: the time (s, the record's clock) of the rising switch at which :func:`judge_noisy` is
    expected to stop the run, from the ``latest`` fit's point at the rising switch of ``now`` (s) and the
    ``previous`` one's a period before, the relay having ``ran`` (s) for ``periods`` whole ``period`` (s) by then:
    the first whole period after which the point's standard error is within ``tol.noise_tol`` (at least the next
    one). The error falls as the inverse square root of the record's length once the model is well determined, and
    faster before (at 1 % noise on the batch's slow lags: 20 % to 0.5 % in a period): the faster of that law and the
    latest period's ratio kept. None where there is no point (the residual is not the noise) or that switch comes
    after NOISY_PERIODS (the estimates' rules judge)."""
    if latest is None or period <= 0.0:
        return None
    ratio = (latest.spread / tol.noise_tol) ** 2
    more = max(1, math.ceil((ratio - 1.0) * ran / period))
    if previous is not None and 0.0 < latest.spread < previous.spread and ratio > 1.0:
        fall = min(previous.spread / latest.spread, SPREAD_FALL)
        more = min(more, max(1, math.ceil(math.log(ratio) / math.log(fall))))
    return now + more * period if periods + more <= NOISY_PERIODS else None
