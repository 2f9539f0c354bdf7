"""The identification experiment: relay with hysteresis behind an adaptive phase filter.

A sample-driven object that replaces the controller for the length of the
experiment (``step(t, pv) -> mv``; timestamps come from the caller, no clock,
no I/O). Stages:

1. ``noise``: hold the MV for a few samples to learn the operating point (the
   set point of the relay is the PV found here) and the measurement noise
   (loop.py); the hysteresis is 3 noise standard deviations unless given.
2. ``relay``: a relay of amplitude ``amp`` around the starting MV, biased by
   ``bias·amp`` so the oscillation carries a DC component that reveals the
   static gain (levels.py, switching.py). The control error passes through a
   first-order lag ``1/(τs + 1)`` before the relay; the lag adds
   ``θ = atan(ωτ)`` of phase so that the limit cycle settles where the
   *process* phase lag equals the requested value. ``θ`` is corrected once
   per period from the measured process phase (adaptation.py, methods.md §6),
   so the describing function's bias never enters.

The point ``F(jω)`` is the ratio of the Fourier coefficients of PV and MV over
the last whole period, and ``x = |F(jω)|/K0`` the ratio of their mean
deviations from the operating point over it (over the last two under noise);
on a quiet, noise-free run the point is taken without the share of the start's
transient a first-order model says it holds (estimates.py, transient.py). The
experiment stops when the estimates agree (convergence.py, stopping.py). Load
steps and drift are estimated through and followed (load_following.py,
load_correction.py); an open-loop unstable process is recognised (unstable.py)
and kept bounded (runaway.py). The ways it ends are in endings.py, the result in
identification.py, ``ite`` and the progress in progress.py.

This class only sequences those parts: each sample goes through :meth:`step`;
the analysis of a period that ended at a switch runs in :meth:`analyse`.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from autotuner.engine.experiment import convergence, endings, load_correction, model_rule, process_fit
from autotuner.engine.experiment.adaptation import Adaptation
from autotuner.engine.experiment.config import RelayConfig
from autotuner.engine.experiment.endings import Ended
from autotuner.engine.experiment.estimates import (GAP, Estimate, Estimates, alt_point, drift, lag, longest_gap,
                                                   mean_x, period_point, response, wide_x)
from autotuner.engine.experiment.identification import INTEGRATING_RATIO, Identification, identification
from autotuner.engine.experiment.levels import Levels, listed
from autotuner.engine.experiment.load_fit import LoadFit
from autotuner.engine.experiment.load_following import LOAD_FRACTION, LoadFollowing
from autotuner.engine.experiment.loop import Loop, cycle_noise
from autotuner.engine.experiment.point import Point
from autotuner.engine.experiment.process_fit import ProcessModel, Spread
from autotuner.engine.experiment.progress import Progress, Stage, Status, final_ite
from autotuner.engine.experiment.record import Record, Samples
from autotuner.engine.experiment.runaway import Runaway
from autotuner.engine.experiment.stopping import Verdict
from autotuner.engine.experiment.switching import Switching
from autotuner.engine.experiment.unstable import Unstable
from autotuner.engine.outcome import MESSAGES, Code

# The experiment's public names, wherever they are defined.
__all__ = ["Identification", "Point", "RelayConfig", "RelayExperiment", "Stage", "Status"]

# The filter is aimed by a process model fitted to the record at the first MODEL_PERIODS whole periods (a fit
# costs 2–3 ms); one that misfits the record by more than MODEL_MISFIT of the PV's swing is not used (the batch's
# higher orders misfit by 1.5–3.3 % and still aim better than the secant; the local minima that four slow two-lag
# processes' first fits settle in, by 7–13 %).
MODEL_PERIODS = 2
MODEL_MISFIT = 0.05

# While a load is followed on a quiet run, at most this many of the latest estimates are re-read with each new
# fit, until a point is held (the settled rule judges up to four estimates by the seventh period; each re-reading
# runs the model over the record three times).
REREAD = 4
# The noisy rule's search from the previous switch's load model stands where it misfits by at most this factor of
# that model's misfit (the noise's share of the swing, about the same at every switch): one search, not three.
ENOUGH = 1.05
# A quiet result's K0 stands against the load model's where the two are within this factor (_checked_x).
K0_AGREE = 2.0


class RelayExperiment:
    """Relay + adaptive phase filter identification of one frequency-response point."""

    def __init__(self, config: RelayConfig, mv0: float) -> None:
        """``config``: the settings; ``mv0``: the MV at the start (MV units), the relay's first centre."""
        if not math.isfinite(mv0):
            raise ValueError(f"starting MV must be finite, got {mv0}")
        self.config = config
        self.mv0 = mv0
        self.stage = Stage.NOISE
        self.code: Code | None = None
        self.message = ""
        self.result: Identification | None = None
        loop = self._loop = Loop(config, mv0, Record(), -1.0 if config.reverse else 1.0)
        levels = self._levels = Levels(config, mv0)
        switching = self._switching = Switching(loop)
        adaptation = self._adaptation = Adaptation(loop)
        estimates = self._estimates = Estimates()
        self._load = LoadFollowing(loop, switching, levels, estimates)
        self._held = load_correction.Held()  # a followed load's point, while K0 may still wait
        self._unstable = Unstable(loop, levels, adaptation, estimates, self._load)
        self._runaway = Runaway(loop, switching, levels)
        self._progress = Progress(loop, switching, estimates, self._load, self._held)
        # The switch whose period awaits its analysis, run after the switch is out (see analyse): 1 rising, −1
        # falling, 0 none. (A value, not the bound method: the experiment would hold itself, and each copy a
        # worker's analysis replaces would be left to the garbage collector's full walks.)
        self._pending = 0
        # The model rule's point at the latest switch (model_rule.py), None where its fit did not explain the record.
        self._model_point: model_rule.ModelPoint | None = None
        self._noisy = model_rule.NoisyFits()
        # The latest model fitted to the record (process_fit.py; the next fit's search starts from it), and the
        # latest with a load at the process input (process_fit.fit_load), None where the plain one explained it.
        self._model: ProcessModel | None = None
        self._loaded: ProcessModel | None = None
        # What the latest fit says of the run's length (ite's, progress.py).
        self._fit_hint = model_rule.Fit.UNKNOWN
        if levels.high <= mv0 or levels.low >= mv0:
            self._end(endings.mv_range(mv0, levels.low, levels.high, config.amp, config.mv_limits))

    # -- public interface -------------------------------------------------

    @property
    def levels(self) -> tuple[float, ...]:
        """Every MV level the relay can hold between switches, ascending, MV units (within the MV limits).

        With its centre at ``mv0``: the high level ``mv0 + amp`` and the low
        ones — the first half period's weak level (levels.FIRST_LOW), the
        biased one ``mv0 − amp·(1 − 2·bias)``, an unstable process's (bias
        levels.UNSTABLE_BIAS) and the full ``amp`` of a rescue (runaway.py).
        A crash recovery reads an MV at any of them as the experiment's, not an
        operator's. A relay that follows a load (``follow_loads``) shifts its
        centre within ±amp and may flip its bias; those levels are not listed.
        """
        return listed(self.config, self.mv0)

    @property
    def done(self) -> bool:
        """True once the experiment has ended (successfully or not)."""
        return self.stage is Stage.DONE

    def abort(self) -> None:
        """TBRK: end the experiment now; the caller restores the loop."""
        self.fail(Code.ABORTED, MESSAGES[Code.ABORTED])

    def fail(self, code: Code, message: str) -> None:
        """End the experiment with ``code`` and ``message``: an error found outside it (e.g. a link fault)."""
        if not self.done:
            self._end(Ended(code, message))

    def step(self, t: float, pv: float) -> float:
        """Take the PV ``pv`` sampled at time ``t`` (seconds) and return the MV to hold until the next sample."""
        if self.done:
            return self.mv0
        try:
            return self._step(t, pv)
        except Ended as ended:
            self._end(ended)
            return self.mv0

    @property
    def analysis_pending(self) -> bool:
        """True when a period ended at the last sample and :meth:`analyse` has not run yet."""
        return self._pending != 0 and not self.done

    def analyse(self) -> None:
        """Analyse the period that ended at the last sample's switch: its estimates, the stopping rule, the load fit.

        The switch itself is in the MV the last :meth:`step` returned: a full
        load fit takes milliseconds of CPU, and a switch waiting for it would
        reach the process that much late. :meth:`step` runs it at the next
        sample if the caller has not; a field session runs it after its write,
        in a worker thread, so that its event loop (other loops, the handshake)
        keeps time meanwhile. Nothing to do otherwise. Its work is bounded,
        whatever the record's length (docs/experiment.md, "The analysis's cost
        per period").
        """
        switched, self._pending = self._pending, 0
        if switched and not self.done:
            try:
                self._on_period() if switched > 0 else self._on_half()
                self._progress.judge()
            except Ended as ended:
                self._end(ended)

    def applied(self, t: float) -> None:
        """The MV returned by the last :meth:`step` reached the process at ``t`` (seconds, the caller's clock).

        A field session calls it after each write: a write that a busy link or
        a stalled session delayed left the previous MV on the process longer
        than the sample times say, and the estimates (the point's MV
        coefficient, the static ratio, the load fit) integrate the MV as the
        process really held it. Without a call the MV counts from its
        sample's time. A time before that sample (clocks that disagree) is
        taken as the sample's.
        """
        record = self._loop.record
        if record.held and record.held == len(record) and math.isfinite(t):
            record.applied(t)

    @property
    def stall_tolerance(self) -> float:
        """The longest time without a sample (s) that leaves the estimates usable: a tenth of the period as well
        as it is known now, and at least three sample intervals (a longer stall leaves its estimates out)."""
        return self._progress.stall_tolerance(self.stage is Stage.RELAY)

    def status(self) -> Status:
        """Stage, progress (0–1), ite and the live relay/filter state."""
        if self.done:
            ite, progress = final_ite(self.code), 1.0
        else:
            lags = self._adaptation.lags
            error = abs(math.degrees(lags[-1]) - self._adaptation.target_deg) if lags else None
            fit = self._fit_hint
            if fit is model_rule.Fit.NEXT and self._pending:
                # (A status between that switch and its analysis — a field session's, whose analysis runs in a
                # worker after the write — read a whole half period more.)
                fit = model_rule.Fit.JUDGING
            ite = self._progress.seconds_left(self.stage is Stage.RELAY, error, fit, self._noisy.end)
            progress = self._progress.fraction(ite)
        return Status(stage=self.stage, progress=progress, ite=ite, relay=self._switching.relay,
                      filter_phase_deg=self._adaptation.phase_deg(), periods=max(self._switching.periods, 0),
                      code=self.code, message=self.message)

    # -- each sample ------------------------------------------------------

    def _step(self, t: float, pv: float) -> float:
        if not (math.isfinite(t) and math.isfinite(pv)):
            raise Ended(Code.BAD_SAMPLE, f"non-finite sample: t={t}, pv={pv}")
        record = self._loop.record
        if len(record) and t <= record.time(-1):
            raise Ended(Code.BAD_SAMPLE, f"timestamp {t} s does not follow {record.time(-1)} s")
        lo, hi = self.config.pv_limits
        if not lo <= pv <= hi:
            raise Ended(Code.PV_OUT_OF_LIMITS, f"PV {pv:g} left the limits [{lo:g}, {hi:g}]")
        self.analyse()
        if self.done:
            return self.mv0
        record.add(t, pv)
        if t - record.time(0) > self.config.time_limit:
            if len(self._switching.switches) < 3:
                raise Ended(Code.NO_OSCILLATION, endings.NO_OSCILLATION_IN_TIME)
            raise self._unfinished("within the time limit")
        if self.stage is Stage.NOISE:
            if len(record) < self.config.noise_samples:
                record.hold(self.mv0)
                return self.mv0
            self._start_relay()
        mv = self._relay_step(t, pv)
        step = self.config.mv_rate * (t - record.time(-2))
        mv = min(max(mv, record.mv(-1) - step), record.mv(-1) + step)
        record.hold(mv)
        return mv

    def _start_relay(self) -> None:
        self._loop.measure_noise()
        self._adaptation.begin()
        self.stage = Stage.RELAY
        self._switching.begin()

    def _relay_step(self, t: float, pv: float) -> float:
        """The relay's MV for the PV ``pv`` sampled at ``t`` (s)."""
        loop, switching, levels, adaptation = self._loop, self._switching, self._levels, self._adaptation
        dt = t - loop.record.time(-2)
        old = levels.mv(switching.relay, t)
        switched = switching.step(loop.sign * (loop.sp - pv), dt, adaptation.filter, adaptation.hysteresis)
        if switched:
            levels.end_rescue()
            # (The period's end is judged once it is analysed.)
            self._pending = switched
        else:
            when = switching.watch(adaptation.hysteresis)
            if when is not None:
                raise self._unfinished(when)
        if self._runaway.check(adaptation.lags):
            # An unstable process the level cannot hold: the full amp at once, a weaker bias from the next
            # switch on, and no filter lag (the requested phase may be out of reach).
            levels.strengthen(switching.relay)
            self._unstable.enter()
            adaptation.drop_lag()
            return levels.mv(switching.relay, t)
        if not switched:
            return old
        return switching.blend(old, levels.mv(switching.relay, t), dt)

    # -- each period ------------------------------------------------------

    def _on_period(self) -> None:
        """A rising switch ended a whole period: estimate, judge, adapt the filter, look for loads."""
        self._levels.end_first_low()
        switching = self._switching
        if len(switching.rising) == 1:
            self._start_filter()
            return
        self._corrects()  # (tells the load following whether its share is taken out of the estimates)
        raw, detrended = self._period_samples()
        ta, tb = switching.crossings[-2], switching.crossings[-1]
        omega = 2.0 * math.pi / (tb - ta)
        value = response(self._loop, raw, ta, tb, omega, hann=False)
        period_lag = lag(value)
        self._adaptation.lags.append(period_lag)
        if len(self._adaptation.lags) == 1 and not self._loop.settling[0]:
            # (A PV still settling at TUNE makes any process's first |F|/K0 negative: the load fit judges it.)
            self._unstable.suspect(mean_x(self._loop, raw, ta, tb, abs(value)), omega)
        self._unstable.recognise(self._since())
        model, explaining = self._fit_record(aim=True)
        self._by_model(explaining)
        self._by_noisy_model(model)
        aims = model is not None and model.misfit <= MODEL_MISFIT and len(self._adaptation.lags) <= MODEL_PERIODS
        self._adapt(ta, omega, period_lag, model if aims else None)
        if len(switching.rising) >= 3:
            self._judge(raw, detrended)
        if self._load.fit is None and self._load.due():
            # Quiet so far: look for a disturbance while the estimates have not settled.
            if self._load.look(self._unstable.unstable) and self._load.fit is not None and self._corrects():
                self._accept(self._verdict())

    def _start_filter(self) -> None:
        """First rising switch: only half a period is known. Start the filter at the describing-function guess."""
        switching, time = self._switching, self._loop.record.time
        half = time(switching.rising[0]) - time(switching.switches[-2])
        if self._unstable.slow_return(half, switching.react):
            self._unstable.enter()  # as after a rescue, until the estimates say otherwise
        self._adaptation.start(half, switching.peak_error, self._unstable.unstable)
        self._fit_hint = self._first_look()

    def _first_look(self) -> model_rule.Fit:
        """ite's first look, at the first rising switch: whether the model rule is likely to stop the run at its first
        chances (model_rule.first_look), under noise the noisy rule (model_rule.noisy_look)."""
        loop, tol = self._loop, convergence.tolerances(self.config)
        record = loop.record.all()
        if self._unstable.unstable or not self._noisy_record(record):
            model = self._fit_record(aim=False)[0]
            return model_rule.first_look(model, tol, self._noise_share(model))
        # (Half a period known: its length twice over is the fit's scale.)
        period = 2.0 * (record.t[-1] - loop.record.time(self._switching.switches[-2]))
        noise = self._record_noise(record)
        model = process_fit.fit(record, loop.mv0, period, noise)
        lag = math.radians(self._adaptation.target_deg)
        spread = None if model is None else process_fit.spread(record, loop.mv0, period, model, lag)
        return model_rule.noisy_look(spread, noise, float(np.ptp(record.y)))

    def _noisy_record(self, record: Samples) -> bool:
        """True when the noisy rule judges the ``record``: its noise keeps the quiet rule out (model_rule.could_explain)
        and the noise stage measured it too. (A daemon's sampling whose time stamps are not the PV's instants reads
        as noise of the cycle's slope times the spread, which the stage's flat PV does not show: not white noise
        on the PV, it left the demo's TIC-101 K0 7 % off, its set-point step 8 % slower than the test allows, one
        run in three — tests/test_handshake.py.)"""
        loop, tol, swing = self._loop, convergence.tolerances(self.config), float(np.ptp(record.y))
        return not (model_rule.could_explain(convergence.sigma(loop, self._estimates), swing, tol)
                    or model_rule.could_explain(loop.noise, swing, tol))

    def _record_noise(self, record: Samples) -> float:
        """The measurement noise's σ (PV units) the fits of the whole ``record`` are judged by: the stopping rule's
        (convergence.sigma) or the record's own (loop.cycle_noise), the larger — the noise stage's few samples may
        read low (0.57 of the true σ on the bench's seed), and an inverse response is judged against it
        (process_fit.inverse_response)."""
        return max(convergence.sigma(self._loop, self._estimates), cycle_noise(record.t, record.y))

    def _noise_share(self, model: ProcessModel | None) -> float:
        """The record's measurement noise as the ``model`` fitted at this switch meets it, over the PV's swing
        (dimensionless; inf without a model or a swing: nothing to judge): the larger of the noise stage's σ and
        the relay's samples' so far (loop.cycle_noise, PV units). A sampling whose time stamps are not the PV's
        times, a simulated PLC's, reads there as noise of the cycle's slope times the spread; the noise stage's
        flat PV does not show it."""
        if model is None:
            return math.inf
        loop = self._loop
        record = loop.record.all()
        swing = float(np.ptp(record.y))
        relay = loop.record.since(loop.record.time(self._switching.start))
        sigma = max(loop.noise, cycle_noise(relay.t, relay.y))
        return sigma / swing if swing > 0.0 else math.inf

    def _period_samples(self) -> tuple[Samples, Samples]:
        """The samples of this period's estimates as recorded and with the PV's drift removed (refitting a
        followed load first)."""
        # From the third latest crossing on (the drift and the two-period means start there). (The switch's
        # own MV, recorded already, holds from this sample on: after every window.)
        crossings = self._switching.crossings
        raw = self._loop.record.since(crossings[max(len(crossings) - 3, 0)])
        if self._load.fit is not None:
            # Disturbed: refit with this period (static gain, the relay's centre). The point is estimated from
            # the PV as measured over windows after the load step only: subtracting the fitted load response
            # would make the point hostage to the fit, which a hiccup of the link can mislead.
            self._load.refit(self._unstable.unstable)
            if self._levels.follow_rate and len(crossings) >= 3:
                # The MV follows a drift: its ramp is slow too, not part of the oscillation.
                raw = replace(raw, u=raw.u - drift(raw.s, raw.u, crossings[-3:]))
        if len(crossings) < 3:
            return raw, raw
        return raw, replace(raw, y=raw.y - drift(raw.t, raw.y, crossings[-3:]))

    def _adapt(self, ta: float, omega: float, period_lag: float, model: ProcessModel | None) -> None:
        """Correct the filter from the period that started at ``ta`` (s), unless it was a transient: aimed from the
        ``model`` fitted to the record where there is one (:meth:`_fit_record`), else by the secant."""
        changed_at = self._levels.changed_at
        # (A change of the levels made just now, at the end of the period, leaves the period clean.)
        clean = ta >= changed_at or changed_at >= self._loop.record.time(-1)
        # Nor, on a process that is or may be unstable, before an estimate has said which phase it reaches.
        if clean and not (self._unstable.unstable and not self._unstable.aimed):
            levels = self._levels
            if model is None or not self._adaptation.aim_from(model, omega, period_lag, levels.high - levels.center,
                                                              levels.low - levels.center):
                self._adaptation.adapt(omega, period_lag)

    def _fit_record(self, aim: bool) -> tuple[ProcessModel | None, ProcessModel | None]:
        """Models of the process fitted to the whole record at this switch (process_fit.py), on a quiet run with
        the relay's levels as they started, when the filter's aim wants one (``aim``: a rising switch of the first
        MODEL_PERIODS whole periods, the relay's levels as they started) or the model rule does (model_rule.py:
        from the first rising switch, ite's first look, to model_rule.PERIODS whole periods, noise low enough for
        its misfit); None elsewhere (under noise, a load followed, a process that is or may be unstable, an inverse
        response, a gain of the wrong sign). The first is the plain model (the aim's and ite's first look's, with the
        levels as they started only), the second the rule's (:meth:`_explaining`)."""
        loop, switching, levels, estimates = self._loop, self._switching, self._levels, self._estimates
        if self._load.fit is not None or self._unstable.unstable or not switching.rising:
            return None, None
        # The aim wants the relay's levels as they started; the rule's fit takes the MV as held, whatever its levels
        # (a relay strengthened while a drift looked like an unstable process's runaway: runaway.py).
        started = levels.center == loop.mv0 and levels.changed_at == -math.inf
        aim = aim and started
        if not switching.periods and switching.switches[-1] != switching.rising[0]:
            return None, None  # (before a whole period, only the first rising switch: ite's first look)
        record, tol = loop.record.all(), convergence.tolerances(self.config)
        # (A stall of the session leaves the rule out, as it leaves the estimates over it out: estimates.STALL.)
        # (Worth it while the plain model or, where that misfits, the load's may explain the record: no load fit
        # yet, as when the noise gate kept the rule out of the first switches, lets it try one.)
        worth = model_rule.worth_fitting(self._model, tol) or model_rule.worth_fitting(self._loaded, tol)
        rule = (switching.periods <= model_rule.PERIODS and worth
                and model_rule.could_explain(convergence.sigma(loop, estimates), float(np.ptp(record.y)), tol)
                and longest_gap(record.t, record.t[0], record.t[-1]) <= GAP * loop.dt)
        if not (rule or aim and len(self._adaptation.lags) <= MODEL_PERIODS):
            return None, None
        time = loop.record.time
        # (At the first rising switch only half a period is known.)
        period = (switching.period() if switching.periods
                  else 2.0 * (time(switching.rising[0]) - time(switching.switches[-2])))
        if convergence.too_scattered(loop, estimates, switching.peak_error, period):
            return None, None
        earlier = self._model
        model = self._model = process_fit.fit(record, loop.mv0, period, loop.noise, earlier)
        if model is None or loop.sign * model.k0 <= 0.0:
            return None, None
        return model if started else None, self._explaining(model, earlier, record, period) if rule else model

    def _explaining(self, model: ProcessModel, earlier: ProcessModel | None, record: Samples,
                    period: float) -> ProcessModel:
        """The plain ``model`` fitted to the ``record`` (``period``: the fit's scale, s), unless it misfits beyond the
        model rule's bound and the fit with a load at the process input (process_fit.fit_load, from the latest load
        fit or the ``earlier`` plain one) explains the record within it. (A load fit that does not, e.g. on three
        lags, tells ite nothing the plain one does not.)"""
        bound = model_rule.bound(convergence.tolerances(self.config))
        if model.misfit <= bound:
            self._loaded = None
            return model
        start = self._loaded if self._loaded is not None else earlier
        loaded = self._loaded = process_fit.fit_load(record, self._loop.mv0, period, model, bound, start)
        return loaded if loaded is not None and loaded.misfit <= bound and self._loop.sign * loaded.k0 > 0.0 else model

    def _by_model(self, model: ProcessModel | None) -> None:
        """The model rule (model_rule.py) on the ``model`` fitted at this switch and the previous switch's: stop with
        the model's point when both explain the record and agree (a load the latest explained reported)."""
        tol = convergence.tolerances(self.config)
        latest = model_rule.model_point(model, self._loop.sign, self._adaptation.target_deg, tol)
        previous, self._model_point = self._model_point, latest
        period = self._switching.period()
        self._fit_hint = model_rule.hint(model, latest, period, tol, self._noise_share(model), self._fit_hint)
        load = model.load_at(self._loop.record.time(-1)) if model is not None and model.loaded else None
        self._accept(model_rule.judge(previous, latest, period, tol), explained=True, load=load)

    def _by_noisy_model(self, plain: ProcessModel | None) -> None:
        """The model rule under noise (model_rule.noisy_point), at a rising switch, on the model fitted to the whole
        record (:meth:`_noisy_fit`; ``plain``: the filter's aim's fit at this switch, None where it made none): its
        point accepted when it is known within the noise tolerance and the previous switch's agrees. Not where the
        quiet rule's misfit judges, nor on a process that is or may be unstable, nor over a stall, nor after
        NOISY_PERIODS. Its fits are its own (``_noisy``): the quiet rule's, where it judges later, are as without it."""
        loop, switching, tol, noisy = self._loop, self._switching, convergence.tolerances(self.config), self._noisy
        record = loop.record.all()
        if (self._unstable.unstable or switching.periods > model_rule.NOISY_PERIODS or not self._noisy_record(record)
                or longest_gap(record.t, record.t[0], record.t[-1]) > GAP * loop.dt):
            noisy.point = noisy.end = None
            return
        period = switching.period()
        model, spread = self._noisy_fit(record, self._record_noise(record), period, plain)
        latest = model_rule.noisy_point(model, spread, loop.sign, self._adaptation.target_deg)
        previous, noisy.point = noisy.point, latest
        now = record.t[-1]
        noisy.end = model_rule.noisy_end(previous, latest, now, now - loop.record.time(switching.start), period,
                                         switching.periods, tol)
        load = model.load_at(now) if model is not None and model.loaded else None
        self._accept(model_rule.judge_noisy(previous, latest, period, tol), explained=True, load=load)

    def _noisy_fit(self, record: Samples, noise: float, period: float,
                   plain: ProcessModel | None) -> tuple[ProcessModel | None, Spread | None]:
        """The noisy rule's model of the ``record`` (``noise``: its σ, PV units, the whole record's where the noise
        stage's few samples read low; ``period``: the fit's scale, s) and its spread (process_fit.spread): the plain
        model (``plain`` where given, else fitted from the previous switch's), or where its residual is not the
        noise (model_rule.white), the one with a load at the process input."""
        loop, noisy, lag = self._loop, self._noisy, math.radians(self._adaptation.target_deg)
        if plain is None:
            earlier = noisy.plain
            enough = ENOUGH * earlier.misfit if earlier is not None else process_fit.WARM
            plain = process_fit.fit(record, loop.mv0, period, noise, earlier, enough)
        noisy.plain = plain
        spread = None if plain is None else process_fit.spread(record, loop.mv0, period, plain, lag)
        if plain is None or model_rule.white(spread):
            return plain, spread
        earlier = noisy.loaded
        # (Where the previous switch's load model did not explain the record either, the model is likely not of
        # the process's family: one search from it, not three, 8-16 ms each on three lags.)
        enough = (ENOUGH * earlier.misfit if noisy.loaded_white else math.inf) if earlier is not None else 0.0
        model = noisy.loaded = process_fit.fit_load(record, loop.mv0, period, plain, enough, earlier)
        spread = None if model is None else process_fit.spread(record, loop.mv0, period, model, lag)
        noisy.loaded_white = model_rule.white(spread)
        return model, spread

    def _judge(self, raw: Samples, detrended: Samples) -> None:
        """Estimate the point over the last period and stop if it has converged."""
        loop, crossings, fit = self._loop, self._switching.crossings, self._load.fit
        bounds = crossings[-3:]
        period = raw.t >= bounds[-2]
        noise = cycle_noise(raw.t[period], raw.y[period])
        # (Judged with this period's σ and the latest estimate's swing and length.)
        noisy = convergence.noisy(loop, self._estimates, noise)
        point, x = period_point(loop, raw, detrended.y, bounds, None if fit is None else fit.x, noisy)
        wide = wide_x(loop, detrended, bounds) if fit is None else x
        quiet = fit is None and not noisy
        alt = alt_point(loop, raw, detrended.y, bounds, (point, x)) if quiet else None
        gap = longest_gap(raw.t, bounds[0], bounds[-1])
        self._estimates.add(Estimate(point, x, wide, *bounds, alt, noise), gap, loop.dt)
        self._accept(self._verdict())

    def _verdict(self) -> Verdict | None:
        """The stopping rule's verdict on the estimates now (those since a followed load's step re-read with its
        latest fit first, on a quiet run: load_correction.py)."""
        fit, corrects = self._load.fit, self._corrects()
        if fit is None or not corrects:
            return convergence.at_rising(self._loop, self._estimates, self._switching.periods, self._since(),
                                         self._adaptation.target_deg, None if fit is None else fit.x_std)
        held, now = self._held, self._loop.record.time(-1)
        step = max(self._load.discard_before, self._estimates.stalled_until)
        verdict, oldest = None, math.inf
        if held.verdict is None or held.oldest < step:
            # (A held point needs no more estimates: only K0 is awaited.)
            self._reread(fit)
            verdict = convergence.at_rising(self._loop, self._estimates, self._switching.periods, self._since(),
                                            self._adaptation.target_deg, fit.x_std, corrected=True)
            if verdict is not None:
                oldest = self._estimates.usable(self._since())[-verdict.count].start
        if not held.gains and self._load.confirmed is not None:
            # (The confirming candidate came a period before, with the same levels.)
            held.gains.append((math.nextafter(now, -math.inf), self._load.confirmed.static_gain))
        held.update(verdict, oldest, step, fit, now)
        self._load.point = None if held.verdict is None else held.verdict.point
        changed, tol = self._levels.changed_at, convergence.tolerances(self.config)
        if held.verdict is not None and held.uncertain(fit, tol):
            self._load.excite()  # the point stands; K0 is not sure yet: a change of the MV's mean excites it
        return held.result(fit, tol, -math.inf if changed >= now else changed)

    def _corrects(self) -> bool:
        """True when a followed load's estimates shed its share through the model (load_correction.py): a quiet run
        (its noise far below the scatter gate in every period: convergence.far_below) of a process that is not
        open-loop unstable (whose model would run away)."""
        self._load.quiet = not self._unstable.unstable and convergence.far_below(self._loop, self._estimates)
        return self._load.corrects

    def _reread(self, fit: LoadFit) -> None:
        """Re-read the latest estimates since the load step (at most REREAD) with the followed ``fit``."""
        items = self._estimates.items
        since = max(self._load.discard_before, self._estimates.stalled_until)
        load = load_correction.loads(self._loop, fit)
        follows = bool(self._levels.follow_rate)
        for i in range(len(items) - 1, max(len(items) - REREAD, 0) - 1, -1):
            if items[i].start < since:
                break
            items[i] = load_correction.reread(self._loop, items[i], fit, load, follows)

    def _on_half(self) -> None:
        """A falling switch: a quiet run may stop half a period sooner."""
        if self._load.fit is None:
            if self._switching.periods > 0:
                self._by_model(self._fit_record(aim=False)[1])
            self._accept(convergence.at_falling(self._loop, self._switching, self._estimates, self._since(),
                                                self._adaptation.target_deg))

    def _accept(self, verdict: Verdict | None, explained: bool = False, load: float | None = None) -> None:
        """End the experiment with the ``verdict`` (nothing without one), unless the record holds a load: a quiet
        result is first looked through for one (load_following.py), but not where a model ``explained`` the whole
        record (model_rule.py: a load it did not fit would misfit it; ``load``: the one it fitted at the process
        input at the end, MV units, None where it fitted none)."""
        if verdict is None:
            return
        # Before accepting a quiet result, make sure the record holds no
        # disturbance that the simple means would have mixed in.
        if not explained and self._load.fit is None and self._load.look(self._unstable.unstable):
            if self._load.fit is not None and self._corrects():
                # Just accepted: the estimates since its step may pass as they are, its share taken out.
                self._accept(self._verdict())
            return
        fit = self._load.fit
        # (Where the load's share was taken out, the verdict's |F|/K0 is the fit's K0 at the verdict's |F|.)
        x = fit.x if fit is not None and not self._load.corrects and not explained else verdict.x
        if not explained and fit is None and load is None:
            x, load = self._checked_x(verdict.point, x)
        self.result = identification(self._loop, verdict.point, x, fit,
                                     self._estimates.discarded(self._load.discard_before),
                                     self._adaptation.hysteresis, self._adaptation.target_deg)
        if load is not None:
            self.result = replace(self.result, disturbance=True, load_estimate=load)
        raise Ended(Code.OK, MESSAGES[Code.OK])

    def _checked_x(self, point: Point, x: float) -> tuple[float, float | None]:
        """The quiet estimates' |F|/K0 ``x`` at the accepted ``point``, checked against the process model with a load
        at the process input fitted to the whole record (process_fit.fit_load): where that model finds a load of at
        least LOAD_FRACTION of amp and a K0 more than K0_AGREE times apart (or of the other sign), and explains the
        record within MODEL_MISFIT, the model's x and its load at the end (MV units), else ``x`` and None.

        A load step with the relay's bias before the first estimate leaves the estimates' mean MV and PV off from
        the start and the load following's fit finds nothing: on three lags and more (which the model fits within
        1–4 % of the swing, its K0 within 15 %) seven of 180 such runs ended "ok" with K0 −1.7 or 3.9–13.6, the
        true 1, and no disturbance reported."""
        loop = self._loop
        record = loop.record.all()
        # (Nor on an integrator as the estimates read it, whose K0 the model cannot tell from a very slow lag's, nor
        # on a resonance, |F| above K0, which lags and a dead time never reach: the load term invents a load there.)
        integrating = x * INTEGRATING_RATIO <= 1.0 and x > -loop.config.static_tol
        if self._unstable.unstable or integrating or x >= 1.0 or not self._switching.periods:
            return x, None
        period = self._switching.period()
        plain = process_fit.fit(record, loop.mv0, period, self._record_noise(record))
        loaded = None if plain is None else process_fit.fit_load(record, loop.mv0, period, plain, 0.0)
        if loaded is None or loop.sign * loaded.k0 <= 0.0 or loaded.misfit > MODEL_MISFIT:
            return x, None
        load = loaded.load_at(record.t[-1])
        model_x = point.gain / (loop.sign * loaded.k0)
        if abs(load) < LOAD_FRACTION * loop.config.amp or (x > 0.0 and 1.0 / K0_AGREE <= model_x / x <= K0_AGREE):
            return x, None
        return model_x, load

    # -- endings ----------------------------------------------------------

    def _since(self) -> float:
        """Estimates whose window starts before this time (s) are not used: a load step, a change of the relay's
        levels or a stall came after them. (Where a followed load's share is taken out, load_correction.py, a
        change made just now, after every window, is none: the load's acceptance may judge them at once.)"""
        changed = self._levels.changed_at
        if changed >= self._loop.record.time(-1) and self._corrects():
            changed = -math.inf
        return max(self._load.discard_before, changed, self._estimates.stalled_until)

    def _unfinished(self, when: str) -> Ended:
        """The ending of an experiment whose estimates did not settle ``when``."""
        return convergence.unsettled(when, self._loop, self._estimates, self._since(), self._load.fit,
                                     self._adaptation.target_deg)

    def _end(self, ended: Ended) -> None:
        self.stage = Stage.DONE
        self.code = ended.code
        self.message = ended.message
