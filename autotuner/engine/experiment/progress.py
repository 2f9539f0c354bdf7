"""Progress: the experiment's stage, the seconds it still needs (``ite``) and its progress report.

The time left: before two whole periods, a typical run's length at the prior
period (the caller's ``expected_period``, else a share of the time limit, else
``SAMPLES_PER_PERIOD`` samples) less the time run; then the periods the
stopping rule still needs, at the latest period: on a quiet run the batch's
median at the same phase error and change of the period (fitted apart for a
settled point of one estimate and one of the mean of two), on a noisy one the
phase error's convergence; while a load is followed, at least what its
stage still needs (confirmation, a held point, K0). The displayed value counts down like a clock within
``HOLD`` of that estimate (docs/experiment.md, "ite and progress", "An honest
ite", "ite under a followed load", "ite after the model aim"). ``ite`` is a report: no decision of the
experiment reads it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

from autotuner.engine.experiment import convergence
from autotuner.engine.experiment.convergence import MIN_PERIODS, estimate_scatter, tolerances
from autotuner.engine.experiment.estimates import GAP, STALL, Estimates
from autotuner.engine.experiment.load_correction import FITS_AGREE, Held
from autotuner.engine.experiment.load_following import LoadFollowing
from autotuner.engine.experiment.loop import Loop
from autotuner.engine.experiment.model_rule import Fit
from autotuner.engine.experiment.stopping import MEAN_SCATTER
from autotuner.engine.experiment.switching import Switching
from autotuner.engine.outcome import Code

# Without an expected period, the time-left estimate starts from this share of the time limit.
LIMIT_SHARE = 200.0
# ... and without a time limit, from this many samples.
SAMPLES_PER_PERIOD = 100.0
# Before two whole periods, the periods from the relay's start to the end: TYPICAL_PERIODS[False] for a quiet run
# whose settled point is the mean of the latest two estimates (stopping.MEAN_SCATTER: the batch's 1 % runs),
# [True] for a noisy run (docs/experiment.md, "An honest ite"), CLEAN_TYPICAL_PERIODS for a quiet run whose point is
# one estimate or the model's (model_rule.py), by what the latest fit says (model_rule.Fit): no fit yet (the batch's
# median), and from the first rising switch on (the first look's) where the model explains the record (the median of
# the batch's runs the model rule stopped: 1.34, p10–p90 1.2–1.6) or does not (of the others).
TYPICAL_PERIODS = {False: 4.0, True: 6.0}
CLEAN_TYPICAL_PERIODS = {Fit.UNKNOWN: 2.8, Fit.EXPLAINS: 1.34, Fit.NOISY: 1.85, Fit.NO: 3.36}


@dataclass(frozen=True)
class QuietFit:
    """A quiet run's periods left at a rising switch, the batch's median at the same errors (fitted in log):
    ``settled[whole periods done, the largest key for more]`` times (phase error / tolerance) ** ``phase_power``
    times (the latest period's change / PERIOD_STEP) ** ``change_power`` times (latest period / the one before)
    ** ``growth_power`` (each power dimensionless). The period's change predicts best: a cycle whose period still
    moves is still settling, and the stop waits on |F|, which settles with it."""

    settled: dict[int, float]
    phase_power: float
    change_power: float
    growth_power: float

    def periods(self, done: int, error: float, change: float, ratio: float) -> float:
        """The periods left after ``done`` whole periods, the phase ``error`` and the period's ``change`` as shares
        of their tolerances, the latest period ``ratio`` times the one before."""
        keys = self.settled
        return (keys[min(max(done, min(keys)), max(keys))] * error ** self.phase_power
                * change ** self.change_power * ratio ** self.growth_power)


# A settled point that is the mean of the latest two estimates (the batch's 1 % noise runs): the fit on the batch
# before the model aim (noise-free and 1 % pooled, docs/experiment.md "ite after the shorter experiment"); the
# 1 % runs still fit it (within ±30 % 58 % of their statuses).
AVERAGED_FIT = QuietFit({2: 0.23, 3: 0.42, 4: 0.60}, phase_power=0.28, change_power=0.47, growth_power=0.165)
# A settled point that is one estimate (noise-free): since the model aim the first two periods step by a third and
# the short runs end at 3–4 periods, so a large change of the period after two or three says less than it did, and
# the runs still going after four are the long lag-dominant ones (docs/experiment.md, "ite after the model aim").
CLEAN_FIT = QuietFit({2: 0.27, 3: 0.32, 4: 1.08, 5: 1.53}, phase_power=0.18, change_power=0.49, growth_power=0.265)
# A change of the period below this share counts as none.
PERIOD_STEP = 0.01
# A noisy or disturbed run: the phase error's decay per period, the periods after it is within the tolerance
# and the whole periods the averaged rule needs at least (calibrated on the batch's 1 % runs when they were noisy
# ones, before the scatter gate; kept).
NOISY_CONVERGENCE = 0.6
NOISY_AFTER_CONVERGED = 1.0
NOISY_MIN_DONE = MIN_PERIODS + 2
# ...and at least NOISY_PERIODS times (one estimate's scatter / noise_tol) ** SCATTER_POWER times (phase error /
# tolerance) ** NOISY_PHASE_POWER: the averaged rule waits for the standard error of a mean of estimates, which
# takes longer the more each scatters (the field bench's 3 % and 5 % noise runs, every 5th process of the batch,
# fitted in log at their rising switches; docs/experiment.md, "ite after the shorter experiment").
NOISY_PERIODS = 3.0
SCATTER_POWER = 0.57
NOISY_PHASE_POWER = 0.4
# A followed load: the periods from the latest rising switch that its stages still need, the medians of the
# field bench's disturbed runs (every 13th process of the batch, docs/experiment.md "ite under a followed load").
# A load fit awaiting its confirmation a period later, and every stage after it (5.1–8.4 periods at the median,
# more the more estimates came before it; 8 carries the countdown through the stages that follow).
CANDIDATE_PERIODS = 8.0
# Followed, no point held yet: the estimates since the step re-read until a rule passes, then K0.
HOLD_PERIODS = 1.0
# The point held, K0 not sure: the bias's flip and the fits after it agreeing, less LOAD_FIT_PERIODS per fit made
# since the levels last changed, at least a period per fit that must agree (load_correction.FITS_AGREE).
K0_PERIODS = 4.5
LOAD_FIT_PERIODS = 0.5
# The point held and K0's standard error within the tolerance: the fits agreeing.
SURE_PERIODS = 2.2
# A followed load whose share the estimates keep (noisy, or open-loop unstable): the estimates start again after
# the step, UNCORRECTED_PERIODS less UNCORRECTED_ESTIMATE per usable estimate since, at least UNCORRECTED_MIN.
UNCORRECTED_PERIODS = 6.0
UNCORRECTED_ESTIMATE = 1.4
UNCORRECTED_MIN = 2.0
# From two whole periods on, at least this share of the latest period is left while the run goes on.
LAST_SHARE = 1.0
# A rise of the raw estimate is held off as long as the countdown stays within this share of it (0.3 → 0.35 with
# the quiet fit (AVERAGED_FIT): 2–6 points more of the batch's runs never rise, within ±30 % the same).
HOLD = 0.35
# A fall of the raw estimate is followed down to this share above it: a countdown held 35 % high (HOLD) from the
# longer count of the noise stage (averaged_point) stayed there through a quiet run now that the model rule ends
# one in 1.1–1.6 periods from its first rising switch (docs/experiment.md, "Three periods, the model rule").
FALL = 0.1
# Where the estimate would still push the countdown up, by at most this share, the clock stops instead: a rise that
# small is the estimate's own scatter from switch to switch, and counting down again later costs less honesty than
# a countdown that goes up (the batch: never rising 51 → 87 % noise-free, 60 → 81 % at 1 %, within ±30 % 45 → 46 %
# and 52 → 51 %; docs/experiment.md "ite under a followed load"). A larger rise is news (a load found) and is shown.
PAUSE = 0.5


class Stage(str, Enum):
    """What the experiment is doing now."""

    NOISE = "noise"
    RELAY = "relay"
    DONE = "done"


@dataclass(frozen=True)
class Status:
    """Progress report: ``ite`` is the estimated seconds left while running, the code when done.

    stage: what the experiment is doing; progress: 0–1; relay: +1 high, −1 low, 0 before the relay;
    filter_phase_deg: the phase filter's lag at the cycle's frequency, degrees (negative: a lead);
    periods: whole periods so far; code, message: how it ended (None, "" while running).
    """

    stage: Stage
    progress: float
    ite: float
    relay: int
    filter_phase_deg: float
    periods: int
    code: Code | None
    message: str


class Progress:
    """The time-left estimate and the progress, which never goes backwards (``loop``, ``switching``,
    ``estimates``: the loop under test, the relay's switches and the estimates of the point; ``load``, ``held``:
    the load following and a followed load's held point, read only, None where there are none)."""

    def __init__(self, loop: Loop, switching: Switching, estimates: Estimates, load: LoadFollowing | None = None,
                 held: Held | None = None) -> None:
        self.loop = loop
        self.switching = switching
        self.estimates = estimates
        self.load = load
        self.held = held
        self._progress = 0.0
        self._shown: tuple[float, float] | None = None  # (elapsed s, ite s) of the latest status
        self._noisy = False  # the scatter gate (convergence.noisy) at the latest analysis (judge)

    def period_guess(self, dt: float | None, relaying: bool) -> float:
        """The oscillation period as well as it is known now (s), given the mean sample interval ``dt`` (s;
        None before two samples); ``relaying``: the relay has started.

        Before the first switch it is at least twice the time since the relay
        started (the first switch comes after a quarter to half a period).
        """
        time, switching = self.loop.record.time, self.switching
        if len(switching.rising) >= 2:
            return switching.period()
        if len(switching.switches) >= 2:
            return 2.0 * (time(switching.switches[-1]) - time(switching.switches[-2]))
        guess = self.configured_period(dt)
        if relaying:
            guess = max(guess, 2.0 * (time(-1) - time(switching.start)))
        return guess

    def configured_period(self, dt: float | None) -> float:
        """The period the configuration implies (s): the caller's ``expected_period``, else a share of the time
        limit, else ``SAMPLES_PER_PERIOD`` samples of the mean sample interval ``dt`` (s; None before two)."""
        c = self.loop.config
        if c.expected_period is not None:
            return c.expected_period
        if math.isfinite(c.time_limit):
            return c.time_limit / LIMIT_SHARE
        return SAMPLES_PER_PERIOD * (dt if dt else 1.0)

    def stall_tolerance(self, relaying: bool) -> float:
        """The longest time without a sample (s) that leaves the estimates usable (``relaying``: the relay has
        started): STALL of the period as well as it is known now, and at least GAP sample intervals."""
        dt = self.loop.mean_interval()
        return max(STALL * self.period_guess(dt, relaying), GAP * (dt or 0.0))

    def judge(self) -> None:
        """Judge the scatter gate (:func:`convergence.noisy`) for :meth:`longer`; the experiment calls it after each
        analysis, the only time the estimates change. (Not per status: status() runs per request, and the gate walks
        every period's σ.)"""
        self._noisy = convergence.noisy(self.loop, self.estimates)

    def longer(self, relaying: bool) -> bool:
        """True when the run will take a disturbed or noisy run's length (``relaying``: the relay has started): a
        followed load, or noise the scatter gate called noisy at the latest analysis (:meth:`judge`).

        Before the first estimate, from the second rising switch on: noise that scatters the first period's
        estimate beyond the gate (:func:`convergence.too_scattered`) at its swing and length as known now
        (:meth:`first_cycle`), judged at each status: the swing still grows after the switch that ends the first
        whole period (judged there, a 1 % noise passed for noisy until the next switch), and before that switch
        it is no measure (the first half period from rest of a lag-dominant process swings a third as much: a
        1 % noise passed for 3 %). The stopping rule does not read it.
        """
        if relaying and len(self.switching.rising) >= 2 and not self.estimates.items:
            return convergence.too_scattered(self.loop, self.estimates, *self.first_cycle())
        return self._noisy or (self.load is not None and self.load.fit is not None)

    def seconds_left(self, relaying: bool, phase_error_deg: float | None, fit: Fit = Fit.UNKNOWN,
                     until: float | None = None) -> float:
        """Estimated seconds to the end, never rising by more than its uncertainty (``relaying``: the relay has
        started; ``phase_error_deg``: how far the latest whole period's process lag is from the target, degrees,
        None before one; ``fit``: what the latest fit of the model rule says of the run's length, model_rule.py;
        ``until``: under noise, when the model rule expects to stop the run, s on the record's clock,
        model_rule.noisy_end).

        The raw estimate (:meth:`raw_seconds_left`) counts down between
        statuses as a clock would; it is followed where it falls below that,
        and where it rises the countdown is held instead as long as it stays
        within ``HOLD`` of it (a countdown that goes up is what operators
        complain about; one that lies low is worse); a rise beyond that of at
        most ``PAUSE`` of the shown value stops the clock instead.
        """
        raw = self.raw_seconds_left(relaying, phase_error_deg, fit, until)
        now = self.loop.elapsed()
        if self._shown is None:
            shown = raw
        else:
            countdown = self._shown[1] - (now - self._shown[0])
            shown = min(max(countdown, raw / (1.0 + HOLD)), raw * (1.0 + FALL))
            if self._shown[1] < shown <= (1.0 + PAUSE) * self._shown[1]:
                shown = self._shown[1]  # (a small rise: the clock stops instead)
        floor = self.loop.mean_interval() or raw
        shown = max(shown, min(floor, raw))
        self._shown = (now, shown)
        return shown

    def raw_seconds_left(self, relaying: bool, phase_error_deg: float | None, fit: Fit = Fit.UNKNOWN,
                         until: float | None = None) -> float:
        """The seconds left as the record says now (``relaying``: the relay has started; ``phase_error_deg``: the
        latest whole period's lag off the target, degrees, None before one; ``fit``, ``until``: as for
        :meth:`seconds_left`), a disturbed or noisy run's (:meth:`longer`) or a quiet one's.

        Where the model rule under noise expects to stop the run (``until``): the time to then, and at least
        ``LAST_SHARE`` of the latest period. Where the model rule may stop the run at the next switch (``fit`` NEXT): the time to that switch; once it
        has come and its analysis is pending (JUDGING), a sample interval. Before
        two whole periods, and while the model explains the record but the cycle has not reached the target:
        the noise stage's rest and ``TYPICAL_PERIODS`` (``CLEAN_TYPICAL_PERIODS`` by ``fit`` on a quiet run) of
        the prior period (:meth:`prior_period`) less the time the relay has run (from the first look's switch on a
        quiet run that has one): the first half periods of a lag-dominant process are 5–10 times shorter than its
        period, and the first whole period's lag carries the start's transient. From then on the periods left
        (:func:`periods_left`) of the latest whole period, less the time since it ended, and at least
        ``LAST_SHARE`` of it.
        """
        if until is not None:
            # (A cycle still slowing down brings the switch later than its latest period says.)
            left = max(until - self.loop.record.time(-1), LAST_SHARE * self.switching.period())
            return max(left, self.loop.mean_interval() or 0.0, 1e-9)
        if fit is Fit.NEXT:
            return self.switch_left()
        if fit is Fit.JUDGING:
            return max(self.loop.mean_interval() or 0.0, 1e-9)
        loop, switching = self.loop, self.switching
        c = loop.config
        dt = loop.mean_interval()
        time = loop.record.time
        rising = len(switching.rising)
        longer = self.longer(relaying)
        # (A run the model explains waits for the cycle to reach the target, not for estimates: its typical count.)
        if rising < 3 or phase_error_deg is None or fit is Fit.EXPLAINS and not longer:
            noise_left = max(c.noise_samples - len(loop.record), 0) * (dt or 0.0)
            prior = self.prior_period(dt, relaying)
            ran = time(-1) - time(switching.start) if relaying else 0.0
            # (A run the noisy rule likely stops is counted as its own, whatever the estimates' rules would take.)
            averaged = (longer or self.averaged_point(relaying)) and fit is not Fit.NOISY
            typical = TYPICAL_PERIODS[longer] if averaged else CLEAN_TYPICAL_PERIODS[fit]
            if not averaged and fit is not Fit.UNKNOWN:
                ran = time(-1) - time(switching.rising[0])  # (counted from the first look's switch)
            left = noise_left + max(typical * prior - ran, 0.5 * prior)
        else:
            period = switching.period()
            # (A period still growing, a lag-dominant process's cycle slowing down to the target, grows on: the
            # periods left count that in, QuietFit.growth_power.)
            ratio = period / (time(switching.rising[-2]) - time(switching.rising[-3]))
            # (Only a run the scatter gate calls noisy, with its hysteresis, waits for the averaged rule; one
            # labelled so for its load fit, or before its first estimate, does not.)
            scatter = estimate_scatter(loop, self.estimates) / c.noise_tol if self._noisy else 0.0
            averaged = self.averaged_point(relaying)
            left = periods_left(rising - 1, phase_error_deg, c.phase_tol_deg, ratio, longer, scatter, averaged)
            left = max(left, self.load_periods_left()) * period
            left -= time(-1) - time(switching.rising[-1])
            # The stop comes at a switch, and whether the next one stops the run is not known before it: at
            # least a share of the period stays left until it has.
            left = max(left, LAST_SHARE * period)
        left = min(left, period_cap(c.max_periods, switching, time) if rising >= 2 else left)
        if math.isfinite(c.time_limit):
            left = min(left, max(c.time_limit - loop.elapsed(), 0.0))
        return max(left, dt or 0.0, 1e-9)

    def switch_left(self) -> float:
        """The seconds to the next switch, the latest half period's length after the latest switch (at least a
        sample interval): where the model fitted at the latest switch explains the record (model_rule.py), the next
        switch's fit stops the run if it agrees, as it does wherever the model holds the process."""
        time, switches = self.loop.record.time, self.switching.switches
        half = time(switches[-1]) - time(switches[-2])
        return max(half - (time(-1) - time(switches[-1])), self.loop.mean_interval() or 0.0, 1e-9)

    def averaged_point(self, relaying: bool) -> bool:
        """True when the stopping rule's settled point will be the mean of the latest two estimates, which takes a
        quiet run longer: the noise scatters one estimate beyond ``stopping.MEAN_SCATTER`` of gain_tol (the
        latest estimate's, before one the first period's at the filtered error's swing so far and the prior
        period). ``relaying``: the relay has started; before, the noise is not measured yet and the longer count
        is taken (a countdown that falls when the relay starts on a quiet loop rather than one that rises)."""
        if not relaying:
            return True
        loop = self.loop
        if self.estimates.items:
            scatter = estimate_scatter(loop, self.estimates)
        else:
            scatter = convergence.swing_scatter(loop, self.estimates, *self.first_cycle())
        return scatter > MEAN_SCATTER * loop.config.gain_tol

    def first_cycle(self) -> tuple[float, float]:
        """Before an estimate, once the relay has started, the first whole period as known now: its swing, the
        filtered error's so far (PV units, standing for the PV's), and its length, the prior period (s,
        :meth:`prior_period`)."""
        return self.switching.peak_error, self.prior_period(self.loop.mean_interval(), True)

    def load_periods_left(self) -> float:
        """The periods from the latest rising switch that a followed (or a candidate) load still needs, 0 without
        one: what its stage waits for (the confirming fit, the estimates since the step, K0), counted as the
        field bench's disturbed runs needed it at the median."""
        load, held = self.load, self.held
        if load is None or held is None:
            return 0.0
        fit = load.fit
        if fit is None:
            return CANDIDATE_PERIODS if load.candidate is not None else 0.0
        if not load.corrects:
            since = max(load.discard_before, load.levels.changed_at, self.estimates.stalled_until)
            usable = len(self.estimates.usable(since))
            return max(UNCORRECTED_PERIODS - UNCORRECTED_ESTIMATE * usable, UNCORRECTED_MIN)
        if held.verdict is not None and not held.uncertain(fit, tolerances(self.loop.config)):
            return SURE_PERIODS
        fits = sum(1 for when, _ in held.gains if when > load.levels.changed_at)
        k0 = max(K0_PERIODS - LOAD_FIT_PERIODS * fits, float(FITS_AGREE))
        return k0 + (HOLD_PERIODS if held.verdict is None else 0.0)

    def prior_period(self, dt: float | None, relaying: bool) -> float:
        """The period expected before the estimates measure it (s), given the mean sample interval ``dt`` (s; None
        before two samples); ``relaying``: the relay has started. The configured one (:meth:`configured_period`),
        at least twice the relay's time until its first rising switch, twice the latest half period until the
        second, the latest whole period after."""
        time, switching = self.loop.record.time, self.switching
        guess = self.configured_period(dt)
        if len(switching.rising) >= 2:
            return max(guess, switching.period())
        if relaying and not switching.rising:
            # (The first rising switch comes after half a period at most.)
            guess = max(guess, 2.0 * (time(-1) - time(switching.start)))
        elif relaying:
            # (Between the first two rising switches: at least twice the latest half period. A configuration's
            # period implied by its time limit may be half the plant's, and the period measured at the second
            # rising switch raised ite by two periods: tests/test_handshake.)
            guess = max(guess, 2.0 * (time(switching.switches[-1]) - time(switching.switches[-2])))
        return guess

    def fraction(self, left: float) -> float:
        """Progress (0–1) with ``left`` seconds to go."""
        elapsed = self.loop.elapsed()
        # Progress never goes backwards, even when a measured period
        # turns out longer than the estimate before it.
        self._progress = max(self._progress, elapsed / (elapsed + left))
        return self._progress


def periods_left(done: int, phase_error_deg: float, phase_tol_deg: float, ratio: float, longer: bool,
                 scatter: float = 0.0, averaged: bool = True) -> float:
    """The periods the stopping rule still needs after ``done`` whole periods (from the first rising switch),
    the latest one's lag ``phase_error_deg`` off the target (degrees) with the tolerance ``phase_tol_deg``
    (degrees), the latest period ``ratio`` times the one before (1: unchanged); ``longer``: a noisy or disturbed
    run; ``scatter``: the latest estimate's expected scatter as a share of ``noise_tol`` (0 before one);
    ``averaged``: the settled point will be the mean of the latest two estimates (:meth:`Progress.averaged_point`).

    A quiet run's: the batch's median at the same errors (``AVERAGED_FIT``, ``CLEAN_FIT`` for one whose point is
    one estimate).
    A noisy one waits for the cycle's phase, which converges geometrically
    (``NOISY_CONVERGENCE``), for ``NOISY_MIN_DONE`` periods (the averaged
    rule's) and for the average of scattered estimates (``NOISY_PERIODS``).
    Calibrated on the batch (docs/experiment.md, "An honest ite", "ite after
    the shorter experiment", "ite after the model aim").
    """
    error = max(phase_error_deg, phase_tol_deg) / phase_tol_deg
    if longer:
        converging = math.log(error) / -math.log(NOISY_CONVERGENCE)
        averaging = NOISY_PERIODS * scatter ** SCATTER_POWER * error ** NOISY_PHASE_POWER
        # (Periods still growing grow on: counted as that many more of the latest. The averaging's fit counts
        # that in already.)
        return max(max(NOISY_MIN_DONE - done, NOISY_AFTER_CONVERGED + converging, 0.5) * max(ratio, 1.0), averaging)
    change = max(abs(ratio - 1.0), PERIOD_STEP) / PERIOD_STEP
    return (AVERAGED_FIT if averaged else CLEAN_FIT).periods(done, error, change, ratio)


def period_cap(max_periods: int, switching: Switching, time: Callable[[int], float]) -> float:
    """The seconds left until ``max_periods`` whole periods (``switching``: the relay's switches; ``time``: the
    record's sample times, s), at the latest period: the experiment ends there whatever the estimates say."""
    done = len(switching.rising) - 1
    return (max_periods - done) * switching.period() - (time(-1) - time(switching.rising[-1])) + 0.5 * switching.period()


def final_ite(code: Code | None) -> float:
    """``ite`` once the experiment is done: its ``code`` (0 without one)."""
    return float(code) if code is not None else 0.0
