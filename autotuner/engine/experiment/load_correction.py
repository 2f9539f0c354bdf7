"""Estimates through a followed load: the load's share taken out as the start's transient is, not waited out.

A load at the process input is one more input that is not periodic. The
model that takes the start's transient out of a quiet estimate (transient.py)
is driven by the MV as the process held it; driven by the MV and the fitted
load (load_fit.py), the same model takes out the tail of a load step, a ramp
and the transient of each change of the relay's levels that following the
load makes. So a quiet, noise-free run that finds a load keeps its estimates
since the step (each re-read with the latest fit, its |F|/K0 that of the
fit's K0) instead of waiting for new ones after the relay's centre moved.

The point stays the PV as measured less a model's transient: a fit that does
not describe the record leaves a share that differs from one window to the
next, and the stopping rule's consistency tests (stopping.py), the same as
on a quiet run, do not pass; a wrong fit delays the end, it does not move
the point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from autotuner.engine.experiment.estimates import Estimate, drift, fitted_x, followed_point
from autotuner.engine.experiment.load_fit import LoadFit
from autotuner.engine.experiment.loop import Loop
from autotuner.engine.experiment.stopping import Tolerances, Verdict, static_bound

# A followed load's K0 is taken when this many consecutive fits agree on it (Held).
FITS_AGREE = 2
from autotuner.engine.experiment.transient import ALT_RATIO


def loads(loop: Loop, fit: LoadFit) -> np.ndarray:
    """The ``fit``'s load at the process input at each of the ``loop``'s recorded holds, MV units."""
    history = loop.record.all()
    return fit.loads(history.s, loop.record.time(0))


def reread(loop: Loop, estimate: Estimate, fit: LoadFit, load: np.ndarray, follows_drift: bool) -> Estimate:
    """``estimate`` of the ``loop`` re-read from the record with the ``fit`` (its ``load`` at the record's holds,
    :func:`loads`): the point and |F|/K0 through the first-order model, the second model's beside them
    (estimates.followed_point).
    ``follows_drift``: the relay's levels follow a ramp (the MV's drift is then taken out, as the period's
    own analysis does)."""
    bounds = [estimate.before, estimate.start, estimate.end]
    raw = loop.record.since(estimate.before)
    if follows_drift:
        raw = replace(raw, u=raw.u - drift(raw.s, raw.u, bounds))
    detrended = raw.y - drift(raw.t, raw.y, bounds)
    point, x = followed_point(loop, raw, detrended, bounds, fit.static_gain, load)
    alt = followed_point(loop, raw, detrended, bounds, fit.static_gain, load, point, ALT_RATIO)
    return replace(estimate, point=point, x=x, alt=alt)


@dataclass
class Held:
    """A followed load's point, held once estimates since its step agreed on it, and the fit's K0 as it came.

    The stopping rule's verdict on those estimates fixes the point; a change of the relay's levels made after
    them (the bias's flip that excites K0) is a transient the point need not wait out. K0 is the fit's, taken
    when its standard error is within ``static_tol`` and the latest two fits (a period apart, both with a
    period of the relay's latest levels) agree on it as a quiet run's means must (stopping.static_bound): the
    first fits after a flip read a model's idea of its transient, which on a process of higher order than the
    fit's model moves K0 from period to period.

    verdict: the held verdict, or None; oldest: the start of the oldest estimate it came from, s; gains: the
    followed fit's K0 at each period (the confirming candidate's first), PV per MV unit, with the time it
    was made, s.
    """

    verdict: Verdict | None = None
    oldest: float = math.inf
    gains: list[tuple[float, float]] = field(default_factory=list)

    def update(self, verdict: Verdict | None, oldest: float, since: float, fit: LoadFit, now: float) -> None:
        """Hold ``verdict`` (from estimates starting at ``oldest``, s) if there is one; drop the held one if the
        step moved beyond its oldest estimate's start (``since``, s); note the ``fit``'s K0 made at ``now`` (s)."""
        if self.verdict is not None and self.oldest < since:
            self.verdict = None
        if verdict is not None:
            self.verdict, self.oldest = verdict, oldest
        self.gains.append((now, fit.static_gain))

    def result(self, fit: LoadFit, tol: Tolerances, changed_at: float) -> Verdict | None:
        """The held verdict with the ``fit``'s |F|/K0 once K0 is as sure as the tolerances ``tol`` ask (the fits
        compared made after the levels last ``changed_at``, s), else None."""
        verdict = self.verdict
        latest = [k0 for when, k0 in self.gains[-FITS_AGREE:] if when > changed_at]
        if verdict is None or len(latest) < FITS_AGREE or self.uncertain(fit, tol):
            return None
        gain = verdict.point.gain
        xs = [fitted_x(gain, k0) for k0 in latest]
        x = fitted_x(gain, fit.static_gain)
        if max(xs) - min(xs) > static_bound(tol, x):
            return None
        return replace(verdict, x=x)

    def uncertain(self, fit: LoadFit, tol: Tolerances) -> bool:
        """True when the ``fit``'s standard error of |F|/K0 at the held point is beyond the tolerances ``tol``
        (:func:`unsure`)."""
        gain = fit.static_gain * fit.x if self.verdict is None else self.verdict.point.gain
        return unsure(fit.x_std, fitted_x(gain, fit.static_gain), tol)


def unsure(x_std: float, x: float, tol: Tolerances) -> bool:
    """True when a standard error ``x_std`` of |F|/K0 at ``x`` is beyond the tolerances ``tol``: one static_tol,
    as a followed load's K0 always had; on a slow mode (|F|/K0 below 0.1) relative to it, twice the settled
    rule's bound (an error of 0.019 at 0.053 — K0 five times off, under a random load the step-and-ramp fit does
    not describe — is no estimate of K0)."""
    return x_std > (tol.static_tol if x >= 0.1 else min(tol.static_tol, 2.0 * static_bound(tol, x)))
