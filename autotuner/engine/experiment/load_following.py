"""Load following: the record searched for load steps and drift, estimated through and followed by the relay.

While the estimates have not settled, every few periods (and before a quiet
result is accepted) the slow part of the record is fitted (load_fit.py). A
disturbance is acted on when two fits a period apart agree on it: its
|F|/K0 replaces the simple means, estimates whose windows reach back before
a load step are left out, and the relay's centre follows the load within
±amp (levels.py). Once disturbed, every period refits near the accepted fit.
On a quiet, noise-free run the estimates since the step shed the load's share
instead (load_correction.py): there the centre stays for a load within
KEEP_CENTRE of the weaker level, and the bias flips only when K0 needs it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from autotuner.engine.experiment import endings
from autotuner.engine.experiment.estimates import Estimates, lag
from autotuner.engine.experiment.convergence import SCATTER_MAX, estimate_scatter, tolerances
from autotuner.engine.experiment.levels import Levels
from autotuner.engine.experiment.load_correction import unsure
from autotuner.engine.experiment.load_fit import LoadFit, LoadFitter
from autotuner.engine.experiment.loop import Loop
from autotuner.engine.experiment.point import Point
from autotuner.engine.experiment.switching import Switching

# The record is searched for a disturbance from this many periods on (earlier,
# the filter's first corrections move the estimates anyway).
CHECK_FROM = 5
# While not converged, the record is searched for a disturbance every this many periods.
CHECK_EVERY = 2
# A fitted load (MV units, per amp) or free response (per |F|·amp) below this is no disturbance.
LOAD_FRACTION = 0.08
# The relay's centre moves only for a change of the fitted load above this fraction of amp.
SHIFT_STEP = 0.03
# A jump of |F|/K0 between consecutive estimates above this starts the search for a disturbance.
JUMP = 0.05
# A fit whose |F|/K0 is this uncertain describes no disturbance reliably enough to act on.
X_STD_MAX = 0.1
# On a run whose estimates shed the load's share (load_correction.py: quiet, noise-free), the relay's centre stays
# where it is while the load is within this share of the weaker level's amplitude (amp·(1 − 2·bias)): the cycle
# goes on around it, and every step of the levels is a new transient in the estimates.
KEEP_CENTRE = 0.5
# Where the estimates read a resonance, a load explains the record instead when the resonance's own model (second
# order through the point with the estimates' K0, no load) misses its slow part by this many times the load fit's
# residual (a resonance's: at most 0.5 times; an early load's on processes of higher order: 2.5–16 times).
RESONANCE_MISFIT = 1.5
# The dead times tried for the resonance's model, as shares of the point's lag over ω.
RESONANCE_DELAYS = (0.0, 0.1, 0.2, 0.3, 0.4)


@dataclass
class _Fits:
    """The load fits of one record (its length) and estimate (their count): the fitter, the answers by
    question (unstable, near)."""

    record: tuple[int, int]
    fitter: LoadFitter | None
    answers: dict[tuple[bool, LoadFit | None], LoadFit | None] = field(default_factory=dict)


class LoadFollowing:
    """The accepted load fit (None while quiet), the candidate awaiting confirmation, and what they discard.

    ``loop``, ``switching``, ``levels``, ``estimates``: the loop under test, the relay's crossings, its levels
    (which the fitted load moves) and the estimates (which the fits start from).
    """

    def __init__(self, loop: Loop, switching: Switching, levels: Levels, estimates: Estimates) -> None:
        self.loop = loop
        self.switching = switching
        self.levels = levels
        self.estimates = estimates
        self.fit: LoadFit | None = None
        self.candidate: LoadFit | None = None
        self.discard_before = -math.inf  # estimates whose period starts before this (s) precede a load step
        self.confirmed: LoadFit | None = None  # the candidate the accepted fit confirmed
        # A point the stopping rule holds (load_correction.Held): the fits' model goes through it rather than
        # through the latest estimate (a flip's transient in it would put the model, and K0, off).
        self.point: Point | None = None
        self.quiet = False  # a quiet, noise-free run of a process not open-loop unstable (set by the experiment)
        self._fits = _Fits((0, 0), None)

    def due(self) -> bool:
        """True when a quiet run's period should look for a disturbance (again, or on a jump of |F|/K0)."""
        periods = self.switching.periods
        items = self.estimates.items
        jump = abs(items[-1].x - items[-2].x) if len(items) >= 2 else 0.0
        # During the filter's first corrections the estimates move anyway:
        # only a large jump counts as a sign of a disturbance then.
        early = periods >= 3 and jump > 3.0 * JUMP
        again = self.candidate is not None
        return again or early or periods >= CHECK_FROM and (jump > JUMP or (periods - CHECK_FROM) % CHECK_EVERY == 0)

    def look(self, unstable: bool) -> bool:
        """Fit the slow part of the record (``unstable``: with an unstable model); True (and the disturbed mode
        on once two fits agree) if it needed a disturbance. Where the estimates read a resonance (:meth:`_resonant`)
        a fit counts only when its |F|/K0 is sure or the resonance explains the record worse
        (:meth:`_resonance_explains`)."""
        if not self.loop.config.follow_loads:
            return False
        fit = self.load_fit(unstable)
        if fit is None or (self._resonant() and unsure(fit.x_std, fit.x, tolerances(self.loop.config))
                           and self._resonance_explains(fit)):
            return False
        if not self._significant(fit):
            self.candidate = None
            return False
        # A disturbance is acted on when two fits a period apart agree on it:
        # a single odd period (a stalled link holding the MV for seconds) fits
        # as a load step too, but not the same one twice. On a quiet run one
        # sure fit is enough (_sure): what follows it checks it anyway.
        previous, self.candidate = self.candidate, fit
        agreed = previous is not None and self._agree(previous, fit)
        if not agreed and not self._sure(fit):
            return True  # look again next period before accepting anything
        # (A sure fit confirms itself: its K0 counts as the confirming candidate's, as the same fit asked twice
        # in one analysis — before a quiet result is accepted and on the period's look — always did.)
        self.confirmed = previous if agreed else fit
        self._accept(fit)
        return True

    def refit(self, unstable: bool) -> None:
        """Refit the record with this period, near the accepted fit (LoadFitter.fit's ``near``; ``unstable``:
        with an unstable model)."""
        fit = self.load_fit(unstable, near=self.fit)
        if fit is None or (self._resonant() and self._resonance_explains(fit)):
            return  # (the followed fit stands while the estimates read a resonance: see _resonant)
        assert self.fit is not None
        if not self._agree(self.fit, fit):
            # Keep following what was accepted until two new fits agree on something else.
            previous, self.candidate = self.candidate, fit
            if previous is None or not self._agree(previous, fit):
                return
        self.candidate = fit
        if fit.step_time is not None and (self.fit is None or self.fit.step_time != fit.step_time):
            self.discard_before = max(self.discard_before, fit.step_time)
        self.fit = fit
        self._follow()

    def load_fit(self, unstable: bool, near: LoadFit | None = None) -> LoadFit | None:
        """The load fit of the record (``unstable``: with an unstable model; ``near``: see LoadFitter.fit), or
        None when there is none to make.

        Made once per record, estimate and question: a quiet period's analysis may ask twice (before it
        accepts a result and when it looks for a disturbance), with the same answer.
        """
        record = (self.loop.record.held, len(self.estimates))
        if self._fits.record != record:
            self._fits = _Fits(record, self._fitter())
        fits, question = self._fits, (unstable, near)
        if question not in fits.answers:
            fits.answers[question] = None if fits.fitter is None else fits.fitter.fit(unstable, near)
        return fits.answers[question]

    def _fitter(self) -> LoadFitter | None:
        """The load fitter of the whole record with the latest estimate's point (None before one)."""
        if not self.estimates.items or len(self.switching.crossings) < 4:
            return None
        loop = self.loop
        point = self.estimates.latest.point if self.point is None else self.point
        record = loop.record.all()
        n = len(record.u)
        scale = point.gain * loop.config.amp
        return LoadFitter(record.t[:n], loop.sign * (record.y[:n] - loop.sp), record.u, loop.mv0,
                          self.switching.start, point.omega, point.gain, lag(point.value), scale, held_from=record.s)

    def _resonant(self) -> bool:
        """True when |F(jω)| reads above the static gain: a resonance, which no first-order model describes.

        The fit would invent loads there. But a load step against the relay's
        bias makes a plain lag's ratio |F|/K0 read above 1 too (−0.1 × amp on
        ``exp(-s)/(2*s+1)``: 0.37, then 1.4; over one period from 2.5 periods on,
        only the first estimate read below 1): there an earlier estimate of about
        the same |F| (within 10 %) read below 1, or a ratio a third away — one
        that cancels the bias runs away (1.1, 1.8, 2.9, 5.9 on
        ``exp(-s)/(0.05*s+1)^2`` at −0.2 × amp). A resonance builds |F| up with
        its ratio (0.49 at 0.13 … 1.68 at 1.68 on ``exp(-0.1*s)/(s^2+0.4*s+1)``).

        A step before the first estimate leaves none below 1 (−0.1 × amp at
        0.3–1.5 periods on ``exp(-s)/(2*s+1)``: 1.4–1.6 from the first on, and
        "ok" with K0 0.26): :meth:`look` fits the record anyway and takes the
        fit where its |F|/K0 is as sure as a followed load's K0 must be
        (load_correction.unsure: the loads invented for seven resonant
        processes, quiet and at 1–3 % noise, had standard errors of 0.06–0.46,
        the early step's 0.0003–0.009), or where the resonance's own model
        explains the record worse than the load does (on processes of higher
        order the early step's fit is unsure: 0.04–0.3).
        """
        latest = self.estimates.latest
        x = latest.x
        if x <= 1.0:
            return False
        gain = latest.point.gain
        return not any((e.x < 1.0 or abs(e.x - x) > x / 3.0) and abs(e.point.gain - gain) <= 0.1 * gain
                       for e in self.estimates.items[:-1])

    def _resonance_explains(self, fit: LoadFit) -> bool:
        """True when a resonance explains the record about as well as the load ``fit`` (RESONANCE_MISFIT): the
        underdamped model through the latest estimate's point and its K0 (below |F| there), no load.

        A first-order fit cannot tell them apart: on a resonance it invents a
        load against the bias too. The resonance's model can: on seven
        resonant processes it missed the slow part by 0.04–0.5 times the
        invented load's residual; on `exp(-s)/(s+1)^2` and four more of
        higher order with −0.1 × amp at 1.2 periods, by 2.5–16 times the
        load fit's (whose |F|/K0 is unsure there: 0.04–0.3).
        """
        # (The design imports the experiment: imported here, once the experiment's modules are.)
        from autotuner.engine.design.point_design import fit_resonant

        fitter = self._fits.fitter
        if fitter is None:
            return True
        latest = self.estimates.latest
        point = latest.point
        delay = lag(point.value) / point.omega
        models = [fit_resonant(point, point.gain / latest.x, share * delay) for share in RESONANCE_DELAYS]
        misfits = [fitter.misfit(m.num, m.den, m.delay) for m in models if m is not None]
        return not misfits or min(misfits) < RESONANCE_MISFIT * fitter.averaged_rms(fit)

    def _agree(self, a: LoadFit, b: LoadFit) -> bool:
        """Two fits describe the same disturbance (step time within a quarter period, sizes within a third)."""
        if a.x_std > X_STD_MAX or b.x_std > X_STD_MAX:
            return False
        period = self.switching.period()
        if (a.step_time is None) != (b.step_time is None):
            return False
        if a.step_time is not None:
            assert b.step_time is not None
            if abs(a.step_time - b.step_time) > 0.25 * period or abs(a.step - b.step) > abs(b.step) / 3.0:
                return False
        # Ramps agree within a third, or when they differ by less than a load worth
        # following over the whole record (the information criterion keeps a negligible
        # ramp in one fit and not the next).
        difference = abs(a.ramp - b.ramp)
        negligible = difference * self.loop.elapsed() < LOAD_FRACTION * self.loop.config.amp
        return negligible or difference <= max(abs(a.ramp), abs(b.ramp)) / 3.0

    def _significant(self, fit: LoadFit) -> bool:
        """A fitted disturbance worth estimating through: larger than a fraction of amp (or of the PV scale)."""
        amp = self.loop.config.amp
        step = fit.step_time is not None and abs(fit.step) >= LOAD_FRACTION * amp
        ramp = abs(fit.ramp) * self.loop.elapsed() >= (1.0 if self.quiet else 2.0) * LOAD_FRACTION * amp
        free = abs(fit.free) >= LOAD_FRACTION * self.estimates.latest.point.gain * amp
        return step or ramp or free

    def _sure(self, fit: LoadFit) -> bool:
        """True when one ``fit`` is evidence enough for a disturbance: a quiet run (the estimates since a step
        shed the load's share and must still pass the quiet rules; after a flip of the bias K0 is taken only
        once two fits agree, load_correction.Held), a fit whose |F|/K0 is as sure as a followed load's K0 must be
        (load_correction.unsure), and a step (if any) with at least a period of the record after it.

        The wrong first fits of the traces (a step placed before the real one with a ramp to make up for it,
        three periods in) had standard errors of 0.09–0.22, the right ones 0.0003–0.05; a random load's ramp
        taken at 0.049 led to K0 five times off (docs/experiment.md, "Finding a load").

        A stalled link's odd period stays out: the record marks a stall (estimates.stalled_until), and the
        two-fit rule still holds on noisy runs.
        """
        tol = tolerances(self.loop.config)
        # (Quiet with a margin: near the scatter gate, at 2 % noise, a run flips between noisy and quiet from
        # period to period, and a quiet spell's single fit is a noisy record's.)
        calm = estimate_scatter(self.loop, self.estimates) <= 0.5 * SCATTER_MAX * tol.gain_tol
        if not (self.quiet and calm) or fit.x < -tol.static_tol or unsure(fit.x_std, fit.x, tol):
            return False
        if fit.step_time is None:
            return True
        return fit.step_time > self.estimates.stalled_until and \
            self.loop.record.time(-1) - fit.step_time >= self.switching.period()

    def _accept(self, fit: LoadFit) -> None:
        self.fit = fit
        if fit.step_time is not None:
            self.discard_before = max(self.discard_before, fit.step_time)
            # (Where the estimates shed the load's share the bias flips only when K0 needs it: excite.)
            if abs(fit.step) >= 2.0 * LOAD_FRACTION * self.loop.config.amp and not self._keeps_centre():
                self.levels.flip_once()
        self._follow()

    def excite(self) -> None:
        """Flip the relay's bias now (once per experiment): after a load step the static gain is known from the
        transients alone, and a change of the MV's mean excites it (the fit's x_std falls)."""
        levels = self.levels
        if levels.flipped and levels.changed_at > -math.inf:
            return  # (a flip made already; one recorded but not applied yet, the levels never changed, goes on)
        levels.flip_once()
        levels.reset()
        levels.changed_at = self.loop.record.time(-1)

    @property
    def corrects(self) -> bool:
        """True when the estimates shed the followed load's share (load_correction.py): a ``quiet`` run, and a
        fit whose model does not run away (|F|/K0 not below −static_tol)."""
        return self.quiet and self.fit is not None and self.fit.x >= -self.loop.config.static_tol

    def _keeps_centre(self) -> bool:
        """True when the relay's centre stays put for the followed load (KEEP_CENTRE; the estimates shed the
        load's share: :attr:`corrects`)."""
        fit, config = self.fit, self.loop.config
        if fit is None or not self.corrects:
            return False
        load = fit.load_at(self.loop.record.time(-1), self.loop.record.time(0))
        return abs(load) <= KEEP_CENTRE * config.amp * (1.0 - 2.0 * config.bias)

    def _follow(self) -> None:
        """Shift the relay's centre to cancel the fitted load at the process input (within ±amp)."""
        fit, levels, loop = self.fit, self.levels, self.loop
        assert fit is not None
        time = loop.record.time
        t = time(-1)
        period = self.switching.period() if len(self.switching.rising) >= 2 else 0.0
        then = t + 0.5 * period
        load = fit.load_at(then, time(0))
        amp = loop.config.amp
        # The ramp part is followed continuously from now on; the centre takes the rest.
        applied = levels.centre_at(then)
        if abs(load) > amp:
            raise endings.load_too_large(load, amp)
        center = loop.mv0 - loop.sign * load
        rate = loop.sign * fit.ramp
        if self._keeps_centre():
            if abs(rate - levels.follow_rate) * period > 0.2 * SHIFT_STEP * amp:
                # A drift is followed from the centre where it is: no step of the levels.
                levels.follow(applied, rate, then)
        elif abs(center - applied) > SHIFT_STEP * amp or levels.changed_at == -math.inf:
            # Each step of the levels starts a transient: estimates are taken after it.
            levels.follow(center, rate, then)
            levels.changed_at = t
        elif abs(rate - levels.follow_rate) * period > 0.2 * SHIFT_STEP * amp:
            # A better drift rate: keep the level continuous where it is now.
            levels.follow(applied, rate, then)
