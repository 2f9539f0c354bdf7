"""The estimates of the point: one :class:`Estimate` per whole period, and how they are measured.

Each whole period (rising crossing to rising crossing, sub-sample times) gives
``F(jω)`` and ``x = |F(jω)|/K0`` over that period (the name the design and
docs/experiment.md give it): the Fourier coefficients of the PV as sampled and
of the MV as the process held it (``applied``), the PV's drift across the
periods taken out, and quiet, the transient's share (transient.py). An estimate whose windows held a stall of the
samples (a link or a machine that stopped) is kept but left out of the
stopping rule, with those before it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from autotuner.engine.experiment import transient
from autotuner.engine.experiment.fourier import held_coefficient, sampled_coefficient
from autotuner.engine.experiment.load_fit import settled_x
from autotuner.engine.experiment.loop import Loop
from autotuner.engine.experiment.point import Point
from autotuner.engine.experiment.record import Samples

# A sample interval this many times the usual one is a gap in the record.
GAP = 3.0
# A time without samples longer than this share of a period (and than GAP sample intervals) in an estimate's
# window (a link or a machine that stalled) leaves that estimate out of the stopping rule: the relay could not
# switch meanwhile.
STALL = 0.1
# Corrections of a quiet estimate for its transient (transient.py): the first model goes through the estimate
# as measured, the second through the first correction's (on the batch a third moved no estimate by more than
# a tenth of the second's change).
CORRECTIONS = 2


@dataclass(frozen=True)
class Estimate:
    """One whole period's estimate.

    point: F(jω) over the period ``[start, end]`` (s).
    x: |F|/K0 over the period ``[start, end]`` (the load fit's when a load is followed).
    wide_x: |F|/K0 over the same two periods with a Hann window (the mean weighted to their middle): the
        unstable-process tests read its sign, which one period of the start-up transient can invert on a
        stable lag-dominant process.
    before, start, end: the crossing times that bound the two periods, s.
    alt: the point and |F|/K0 with the transient's share read off the second model (transient.ALT_RATIO), on a
        quiet, noise-free run; else None.
    cycle_noise: σ of the measurement noise over the period ``[start, end]`` (loop.cycle_noise), PV units.
    """

    point: Point
    x: float
    wide_x: float
    before: float
    start: float
    end: float
    alt: tuple[Point, float] | None = None
    cycle_noise: float = 0.0


@dataclass
class Estimates:
    """Every estimate so far, and the stalls that left some of them out.

    items: the estimates, oldest first.
    stalled_until: the end of the latest window that held a stall (STALL), s.
    stalls: the longest gap of each such window, s.
    """

    items: list[Estimate] = field(default_factory=list)
    stalled_until: float = -math.inf
    stalls: list[float] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.items)

    @property
    def latest(self) -> Estimate:
        """The latest estimate (there must be one)."""
        return self.items[-1]

    def add(self, estimate: Estimate, gap: float, dt: float) -> None:
        """Keep ``estimate``; ``gap``: the longest time without a sample in its windows (s); ``dt``: the usual
        sample interval (s)."""
        self.items.append(estimate)
        if gap > max(STALL * (estimate.end - estimate.start), GAP * dt):
            # No sample, so no switch, for that long: the cycle around it is no limit cycle. This estimate
            # and those before it are left out, as after a change of the relay's levels.
            self.stalled_until = estimate.end
            self.stalls.append(gap)

    def usable(self, since: float) -> list[Estimate]:
        """The estimates whose period starts at ``since`` (s) or later."""
        return [e for e in self.items if e.start >= since]

    def wide_xs(self, since: float) -> list[float]:
        """The Hann |F|/K0 of the estimates whose two periods do not span ``since`` (s)."""
        return [e.wide_x for e in self.items if not e.before < since < e.end]

    def discarded(self, before: float) -> int:
        """How many estimates' periods start before ``before`` (s)."""
        return sum(1 for e in self.items if e.start < before)


def pairs(estimates: list[Estimate], alt: bool = False) -> list[tuple[Point, float]]:
    """(point, x) of each of ``estimates``: what the stopping rule judges; the second model's where ``alt`` (and
    an estimate has it)."""
    return [e.alt if alt and e.alt is not None else (e.point, e.x) for e in estimates]


def response(loop: Loop, samples: Samples, ta: float, tb: float, omega: float, hann: bool) -> complex:
    """F(jω) of the ``loop`` from the ``samples`` over ``[ta, tb]`` (s) at ``omega`` (rad/s), with a Hann window
    if ``hann``: the PV as sampled, the MV as the process held it."""
    # Means are removed first: over a window that is not exactly whole
    # periods they would leak into the coefficient.
    t, s = samples.t, samples.s
    u = samples.u - held_coefficient(s, samples.u, ta, tb, 0.0, hann).real
    y = samples.y - sampled_coefficient(t, samples.y, ta, tb, 0.0, hann).real
    return loop.sign * sampled_coefficient(t, y, ta, tb, omega, hann) / held_coefficient(s, u, ta, tb, omega, hann)


def lag(value: complex) -> float:
    """The phase lag of ``value`` (a point's F), radians in [0, 2π)."""
    return (-math.atan2(value.imag, value.real)) % (2.0 * math.pi)


def mean_x(loop: Loop, samples: Samples, ta: float, tb: float, gain: float, hann: bool = False) -> float:
    """``gain`` (|F|, PV per MV unit) over the static ratio of the means of the ``samples`` over ``[ta, tb]``
    (s), Hann-weighted if ``hann``, as deviations from the ``loop``'s operating point: |F|/K0."""
    du = held_coefficient(samples.s, samples.u - loop.mv0, ta, tb, 0.0, hann).real
    dy = sampled_coefficient(samples.t, samples.y - loop.sp, ta, tb, 0.0, hann).real
    return loop.sign * du / dy * gain if dy != 0.0 else 0.0


def drift(tt: np.ndarray, yy: np.ndarray, bounds: list[float]) -> np.ndarray:
    """Linear drift of ``yy`` sampled at ``tt`` (s) across consecutive whole periods between ``bounds`` (s).

    A slow drift (the tail of a transient, an integrating process settling
    its mean) leaks into the Fourier coefficients. The mean over a whole
    period is free of the oscillation, so the change of the means from
    period to period measures the drift alone.
    """
    first = sampled_coefficient(tt, yy, bounds[0], bounds[1], 0.0, hann=False).real
    last = sampled_coefficient(tt, yy, bounds[-2], bounds[-1], 0.0, hann=False).real
    spacing = 0.5 * (bounds[-1] + bounds[-2] - bounds[1] - bounds[0])
    return (last - first) / spacing * (tt - 0.5 * (bounds[0] + bounds[-1]))


def longest_gap(tt: np.ndarray, start: float, end: float) -> float:
    """The longest time without a sample of ``tt`` (s) within ``[start, end]`` (``start``, ``end``: s)."""
    inside = tt[(tt > start) & (tt < end)]
    return float(np.max(np.diff(np.concatenate(([start], inside, [end])))))


def period_point(loop: Loop, raw: Samples, detrended: np.ndarray, bounds: list[float],
                 fitted_x: float | None, noisy: bool = False) -> tuple[Point, float]:
    """The point over the last whole period of ``bounds`` (crossing times, s) and |F|/K0 over it, or over the
    periods of ``bounds`` when ``noisy`` (measurement noise that scatters the estimates, convergence.noisy).

    ``loop``: the loop under test; ``raw``: the samples from ``bounds[0]`` on; ``detrended``: their PV with its
    drift across ``bounds`` removed (for the point); ``fitted_x``: the load fit's |F|/K0 when a load is
    followed (then the answer, and the point as measured). Quiet and noise-free, the transient's share is
    taken out of the point (transient.py), CORRECTIONS times: the model it uses goes through the point.
    """
    ta, tb = bounds[-2], bounds[-1]
    # One whole period, rectangular: a Hann window over a single period
    # would mix the fundamental with the mean and the second harmonic.
    omega = 2.0 * math.pi / (tb - ta)
    measured = response(loop, replace(raw, y=detrended), ta, tb, omega, hann=False)
    if fitted_x is not None:
        return Point(omega, measured), fitted_x
    measure = _measure(loop, raw, bounds)
    start = bounds[0] if noisy else ta
    value = measured
    x = _static_x(loop, raw, start, tb, omega, value)
    # Not under noise: a model through one noisy estimate corrects by its noise too (at 5 % noise on
    # exp(-s)/(100*s+1) the runs ended in half the periods with the point 1 % off and K0 7 % off).
    for _ in range(0 if noisy else CORRECTIONS):
        value = measured - transient.bias(loop, raw.t, measure, bounds, value, x)
        x = _static_x(loop, raw, start, tb, omega, value)
    return Point(omega, value), x


def alt_point(loop: Loop, raw: Samples, detrended: np.ndarray, bounds: list[float],
              first: tuple[Point, float]) -> tuple[Point, float]:
    """The quiet, noise-free estimate over the last whole period of ``bounds`` (crossing times, s) with the
    transient's share read off the second model (two lags, transient.ALT_RATIO) instead of the first-order one,
    through the first-order estimate ``first`` (point, |F|/K0: :func:`period_point` of the same ``loop``,
    ``raw`` samples and ``detrended`` PV).

    Its |F|/K0 is the first's at its |F|: the static ratio is a ratio of means times |F|, and its refinement
    (settled_x) reads the slow lag's memory alike under either model; the root it finds is most of an
    analysis's cost.
    """
    ta, tb = bounds[-2], bounds[-1]
    point, x = first
    measured = response(loop, replace(raw, y=detrended), ta, tb, point.omega, hann=False)
    measure = _measure(loop, raw, bounds)
    # One correction: the model goes through the first-order estimate, which has shed most of the transient
    # already (a second moved the batch's points by at most 0.003 % and stopped no run sooner).
    value = measured - transient.bias(loop, raw.t, measure, bounds, point.value, x, transient.ALT_RATIO)
    return Point(point.omega, value), x * abs(value) / point.gain


def followed_point(loop: Loop, raw: Samples, detrended: np.ndarray, bounds: list[float], static_gain: float,
                   load: np.ndarray, first: Point | None = None, ratio: float = 0.0) -> tuple[Point, float]:
    """The quiet, noise-free estimate over the last whole period of ``bounds`` (crossing times, s) while a load is
    followed: the transient's share read off the model (transient.py; two lags ``ratio`` apart, or first order
    for 0) driven by the MV and the fitted ``load`` (MV units at each of the record's holds), through the point
    and the fit's ``static_gain`` (K0, PV per MV unit); its |F|/K0 is |F|/K0 of the fit.

    ``loop``, ``raw``, ``detrended``: as for :func:`period_point`. ``first``: the first-order model's estimate,
    which the second model goes through (one correction, as :func:`alt_point`); None for the first-order one
    (CORRECTIONS). The point is the PV as measured less a model's transient: a fit that does not describe the
    record leaves a share that differs from window to window, and the stopping rule's consistency tests
    (stopping.py) do not pass on such estimates.
    """
    ta, tb = bounds[-2], bounds[-1]
    omega = 2.0 * math.pi / (tb - ta)
    measured = response(loop, replace(raw, y=detrended), ta, tb, omega, hann=False)
    measure = _measure(loop, raw, bounds)
    value = measured if first is None else first.value
    for _ in range(CORRECTIONS if first is None else 1):
        x = fitted_x(abs(value), static_gain)
        value = measured - transient.bias(loop, raw.t, measure, bounds, value, x, ratio, load)
    return Point(omega, value), fitted_x(abs(value), static_gain)


def fitted_x(gain: float, static_gain: float) -> float:
    """|F|/K0 of a point of ``gain`` (|F|, PV per MV unit) with a fitted ``static_gain`` (K0, PV per MV unit; inf
    for an integrator: 0)."""
    return gain / static_gain if math.isfinite(static_gain) and static_gain != 0.0 else 0.0


def _measure(loop: Loop, raw: Samples, bounds: list[float]) -> Callable[[np.ndarray], complex]:
    """The estimate over the last period of ``bounds`` (crossing times, s) made from a PV deviation at the
    ``raw`` samples' times as from the measured PV of the ``loop`` (the drift across ``bounds`` removed)."""
    ta, tb = bounds[-2], bounds[-1]
    omega = 2.0 * math.pi / (tb - ta)

    def measure(out: np.ndarray) -> complex:
        shifted = loop.sign * (out - drift(raw.t, out, bounds))
        return response(loop, replace(raw, y=shifted), ta, tb, omega, hann=False)

    return measure


def _static_x(loop: Loop, raw: Samples, start: float, end: float, omega: float, value: complex) -> float:
    """|F|/K0 of the ``loop`` for the point ``value`` (F at ``omega``, rad/s) from the means of the ``raw`` samples over ``[start, end]`` (s), with the MV's as the slow lag has passed it
    on.

    Over the last period alone unless the noise scatters the estimates (then two: the noise of a mean falls
    with its length): the period before still carries more of the start's transient, and the point's
    correction needs an |F|/K0 that has shed it (the first two estimates of
    ``10*exp(-0.3*s)/((10*s+1)*(0.7*s+1))`` read −2.0 and 0.77 times the true |F|/K0 over two periods, 0.56
    and 0.84 over one).
    """
    du = held_coefficient(raw.s, raw.u - loop.mv0, start, end, 0.0, hann=False).real
    dy = sampled_coefficient(raw.t, raw.y - loop.sp, start, end, 0.0, hann=False).real
    # Compare estimates through |F|/K0, which stays bounded as K0 grows.
    plain = loop.sign * du / dy * abs(value) if dy != 0.0 else 0.0
    # The MV since the start: the slow lag remembers it (settled_x reads what its lag still holds).
    history = loop.record.all()
    return settled_x(history.s, history.u, loop.sign * dy, plain, abs(value), omega, lag(value), start, end,
                     *loop.settling, u0=loop.mv0)


def wide_x(loop: Loop, samples: Samples, bounds: list[float]) -> float:
    """|F|/K0 of the ``loop`` from the ``samples`` over the two whole periods between ``bounds`` (three crossing
    times, s), Hann-windowed."""
    ta, tb = bounds[0], bounds[-1]
    value = response(loop, samples, ta, tb, 4.0 * math.pi / (tb - ta), hann=True)
    return mean_x(loop, samples, ta, tb, abs(value), hann=True)
