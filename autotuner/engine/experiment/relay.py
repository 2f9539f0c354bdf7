"""The identification experiment: relay with hysteresis behind an adaptive phase filter.

A sample-driven object that replaces the controller for the length of the
experiment (``step(t, pv) -> mv``; timestamps come from the caller, no clock,
no I/O). Stages:

1. ``noise``: hold the MV for a few samples to learn the operating point (the
   set point of the relay is the PV found here) and the measurement noise;
   the hysteresis is 3 noise standard deviations unless given.
2. ``relay``: a relay of amplitude ``amp`` around the starting MV, biased by
   ``bias·amp`` so the oscillation carries a DC component that reveals the
   static gain. The control error passes through a first-order lag
   ``1/(τs + 1)`` before the relay; the lag adds ``θ = atan(ωτ)`` of phase so
   that the limit cycle settles where the *process* phase lag equals the
   requested value. ``θ`` is corrected once per period from the measured
   process phase (methods.md §6), so the describing function's bias never
   enters.

The point ``F(jω)`` is the ratio of the Fourier coefficients of PV and MV over
the last whole period (between two rising crossings, so the window holds
exactly one period of the cycle; the MV integrated exactly as a held signal),
and the static gain the ratio of their mean deviations from the operating
point (the MV's mean as the process's slow lag has passed it on,
load_fit.settled_ratio). The experiment stops when the phase is within
tolerance and consecutive estimates agree (or, when noise makes them
scatter, when the mean of more of them is settled); on a quiet run a
period between falling crossings that agrees with the latest within a
third of the tolerances stops it half a period sooner.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from enum import Enum

import numpy as np

from autotuner.engine.described import described as _d
from autotuner.engine.outcome import MESSAGES, Code
from autotuner.engine.experiment.fourier import held_coefficient, sampled_coefficient
from autotuner.engine.experiment.load_fit import LoadFit, LoadFitter, settled_ratio
from autotuner.engine.experiment.point import Point
from autotuner.engine.experiment.record import Record, Samples
from autotuner.engine.experiment.stopping import Tolerances, Verdict, amp_factor, judge, slow_memory
from autotuner.engine.experiment.phase_filter import PhaseFilter


class Stage(str, Enum):
    """What the experiment is doing now."""

    NOISE = "noise"
    RELAY = "relay"
    DONE = "done"


@dataclass(frozen=True)
class RelayConfig:
    """Settings of one experiment.

    amp: largest change of the MV from its starting value (MV units, > 0).
    phase_deg: requested process phase lag at the identified point, degrees (90–170).
    hysteresis: relay hysteresis in PV units; ``None`` measures the noise first.
    bias: asymmetry of the relay as a fraction of ``amp`` (0 ≤ bias < 0.5); the
        MV alternates between ``mv0 + amp`` and ``mv0 − amp·(1 − 2·bias)``.
    reverse: reverse-acting loop (more MV gives less PV).
    pv_limits, mv_limits: safety range of the PV and allowed range of the MV.
    mv_rate: largest rate of change of the MV, MV units per second (the relay
        then ramps between its levels; the estimate uses the MV as applied).
    time_limit: longest experiment, seconds.
    noise_samples: samples of the noise-measuring stage.
    max_periods: give up after this many oscillation periods.
    phase_tol_deg: accepted error of the phase, degrees.
    gain_tol: accepted relative change of the point between consecutive estimates.
    static_tol: accepted change of ``|F(jω)|/K0`` between consecutive estimates
        (measured this way, the tolerance on the static gain stays meaningful as
        ``K0`` grows towards an integrator).
    noise_tol: with measurement noise, the accepted standard error of the mean
        |F(jω)| (relative) over several periods (stopping.py); the experiment
        refuses with NOISE_TOO_HIGH when it is out of reach by ``max_periods``.
    expected_period: the oscillation period expected, seconds (only for the
        time-left estimate ``ite`` before the period is measured; None: a
        share of the time limit).
    follow_loads: look for load steps and drift in the record (load_fit.py),
        estimate the static gain through them and let the relay's centre
        follow them within ±amp; off, the experiment is the plain one (which
        takes a load's response for the relay's and reports a wrong static
        gain). A session whose writes can be late (a link, a busy machine)
        tells the experiment when each MV arrived (:meth:`RelayExperiment.applied`):
        a stall recorded as if the MV had arrived on time is what a load step
        looks like to the fit.
    """

    amp: float
    phase_deg: float = 135.0
    hysteresis: float | None = None
    bias: float = 0.2
    reverse: bool = False
    pv_limits: tuple[float, float] = (-math.inf, math.inf)
    mv_limits: tuple[float, float] = (-math.inf, math.inf)
    mv_rate: float = math.inf
    time_limit: float = math.inf
    noise_samples: int = 20
    max_periods: int = 25
    phase_tol_deg: float = 0.5
    gain_tol: float = 0.01
    static_tol: float = 0.02
    noise_tol: float = 0.004
    expected_period: float | None = None
    follow_loads: bool = True

    def __post_init__(self) -> None:
        if not (math.isfinite(self.amp) and self.amp > 0.0):
            raise ValueError(f"amp must be a positive number of MV units, got {self.amp}")
        if not 90.0 <= self.phase_deg <= 170.0:
            raise ValueError(f"phase must be between 90 and 170 degrees of lag, got {self.phase_deg}")
        if self.hysteresis is not None and not (math.isfinite(self.hysteresis) and self.hysteresis >= 0.0):
            raise ValueError(f"hysteresis must be ≥ 0 PV units, got {self.hysteresis}")
        if not 0.0 <= self.bias < 0.5:
            raise ValueError(f"bias must be in [0, 0.5), got {self.bias}")
        if not self.mv_rate > 0.0:
            raise ValueError(f"mv_rate must be positive MV units per second, got {self.mv_rate}")
        if not self.time_limit > 0.0:
            raise ValueError(f"time limit must be positive seconds, got {self.time_limit}")
        if self.expected_period is not None and not (math.isfinite(self.expected_period) and self.expected_period > 0):
            raise ValueError(f"expected_period must be a positive number of seconds, got {self.expected_period}")
        if self.noise_samples < 5:
            raise ValueError(f"noise_samples must be at least 5, got {self.noise_samples}")
        for name, (lo, hi) in (("pv_limits", self.pv_limits), ("mv_limits", self.mv_limits)):
            if not lo < hi:
                raise ValueError(f"{name} must be (low, high) with low < high, got ({lo}, {hi})")


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


@dataclass(frozen=True)
class Status:
    """Progress report: ``ite`` is the estimated seconds left while running, the code when done."""

    stage: Stage
    progress: float
    ite: float
    relay: int
    filter_phase_deg: float
    periods: int
    code: Code | None
    message: str


# A static gain above this many times |F(jω)| is indistinguishable from an
# integrating process with the resolution of the mean MV shift; the design
# (point_design) models such a process as an integrator.
INTEGRATING_RATIO = 200.0
# Minimum number of whole periods before convergence is judged: one for the
# start-up transient and the first filter correction, one per estimate.
_MIN_PERIODS = 3
# The record is searched for a disturbance from this many periods on (earlier,
# the filter's first corrections move the estimates anyway).
_CHECK_FROM = 5
# While not converged, the record is searched for a disturbance every this many periods.
_CHECK_EVERY = 2
# A fitted load (MV units, per amp) or free response (per |F|·amp) below this is no disturbance.
_LOAD_FRACTION = 0.08
# The relay's centre moves only for a change of the fitted load above this fraction of amp.
_SHIFT_STEP = 0.03
# A jump of |F|/K0 between consecutive estimates above this starts the search for a disturbance.
_JUMP = 0.05
# A fit whose |F|/K0 is this uncertain describes no disturbance reliably enough to act on.
_X_STD_MAX = 0.1
# A sample interval this many times the usual one is a gap in the record.
_GAP = 3.0
# A time without samples longer than this share of a period (and than _GAP sample intervals) in an estimate's
# window (a link or a machine that stalled) leaves that estimate out of the stopping rule: the relay could not
# switch meanwhile.
_STALL = 0.1
# Without an expected period, the time-left estimate starts from this share of the time limit.
_LIMIT_SHARE = 200.0
_SAMPLES_PER_PERIOD = 100.0
# Noise (σ) above this fraction of |F|·amp makes single estimates scatter beyond gain_tol.
_NOISY = 0.002
_MAX_LOG_STEP = math.log(3.0)
_RELAXATION = 0.75
# Open-loop unstable processes (a negative mean ratio, or a PV that ran away from a weak relay
# level): the relay's bias drops to this, so that the weaker level (amp·(1 − 2·bias)) keeps the
# authority to bring the PV back after the overshoot the dead time gives (e^{D/T} − 1 at D/T = 0.5
# is 0.65 × amp: more than the 0.6 of bias 0.2).
_UNSTABLE_BIAS = 0.1
# The phase target of an unstable process moves this share of the way from the least lag its
# model reaches to 180° (where the plain relay oscillates): a target near the least lag sits where
# the phase curve is flat and the cycle slides onto the low-frequency branch and runs away.
_UNSTABLE_MARGIN = 0.4
# The share of gain_tol and static_tol within which a period between falling crossings must agree with the
# latest rising one (_judge_half): a transient decaying by ρ per period leaves the latest estimate off by
# ρ/(1 − ρ) × the difference of disjoint windows, but by √ρ/(1 − √ρ) × that of windows half a period apart —
# 2.4–2.9 times more for ρ = 0.5–0.3.
_HALF_TOL = 1.0 / 3.0
# A PV slope over the noise stage beyond this many of its standard errors is a PV still settling at TUNE.
_SETTLING_EVIDENCE = 5.0
# Highest phase target (the RelayConfig's upper bound).
_MAX_TARGET_DEG = 170.0
# The relay's low level in its first half period, as a share of amp (see RelayExperiment.__init__):
# an unstable process with D/T ≥ ln(1 + 0.4) ≈ 0.34 overshoots beyond it and is recognised in the
# first period, while a rescue to the full amp still holds it (up to D/T ≈ 0.55).
_FIRST_LOW = 0.4
# An open-loop unstable process is recognised from the mean ratios of the first this many estimates (the
# first one still carries the start's transient); one whose ratio turns negative later is a load step or
# noise, which the load fit and the stopping rule deal with.
_HINT_ESTIMATES = 3
# A first half period at the weak level longer than this many reaction times (_reaction): the level barely
# held the PV, as on an unstable process whose dead time and lag are near what a relay holds; the
# describing function's lag in the next period would let it run away beyond the full amp (seen at 9.3 on
# exp(-0.3*s)/((s-1)*(0.1*s+1))). The batch's stable processes stay below 7.1.
_SLOW_RETURN = 8.0
# The mean ratio |F|/K0 over the first whole period below which the process may be open-loop unstable: it is
# then treated as unstable, as after a rescue, until the estimates decide. The start's transient takes a stable
# process's first period down to −0.31 (the batch); an unstable one whose dead time the first weak level
# does not reveal (D/T 0.25–0.34) shows −0.8 to −1.1, and the describing function's lag would make it run
# away in the next period.
_SUSPECT_RATIO = -0.5
# How much lower (information criterion) the unstable load fit must score than the stable one to call a
# process unstable: both ranges share x = 0, so an integrator with a load ties (differences of 1–3 seen);
# unstable processes score 20–250 lower. 10 is "very strong" evidence on the usual BIC scale.
_UNSTABLE_EVIDENCE = 10.0
# A runaway from a full-amp level within this fraction of its growth time constant after the relay's answer
# arrived is faster than one unstable pole with dead time runs from it (D/T ≥ 0.5 for that): _runaway_at_full_amp.
_REACH_ONE_POLE = 0.25
# A first switch within this many samples of the relay's start tells nothing of the process's reaction time
# (see RelayExperiment._reaction).
_REACT_SAMPLES = 3
# Windows of the runaway test (_check_runaway), as a share of the process's reaction time.
_RUNAWAY_WINDOW = 0.15
# The runaway test's steps must grow this close to geometrically (s0·s2 ≥ _GEOMETRIC·s1², less the noise).
_GEOMETRIC = 0.97
# ... and by more than this share of the distance from the set point: the rounding of the windows' means
# (running sums since the switch: about 1e-13 of it) is no growth.
_ROUNDING = 1e-9


@dataclass
class _Fits:
    """The load fits of one record (its length) and estimate (their count): the fitter, the answers by
    question (unstable, near)."""

    record: tuple[int, int]
    fitter: LoadFitter | None
    answers: dict[tuple[bool, LoadFit | None], LoadFit | None] = field(default_factory=dict)


class RelayExperiment:
    """Relay + adaptive phase filter identification of one frequency-response point."""

    def __init__(self, config: RelayConfig, mv0: float) -> None:
        if not math.isfinite(mv0):
            raise ValueError(f"starting MV must be finite, got {mv0}")
        self.config = config
        self.mv0 = mv0
        lo, hi = config.mv_limits
        self._mv_high = min(mv0 + config.amp, hi)
        # The first half period below the centre is held at a weak level (_FIRST_LOW): no estimate uses
        # the first period, and an open-loop unstable process then overshoots beyond the level's
        # authority at once, while the PV is still near the set point, so that _check_runaway
        # recognises it before a phase filter's lag can make it run away beyond the full amp.
        self._mv_low = max(mv0 - config.amp * min(_FIRST_LOW, 1.0 - 2.0 * config.bias), lo)
        self._first_low = True
        # The relay's centre follows a fitted load (within ±amp of mv0), and
        # its bias changes sign once after a load step, so that the static
        # gain has a known excitation after the step as well.
        self._center = mv0
        self._bias_sign = 1.0
        self._fit: LoadFit | None = None
        self._fitted_at = 0
        self._discard_before = -math.inf
        self._flipped = False
        self._changed_at = -math.inf
        self._stalled_until = -math.inf  # the end of the latest window that held a stall (_STALL)
        self._stalls: list[float] = []  # the longest gap of each such window, s
        self._candidate: LoadFit | None = None
        self._fits = _Fits((0, 0), None)
        # The analysis of the period that ended at a switch, run after the switch is out (see analyse).
        self._analyse: Callable[[], None] | None = None
        self._progress = 0.0
        self._follow_rate = 0.0
        self._follow_from = 0.0
        # The samples, the MV held from each and when it reached the process (s): the sample's time unless
        # the caller said it came later (``applied``: a write that a busy link or a stalled session delayed).
        self._record = Record()
        self.stage = Stage.NOISE
        self.code: Code | None = None
        self.message = ""
        self.result: Identification | None = None
        self._sign = -1.0 if config.reverse else 1.0
        self._sp = 0.0
        self._eps = 0.0
        self._noise = 0.0
        self._relay = 0
        self._filtered = 0.0
        self._crossing = 0.0
        self._filter = PhaseFilter()
        self._omega = 0.0
        self._dt = 0.0
        self._switches: list[int] = []
        self._longest_half = 0.0  # the longest time between two switches so far, s (_check_oscillation)
        self._rising: list[int] = []
        # Sub-sample times of the rising crossings: the period they give is
        # free of the sampling jitter of the switch instants.
        self._crossings: list[float] = []
        self._falls: list[float] = []  # the same at the falling switches
        self._estimates: list[tuple[Point, float]] = []
        self._windows: list[float] = []
        # |F|/K0 over the last two periods (Hann), one per estimate: the unstable-process tests
        # (_negative_ratio) read the sign of the static gain, which one period of the start-up
        # transient can invert on a stable lag-dominant process.
        self._wide: list[float] = []
        self._wide_spans: list[tuple[float, float]] = []  # the window of each, s
        # The lag over every whole period, radians (also those before the first estimate is judged).
        self._lags: list[float] = []
        self._disturbance_seen = False
        self._settling = (0.0, 0.0)  # (PV slope at the start, sign-corrected PV units per s; its time, s)
        self._last: tuple[float, float] | None = None
        self._slope = 1.0
        self._relay_start = 0
        self._peak_error = 0.0
        # The phase the filter aims at: the requested one, or a reachable one (unstable processes).
        self._target_deg = config.phase_deg
        self._bias = config.bias
        self._unstable = False
        # Seconds from the relay's start to its first switch: how long the process takes to answer.
        self._react = 0.0
        self._full_level = False
        self._turn = 0.0  # seconds from the first switch to the PV's first turn (see _reaction)
        self._rescued_at = 0
        # Running sums of the PV's distance from the set point over the samples after _sums_from (the
        # latest switch or rescue): the long runaway windows' means at O(1) per sample (_runaway).
        self._sums_from = -1
        self._sums = [0.0]
        self._aimed = False  # an unstable process's target has been set from an estimate
        if self._mv_high <= mv0 or self._mv_low >= mv0:
            self._finish(
                Code.MV_RANGE,
                f"the relay cannot move the MV from {mv0:g}: the levels {self._mv_low:g} and {self._mv_high:g} "
                f"(amp {config.amp:g} within the limits {config.mv_limits}) do not straddle it",
            )

    # -- public interface -------------------------------------------------

    @property
    def levels(self) -> tuple[float, ...]:
        """Every MV level the relay can hold between switches, ascending, MV units (within the MV limits).

        With its centre at ``mv0``: the high level ``mv0 + amp`` and the low
        ones — the first half period's weak level (``_FIRST_LOW``), the biased
        one ``mv0 − amp·(1 − 2·bias)``, an unstable process's (bias
        ``_UNSTABLE_BIAS``) and the full ``amp`` of a rescue (``_check_runaway``).
        A crash recovery reads an MV at any of them as the experiment's, not an
        operator's. A relay that follows a load (``follow_loads``) shifts its
        centre within ±amp and may flip its bias; those levels are not listed.
        """
        lo, hi = self.config.mv_limits
        amp = self.config.amp
        shares = {1.0, 1.0 - 2.0 * self.config.bias, min(_FIRST_LOW, 1.0 - 2.0 * self.config.bias),
                  1.0 - 2.0 * min(self.config.bias, _UNSTABLE_BIAS)}
        low = {max(self.mv0 - amp * share, lo) for share in shares}
        return tuple(sorted(low | {min(self.mv0 + amp, hi)}))

    @property
    def done(self) -> bool:
        """True once the experiment has ended (successfully or not)."""
        return self.stage is Stage.DONE

    def abort(self) -> None:
        """TBRK: end the experiment now; the caller restores the loop."""
        if not self.done:
            self._finish(Code.ABORTED, MESSAGES[Code.ABORTED])

    def fail(self, code: Code, message: str) -> None:
        """End the experiment with an error found outside it (e.g. a link fault)."""
        if not self.done:
            self._finish(code, message)

    def step(self, t: float, pv: float) -> float:
        """Take the PV sampled at time ``t`` (seconds) and return the MV to hold until the next sample."""
        if self.done:
            return self.mv0
        if not (math.isfinite(t) and math.isfinite(pv)):
            self._finish(Code.BAD_SAMPLE, f"non-finite sample: t={t}, pv={pv}")
            return self.mv0
        record = self._record
        if len(record) and t <= record.time(-1):
            self._finish(Code.BAD_SAMPLE, f"timestamp {t} s does not follow {record.time(-1)} s")
            return self.mv0
        lo, hi = self.config.pv_limits
        if not lo <= pv <= hi:
            self._finish(Code.PV_OUT_OF_LIMITS, f"PV {pv:g} left the limits [{lo:g}, {hi:g}]")
            return self.mv0
        self.analyse()
        if self.done:
            return self.mv0
        record.add(t, pv)
        if t - record.time(0) > self.config.time_limit:
            self._timeout()
            return self.mv0
        if self.stage is Stage.NOISE:
            if len(record) >= self.config.noise_samples:
                self._start_relay()
            else:
                record.hold(self.mv0)
                return self.mv0
        mv = self._relay_step(t, pv)
        if self.done:
            return self.mv0
        step = self.config.mv_rate * (t - record.time(-2))
        mv = min(max(mv, record.mv(-1) - step), record.mv(-1) + step)
        record.hold(mv)
        return mv

    @property
    def analysis_pending(self) -> bool:
        """True when a period ended at the last sample and :meth:`analyse` has not run yet."""
        return self._analyse is not None and not self.done

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
        analyse, self._analyse = self._analyse, None
        if analyse is not None and not self.done:
            analyse()

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
        if self._record.held and self._record.held == len(self._record) and math.isfinite(t):
            self._record.applied(t)

    @property
    def stall_tolerance(self) -> float:
        """The longest time without a sample (s) that leaves the estimates usable: a tenth of the period as well
        as it is known now, and at least three sample intervals (a longer stall leaves its estimates out)."""
        dt = self._mean_interval()
        return max(_STALL * self._period_guess(dt), _GAP * (dt or 0.0))

    def _mean_interval(self) -> float | None:
        """The mean time between the samples so far (s); None before two."""
        samples = len(self._record)
        return (self._record.time(-1) - self._record.time(0)) / (samples - 1) if samples >= 2 else None

    def status(self) -> Status:
        """Stage, progress (0–1), ite and the live relay/filter state."""
        if self.done:
            ite = float(self.code) if self.code is not None else 0.0
            progress = 1.0
        else:
            left = self._seconds_left()
            elapsed = self._record.time(-1) - self._record.time(0) if len(self._record) else 0.0
            ite = left
            # Progress never goes backwards, even when a measured period
            # turns out longer than the estimate before it.
            self._progress = max(self._progress, elapsed / (elapsed + left))
            progress = self._progress
        return Status(
            stage=self.stage,
            progress=progress,
            ite=ite,
            relay=self._relay,
            filter_phase_deg=math.degrees(self._filter.phase(self._omega)),
            periods=max(len(self._rising) - 1, 0),
            code=self.code,
            message=self.message,
        )

    # -- stages -----------------------------------------------------------

    def _start_relay(self) -> None:
        t, y = self._record.t, self._record.y
        slope, offset = np.polyfit(t - t[0], y, 1)
        residual = y - (offset + slope * (t - t[0]))
        self._noise = float(np.std(residual, ddof=2))
        self._sp = float(np.mean(y))
        # A PV still moving when TUNE came (a load step just before, a set point change): the lag's free
        # response, which the static ratio takes out (settled_ratio). Noise alone gives a slope within
        # a few of its standard errors.
        centred = t - float(np.mean(t))
        slope_std = self._noise / math.sqrt(float(centred @ centred)) if np.any(centred) else math.inf
        if abs(slope) > _SETTLING_EVIDENCE * slope_std:
            self._settling = (self._sign * float(slope), float(np.mean(t)))
        h = self.config.hysteresis
        self._dt = float(t[-1] - t[0]) / (len(t) - 1)
        self._eps = 3.0 * self._noise if h is None else h
        self.stage = Stage.RELAY
        self._relay = 1
        self._relay_start = len(self._record) - 1
        self._filtered = 0.0
        self._crossing = self._record.time(-1)

    def _relay_step(self, t: float, pv: float) -> float:
        e = self._sign * (self._sp - pv)
        before = self._filtered
        dt = t - self._record.time(-2)
        self._filtered = self._filter.step(e, dt)
        self._peak_error = max(self._peak_error, abs(self._filtered))
        k = len(self._record) - 1
        old = self._relay_mv()
        if self._relay > 0 and self._filtered < -self._eps:
            self._switch(-1, k, -self._eps, before, dt)
            self._analyse = self._judge_half
        elif self._relay < 0 and self._filtered > self._eps:
            self._switch(1, k, self._eps, before, dt)
            self._analyse = self._on_period
        if not self.done and self._analyse is None:  # (the period's end is judged once it is analysed)
            self._check_oscillation(k)
        if not self.done and self._check_runaway(k):
            return self._relay_mv()
        if self.done:
            return self.mv0
        if self._switches[-1:] != [k]:
            return old
        # The crossing happened between the last two samples; switching one
        # sample period after it, with the interval's MV averaged to keep the
        # area, makes the limit cycle periodic in continuous time instead of
        # jittering by a sample at every switch. The frequency-response
        # estimate depends on that periodicity.
        late = (self._crossing - self._record.time(k - 1)) / dt
        return old * late + self._relay_mv() * (1.0 - late)

    def _switch(self, relay: int, k: int, threshold: float, before: float, dt: float) -> None:
        frac = (threshold - before) / (self._filtered - before)
        self._crossing = self._record.time(k - 1) + frac * dt
        self._relay = relay
        if self._switches:
            self._longest_half = max(self._longest_half, self._record.time(k) - self._record.time(self._switches[-1]))
        self._switches.append(k)
        if len(self._switches) == 1:
            # At least a sample: a process without dead time answers within one (noise-free, no hysteresis).
            self._react = self._crossing - self._record.time(self._relay_start)
        if self._full_level:
            # A rescued half period (_check_runaway) ends: the weaker bias from now on.
            self._full_level = False
            self._set_levels()
        if relay > 0:
            self._rising.append(k)
            self._crossings.append(self._crossing)
        else:
            self._falls.append(self._crossing)

    def _relay_mv(self) -> float:
        level = self._mv_high if self._relay > 0 else self._mv_low
        if self._follow_rate:
            # A drifting load is followed continuously: no step, no transient.
            lo, hi = self.config.mv_limits
            level = min(max(level - self._follow_rate * (self._record.time(-1) - self._follow_from), lo), hi)
        return level

    def _set_levels(self) -> None:
        """Relay levels from the centre and the sign of the bias, within the MV limits."""
        lo, hi = self.config.mv_limits
        amp, short = self.config.amp, self.config.amp * (1.0 - 2.0 * self._bias)
        up, down = (amp, short) if self._bias_sign > 0 else (short, amp)
        self._mv_high = min(self._center + up, hi)
        self._mv_low = max(self._center - down, lo)

    def _check_runaway(self, k: int) -> bool:
        """Keep an open-loop unstable process bounded: True when the relay's level was just strengthened.

        A PV that keeps moving away from the set point, faster and faster, long
        after the relay turned against it (over three windows of 0.15 reaction
        time after the process had time to answer, or, below full amp, over four
        windows that split the whole time since: ``_runaway``) is an unstable
        process the level cannot hold: the weaker level of the biased relay
        has less authority than the overshoot the dead time gave. The level
        goes to the full amp at once, the bias drops to ``_UNSTABLE_BIAS`` and
        the filter's lag is removed (the requested phase may be out of reach).
        If the PV runs away from a level at full amp, no relay holds the
        process: the experiment ends with UNSTABLE_DEAD_TIME_TOO_LONG.
        """
        react = self._reaction(k)
        if not self._switches:
            return False
        # Since the last switch, or since the level was strengthened (its effect takes as long to arrive).
        last = max(self._switches[-1], self._rescued_at)
        self._sum_distance(last, k)
        if react <= 0.0:
            return False
        m = max(int(round(_RUNAWAY_WINDOW * react / self._dt)), 2)  # samples per window
        # The dead time after the switch has passed, and three windows since (the PV accelerates
        # away during the dead time whatever the process).
        elapsed = self._record.time(k) - self._record.time(last) - react
        if elapsed < 3 * m * self._dt:
            return False
        level = self._mv_high if self._relay > 0 else self._mv_low
        amp = self.config.amp
        full = abs(level - self._center) >= amp * (1.0 - 1e-9) or self._full_level
        growth = self._runaway(k, m, samples=True)
        if growth is None and not full and elapsed >= 4 * m * self._dt:
            # Windows that grow with the time since, and the PV's mean over each: a runaway much slower
            # than the reaction time (D/T 0.275 near a weak level's equilibrium) grows by less than the
            # noise from window to window, and the short windows' samples saw it only once it was beyond
            # the full amp's reach (exp(-0.55*s)/(2*s-1) with 1 % noise: 10 s late, refused with 17).
            # (Not at full amp: there the short windows' growth rate tells one unstable pole from two.)
            m = int(elapsed / (4.0 * self._dt))
            growth = self._runaway(k, m, samples=False)
        if growth is None:
            return False
        away, steps = growth
        if len(self._switches) >= 3 and away[-1] <= self._peak_away():
            return False  # within the swing the cycle already had
        if full:
            # The runaway's growth rate (1/s) is an unstable pole's 1/T once the MV is held.
            self._runaway_at_full_amp(amp, react * math.log(steps[2] / steps[1]) / (m * self._dt))
            return False
        lo, hi = self.config.mv_limits
        if self._relay > 0:
            self._mv_high = min(self._center + amp, hi)
        else:
            self._mv_low = max(self._center - amp, lo)
        self._full_level = True
        self._rescued_at = k
        self._enter_unstable()
        self._set_filter(0.0, self._omega or 1.0)
        self._last = None
        return True

    def _sum_distance(self, last: int, k: int) -> None:
        """Add sample ``k``'s distance of the PV from the set point to the sums since sample ``last`` (the
        latest switch or rescue), starting them anew when ``last`` moved."""
        if last != self._sums_from:
            self._sums_from, self._sums = last, [0.0]
        if k > last:
            self._sums.append(self._sums[-1] + (self._record.pv(k) - self._sp))

    def _mean_distance(self, i: int, m: int) -> float:
        """The PV's mean distance from the set point over the ``m`` samples up to sample ``i``.

        From the running sums since the latest switch (O(1) per mark, whatever the time since the switch);
        a window reaching back to the switch (samples denser than the noise stage's) is summed as it is.
        """
        first = i - m + 1
        if first > self._sums_from:
            return (self._sums[i - self._sums_from] - self._sums[first - 1 - self._sums_from]) / m
        return float(np.sum(self._record.y[first:i + 1] - self._sp)) / m

    def _runaway(self, k: int, m: int, samples: bool) -> tuple[list[float], np.ndarray] | None:
        """(distances from the set point, their steps) when the PV moves away faster and faster, else None.

        Over four marks ``m`` samples apart ending at sample ``k``: the PV at each (``samples``) or its mean
        over the ``m`` samples up to each. Equal windows of samples (a sampled ramp compared over unequal
        ones looks curved); the steps must grow by more than the noise, and geometrically: a stable
        process's answer to a ramp (a drifting load) grows too, but its steps converge to the ramp's, and
        an unstable pole's grow as ``s0·s2 = s1²``.
        """
        marks = (k - 3 * m, k - 2 * m, k - m, k)
        distances = ([self._record.pv(i) - self._sp for i in marks] if samples
                     else [self._mean_distance(i, m) for i in marks])
        away = [-self._relay * self._sign * d for d in distances]
        steps = np.diff(away)
        # (And by more than the means' rounding: a followed drift's PV is a ramp, whose equal steps come out of
        # running sums a rounding apart, and a noise-free record's floor is nothing else.)
        floor = 3.0 * self._noise / (1.0 if samples else math.sqrt(m)) + _ROUNDING * max(abs(a) for a in away)
        if not (steps[0] > floor and steps[1] > steps[0] + floor and steps[2] > steps[1] + floor):
            return None
        if steps[0] * steps[2] < _GEOMETRIC * steps[1] ** 2 - floor * (steps[0] + steps[2]):
            return None
        return away, steps

    def _reaction(self, k: int) -> float:
        """Seconds the process takes to answer the relay: the runaway test's time scale (0 while unknown).

        The time from the relay's start to its first switch. A process without
        dead time crosses a zero hysteresis (no noise) at its first sample, and
        a high-order lag then still accelerates long after: for such a process
        (a first switch within ``_REACT_SAMPLES`` samples) it is the time from
        the first switch until the PV turned back towards the set point.
        """
        if self._react > _REACT_SAMPLES * self._dt:
            return self._react
        if not self._turn and self._switches:
            first = self._switches[0]
            if len(self._switches) >= 2:
                self._turn = self._record.time(self._switches[1]) - self._record.time(first)
            elif k - 1 > first:
                # After the first switch the relay pushes the PV back: it turns when its distance from the set
                # point stops growing.
                away = [self._relay * self._sign * (self._sp - self._record.pv(i)) for i in (k - 1, k)]
                if away[1] < away[0]:
                    self._turn = self._record.time(k - 1) - self._record.time(first)
        return self._turn

    def _runaway_at_full_amp(self, amp: float, reach: float) -> None:
        """End the experiment: the PV runs away from a level at full amp (no relay holds this process).

        ``reach``: the time the process takes to answer the relay times the
        runaway's growth rate — for ``K·e^{−Ds}/(Ts − 1)``, D/T. A single
        unstable pole defeats a full-amp relay only from D/T ≈ 0.5–0.7 on, and
        its lag stays below 180° at any frequency where a relay oscillates; a
        runaway with ``reach`` below ``_REACH_ONE_POLE`` or a lag beyond 180°
        means more than one unstable pole: NOT_STABILISABLE, as the design says
        of such a process. Otherwise the dead time is too long for a relay to
        hold the process, so too long for a PI/PID as well:
        UNSTABLE_DEAD_TIME_TOO_LONG.
        """
        what = (f"the PV runs away from the set point faster and faster while the relay pushes back with its full "
                f"amplitude ({amp:g})")
        lag = max(self._lags, default=0.0)
        if lag > math.pi or reach < _REACH_ONE_POLE:
            if lag > math.pi:
                evidence = (f"the process lagged {math.degrees(lag):.0f}° (more than 180°) at the relay's frequency "
                            "— an open-loop unstable process with more than one unstable pole")
            else:
                # A runaway this fast from a level the dead time alone would let a relay hold: more than one
                # unstable pole, or stable lags that add to the dead time (the growth is then measured while
                # the full level is still arriving through them).
                evidence = (f"the relay's answer reached it within {reach:.2f} × the runaway's time constant (a "
                            "relay holds a single unstable pole with so short a dead time) — an open-loop unstable "
                            "process with more than one unstable pole, or lags that add to its dead time beyond "
                            "what a relay holds")
            self._finish(
                Code.NOT_STABILISABLE,
                f"{MESSAGES[Code.NOT_STABILISABLE]}: {what}, and {evidence}: no relay holds it and no PI/PID "
                f"stabilises it robustly, so no relay experiment tunes it{self._stalled_note()}",
            )
            return
        self._finish(
            Code.UNSTABLE_DEAD_TIME_TOO_LONG,
            f"{MESSAGES[Code.UNSTABLE_DEAD_TIME_TOO_LONG]}: {what} — an open-loop unstable process whose dead time "
            f"is too long for a relay to hold it (about {reach:.2f} × the runaway's time constant; a relay holds up "
            f"to about 0.5–0.7), so too long for a PI/PID as well{self._stalled_note()}",
        )

    def _stalled_note(self) -> str:
        """What a stall of the samples over the last period adds to a runaway's refusal ("" without one)."""
        record = self._record
        start = record.time(self._switches[-3] if len(self._switches) >= 3 else self._relay_start)
        gap = self._longest_gap(record.since(start).t, start, record.time(-1))
        if gap <= _GAP * self._dt:
            return ""
        # The relay cannot switch without a sample: on an unstable process a stall acts as extra dead time.
        return (f"; but the samples stopped for up to {gap:.2g} s meanwhile (a slow link or a loaded machine), "
                "which acts as extra dead time: retry where the tuner samples without stalls")

    def _peak_away(self) -> float:
        """Largest deviation of the PV from the set point over the last whole period before the current half (PV units)."""
        start, end = self._switches[-3], self._switches[-1]
        return float(np.max(np.abs(self._record.y[start:end] - self._sp)))

    def _enter_unstable(self) -> None:
        """An open-loop unstable process: the weaker bias, levels changed (estimates from now on)."""
        self._unstable = True
        if self._bias > _UNSTABLE_BIAS:
            self._bias = min(self._bias, _UNSTABLE_BIAS)
            if not self._full_level:
                self._set_levels()
            self._changed_at = self._record.time(-1)

    def _move_target(self, point: Point, x: float) -> None:
        """Aim at a phase an unstable process reaches, from the model the latest estimate fixes.

        The lag ``π − atan(ωT) + ωD`` of the model (``_unstable_model``) is least,
        ``π − atan(s) + s·D/T``, at ``ωT = s = sqrt(T/D − 1)``. The target moves
        ``_UNSTABLE_MARGIN`` of the way from there to 180° (never below the
        requested phase, never above 170°, never back down).
        """
        model = self._unstable_model(point, x)
        if model is None:
            return
        ratio = model[1]
        if ratio >= 1.0:
            least = math.pi
        elif ratio > 0.0:
            s = math.sqrt(1.0 / ratio - 1.0)
            least = math.pi - math.atan(s) + s * ratio
        else:
            least = math.pi / 2.0
        self._aimed = True
        wanted = math.degrees(least + _UNSTABLE_MARGIN * (math.pi - least))
        self._target_deg = min(max(self._target_deg, wanted), _MAX_TARGET_DEG)

    def _on_period(self) -> None:
        time = self._record.time
        if self._first_low:
            self._first_low = False
            if not self._full_level:
                self._set_levels()
        if len(self._rising) == 1:
            # First rising switch: only half a period is known. Start the filter
            # at the describing-function guess.
            half = time(self._rising[0]) - time(self._switches[-2])
            omega = math.pi / half
            ratio = min(1.0, self._eps / self._peak_error) if self._peak_error > 0 else 0.0
            if self._react > _REACT_SAMPLES * self._dt and half > _SLOW_RETURN * self._react:
                self._enter_unstable()  # as after a rescue, until the estimates say otherwise
            # A PV that already ran away once (unstable): no lag until an estimate says what is reachable.
            theta = 0.0 if self._unstable else math.pi - math.radians(self._target_deg) - math.asin(ratio)
            self._set_filter(theta, omega)
            return
        # The samples of this period's estimates: from the third latest crossing on (the drift and the
        # two-period means start there). (The switch's own MV, recorded already, holds from this sample
        # on: after every window.)
        raw = self._record.since(self._crossings[max(len(self._crossings) - 3, 0)])
        if self._fit is not None:
            # Disturbed: refit with this period (static gain, the relay's centre).
            self._refit()
            if self.done:
                return
            # The point is estimated from the PV as measured (detrended as
            # usual) over windows after the load step only: subtracting the
            # fitted load response would make the point hostage to the fit,
            # which a hiccup of the link can mislead.
            if self._follow_rate and len(self._crossings) >= 3:
                # The MV follows a drift: its ramp is slow too, not part of the oscillation.
                raw = replace(raw, u=raw.u - self._drift(raw.s, raw.u, self._crossings[-3:]))
        detrended = raw
        if len(self._crossings) >= 3:
            detrended = replace(raw, y=raw.y - self._drift(raw.t, raw.y, self._crossings[-3:]))
        ta, tb = self._crossings[-2], self._crossings[-1]
        omega = 2.0 * math.pi / (tb - ta)
        value = self._estimate(raw, ta, tb, omega, hann=False)
        lag = self._lag(value)
        self._lags.append(lag)
        # (A PV still settling at TUNE makes any process's first ratio negative: the load fit judges that one.)
        first = len(self._lags) == 1 and not self._settling[0]
        if first and self._mean_ratio(raw, ta, tb, abs(value)) < _SUSPECT_RATIO:
            self._enter_unstable()
            self._set_filter(0.0, omega)
        # An open-loop unstable process shows a negative mean ratio from its first estimates on (or ran
        # away from a level already); one that turns negative later is a load step or noise, which the
        # load fit and the stopping rule deal with.
        negative = self._negative_ratio()
        recognised = self._unstable or (len(self._estimates) <= _HINT_ESTIMATES and self._unstable_hint())
        # (Asked once, when the process would first be taken for unstable: the load fit costs two fits.)
        if negative and recognised and self._fit is None and (self._unstable or not self._stable_with_load()):
            # An open-loop unstable process: a weaker bias, and a phase it reaches.
            self._enter_unstable()
            self._move_target(self._estimates[-1][0], self._wide[-1])
        elif negative is False:
            self._unstable = False  # a rescued level (_check_runaway) on a process the estimates call stable
        # (A change of the levels made just now, at the end of the period, leaves the period clean.)
        clean = ta >= self._changed_at or self._changed_at >= time(-1)
        if clean and not (self._unstable and not self._aimed):
            # A period that saw the relay's levels change is a transient: the
            # filter is not corrected from it (nor, on a process that is or may be
            # unstable, before an estimate has said which phase it reaches).
            self._adapt(omega, lag)
        if len(self._rising) >= 3:
            self._judge(raw, detrended.y)
        if self.done or self._fit is not None:
            return
        # Quiet so far: look for a disturbance every few periods while the
        # estimates have not settled (a load step keeps them moving).
        periods = len(self._rising) - 1
        jump = abs(self._estimates[-1][1] - self._estimates[-2][1]) if len(self._estimates) >= 2 else 0.0
        # During the filter's first corrections the estimates move anyway:
        # only a large jump counts as a sign of a disturbance then.
        early = periods >= 3 and jump > 3.0 * _JUMP
        again = self._candidate is not None
        if again or early or periods >= _CHECK_FROM and (jump > _JUMP or (periods - _CHECK_FROM) % _CHECK_EVERY == 0):
            self._look_for_disturbance()

    # -- disturbances -------------------------------------------------------

    def _fitter(self) -> LoadFitter | None:
        """The load fitter of the whole record with the latest estimate's point (None before one, or resonant)."""
        if not self._estimates or len(self._crossings) < 4:
            return None
        if self._resonant():
            return None
        point = self._estimates[-1][0]
        record = self._record.all()
        n = len(record.u)
        scale = point.gain * self.config.amp
        return LoadFitter(record.t[:n], self._sign * (record.y[:n] - self._sp), record.u, self.mv0, self._relay_start,
                          point.omega, point.gain, self._lag(point.value), scale, held_from=record.s)

    def _resonant(self) -> bool:
        """True when |F(jω)| reads above the static gain: a resonance, which no first-order model describes.

        The fit would invent loads there. But a load step against the relay's
        bias makes a plain lag's ratio |F|/K0 read above 1 too (−0.1 × amp on
        ``exp(-s)/(2*s+1)``: 0.37, then 1.4): there an earlier estimate of about
        the same |F| (within 10 %) read below 1, or a ratio a third away — one
        that cancels the bias runs away (1.1, 1.8, 2.9, 5.9 on
        ``exp(-s)/(0.05*s+1)^2`` at −0.2 × amp). A resonance builds |F| up with
        its ratio (0.49 at 0.13 … 1.68 at 1.68 on ``exp(-0.1*s)/(s^2+0.4*s+1)``).
        """
        latest, x = self._estimates[-1]
        if x <= 1.0:
            return False
        return not any((i < 1.0 or abs(i - x) > x / 3.0) and abs(p.gain - latest.gain) <= 0.1 * latest.gain
                       for p, i in self._estimates[1:-1])

    def _load_fit(self, unstable: bool, near: LoadFit | None = None) -> LoadFit | None:
        """The load fit of the record (``near``: see LoadFitter.fit), or None when there is none to make.

        Made once per record, estimate and question: a quiet period's analysis may ask twice (before it
        accepts a result and when it looks for a disturbance), with the same answer.
        """
        record = (self._record.held, len(self._estimates))
        if self._fits.record != record:
            self._fits = _Fits(record, self._fitter())
        fits, question = self._fits, (unstable, near)
        if question not in fits.answers:
            fits.answers[question] = None if fits.fitter is None else fits.fitter.fit(unstable, near)
        return fits.answers[question]

    def _look_for_disturbance(self) -> bool:
        """Fit the slow part of the record; True (and the disturbed mode on) if it needed a disturbance."""
        if not self.config.follow_loads:
            return False
        fit = self._load_fit(self._unstable)
        if fit is None:
            return False
        if not self._significant(fit):
            self._candidate = None
            return False
        # A disturbance is acted on when two fits a period apart agree on it:
        # a single odd period (a stalled link holding the MV for seconds) fits
        # as a load step too, but not the same one twice.
        previous, self._candidate = self._candidate, fit
        if previous is None or not self._agree(previous, fit):
            return True  # look again next period before accepting anything
        self._enter_disturbed(fit)
        return True

    def _agree(self, a: LoadFit, b: LoadFit) -> bool:
        """Two fits describe the same disturbance (step time within a quarter period, sizes within a third)."""
        if a.x_std > _X_STD_MAX or b.x_std > _X_STD_MAX:
            return False
        period = self._record.time(self._rising[-1]) - self._record.time(self._rising[-2])
        if (a.step_time is None) != (b.step_time is None):
            return False
        if a.step_time is not None:
            if abs(a.step_time - b.step_time) > 0.25 * period or abs(a.step - b.step) > abs(b.step) / 3.0:
                return False
        # Ramps agree within a third, or when they differ by less than a load worth
        # following over the whole record (the information criterion keeps a negligible
        # ramp in one fit and not the next).
        duration = self._record.time(-1) - self._record.time(0)
        difference = abs(a.ramp - b.ramp)
        negligible = difference * duration < _LOAD_FRACTION * self.config.amp
        return negligible or difference <= max(abs(a.ramp), abs(b.ramp)) / 3.0

    def _significant(self, fit: LoadFit) -> bool:
        """A fitted disturbance worth estimating through: larger than a fraction of amp (or of the PV scale)."""
        amp = self.config.amp
        step = fit.step_time is not None and abs(fit.step) >= _LOAD_FRACTION * amp
        duration = self._record.time(-1) - self._record.time(0)
        ramp = abs(fit.ramp) * duration >= 2.0 * _LOAD_FRACTION * amp
        point = self._estimates[-1][0]
        free = abs(fit.free) >= _LOAD_FRACTION * point.gain * amp
        return step or ramp or free

    def _enter_disturbed(self, fit: LoadFit) -> None:
        self._fit = fit
        self._fitted_at = len(self._rising)
        self._disturbance_seen = True
        if fit.step_time is not None:
            self._discard_before = max(self._discard_before, fit.step_time)
            if not self._flipped and abs(fit.step) >= 2.0 * _LOAD_FRACTION * self.config.amp:
                self._bias_sign = -self._bias_sign
                self._flipped = True
        self._follow_load()

    def _refit(self) -> None:
        """Refit the record with this period, near the accepted fit (LoadFitter.fit's ``near``)."""
        fit = self._load_fit(self._unstable, near=self._fit)
        if fit is None:
            return
        if not self._agree(self._fit, fit):
            # Keep following what was accepted until two new fits agree on something else.
            previous, self._candidate = self._candidate, fit
            if previous is None or not self._agree(previous, fit):
                return
        self._candidate = fit
        if fit.step_time is not None and (self._fit is None or self._fit.step_time != fit.step_time):
            self._discard_before = max(self._discard_before, fit.step_time)
        self._fit = fit
        self._follow_load()

    def _follow_load(self) -> None:
        """Shift the relay's centre to cancel the fitted load at the process input (within ±amp)."""
        fit = self._fit
        assert fit is not None
        time = self._record.time
        t = time(-1)
        period = time(self._rising[-1]) - time(self._rising[-2]) if len(self._rising) >= 2 else 0.0
        load = fit.load_at(t + 0.5 * period, time(0))
        amp = self.config.amp
        # The ramp part is followed continuously from now on; the centre takes the rest.
        then = t + 0.5 * period
        applied = self._center - self._follow_rate * (then - self._follow_from)
        if abs(load) > amp:
            self._finish(
                Code.DISTURBANCE,
                f"{MESSAGES[Code.DISTURBANCE]}: the load at the process input has moved by {load:+.3g} MV units "
                f"({abs(load) / amp:.2f} × amp); the relay follows a load within ±amp of the starting MV only",
            )
            return
        center = self.mv0 - self._sign * load
        rate = self._sign * fit.ramp
        if abs(center - applied) > _SHIFT_STEP * amp or self._changed_at == -math.inf:
            # Each step of the levels starts a transient: estimates are taken after it.
            self._center, self._follow_rate, self._follow_from = center, rate, then
            self._set_levels()
            self._changed_at = t
        elif abs(rate - self._follow_rate) * period > 0.2 * _SHIFT_STEP * amp:
            # A better drift rate: keep the level continuous where it is now.
            self._center, self._follow_rate, self._follow_from = applied, rate, then
            self._set_levels()

    def _unstable_hint(self) -> bool:
        """True when the estimates say the process is open-loop unstable.

        The simple mean ratio of the latest two estimates is negative, and the
        unstable model that the latest estimate fixes has its point on the
        rising branch of its phase curve, where a relay cycle sits. An
        integrating or stable process with a load at the process input from the
        start shows a negative mean ratio too (the relay's mean MV balances the
        load, not the PV's mean), but the model it implies puts the point on
        the falling branch: that is no unstable process.
        """
        if not self._negative_ratio():
            return False
        point, x = self._estimates[-1][0], self._wide[-1]
        return x < 0.0 and self._on_rising_branch(point, x)

    def _stable_with_load(self) -> bool:
        """True unless an unstable model explains the record clearly better than a stable one with a load.

        A load step early in the experiment shifts the relay's mean MV against
        the PV's mean and makes the mean ratio negative, as an unstable process
        does; the load fit tells them apart: the growth of an unstable process
        is no stable model's response to a step, and a stable process's
        response to a load is no unstable model's.
        """
        if not self.config.follow_loads:
            return False
        unstable, stable = (self._load_fit(mode) for mode in (True, False))
        if unstable is None or stable is None:
            return False
        return unstable.score > stable.score - _UNSTABLE_EVIDENCE

    def _negative_ratio(self) -> bool | None:
        """True when the mean two-period ratio |F|/K0 of the latest two estimates is below −static_tol.

        Estimates whose windows span the latest change of the relay's levels do not count (the transient
        between two cycles); None while there is no other.
        """
        since = self._since()
        wide = [x for x, (start, end) in zip(self._wide, self._wide_spans) if not start < since < end][-2:]
        if not wide:
            return None
        return bool(sum(wide) / len(wide) < -self.config.static_tol)

    def _unstable_model(self, point: Point, x: float) -> tuple[float, float] | None:
        """(ω·T, D/T) of ``K·e^{−Ds}/(Ts − 1)`` through ``point`` with ``|F|/K0 = x < 0``, or None if none fits.

        ``K = |F|/|x|``, ``ωT = sqrt(1/x² − 1)``, ``ωD = lag − π + atan(ωT)``
        (methods.md §6, unstable_design).
        """
        if not -1.0 < x < 0.0:
            return None
        wt = math.sqrt(1.0 / (x * x) - 1.0)
        wd = self._lag(point.value) - math.pi + math.atan(wt)
        return wt, max(wd, 0.0) / wt

    def _on_rising_branch(self, point: Point, x: float) -> bool:
        """True when the point lies where the unstable model's lag rises with ω (``ωT > sqrt(T/D − 1)``).

        The lag ``π − atan(ωT) + ωD`` falls from 180° at ω = 0 to its least at
        ``ωT = sqrt(T/D − 1)`` and rises after it; a relay cycle needs the
        rising branch (on the falling one it slides away to ω → 0).
        """
        model = self._unstable_model(point, x)
        if model is None:
            return False
        wt, ratio = model
        return 0.0 < ratio and (ratio >= 1.0 or wt * wt > 1.0 / ratio - 1.0)

    @staticmethod
    def _drift(tt: np.ndarray, yy: np.ndarray, bounds: list[float]) -> np.ndarray:
        """Linear drift of the PV across consecutive whole periods between ``bounds`` (seconds).

        A slow drift (the tail of a transient, an integrating process settling
        its mean) leaks into the Fourier coefficients. The mean over a whole
        period is free of the oscillation, so the change of the means from
        period to period measures the drift alone.
        """
        first = sampled_coefficient(tt, yy, bounds[0], bounds[1], 0.0, hann=False).real
        last = sampled_coefficient(tt, yy, bounds[-2], bounds[-1], 0.0, hann=False).real
        spacing = 0.5 * (bounds[-1] + bounds[-2] - bounds[1] - bounds[0])
        return (last - first) / spacing * (tt - 0.5 * (bounds[0] + bounds[-1]))

    def _judge(self, raw: Samples, detrended: np.ndarray) -> None:
        """Estimate the point over the last period and stop if it has converged.

        ``raw``: the samples from the third latest crossing on; ``detrended``: their PV with its drift removed.
        """
        ta, tb = self._crossings[-2], self._crossings[-1]
        point, inverse_gain = self._period_point(raw, detrended, self._crossings[-3:])
        # Windows that reach back before a load step are left out.
        self._estimates.append((point, inverse_gain))
        self._windows.append(ta)
        self._wide.append(self._wide_inverse(replace(raw, y=detrended)) if self._fit is None else inverse_gain)
        self._wide_spans.append((self._crossings[-3], tb))
        gap = self._longest_gap(raw.t, self._crossings[-3], tb)
        if gap > max(_STALL * (tb - ta), _GAP * self._dt):
            # No sample, so no switch, for that long: the cycle around it is no limit cycle. This estimate
            # and those before it are left out, as after a change of the relay's levels.
            self._stalled_until = tb
            self._stalls.append(gap)
        periods = len(self._rising) - 1
        if periods < _MIN_PERIODS or len(self._estimates) < 2:
            return
        usable = self._usable()
        if len(usable) < 2:
            return
        # Estimates scatter with noise and sampling jitter; the longer the
        # experiment runs, the more of the latest may be averaged (stopping.py).
        noisy = self._noisy()
        # With noise, all estimates since the last disturbance may be averaged but the first
        # (the period right after the filter's first correction).
        longest = len(usable) - 1 if noisy else 2 + (periods - _MIN_PERIODS) // 2
        self._accept(judge(usable, self._target_deg, self._tolerances(), longest, noisy,
                           None if self._fit is None else self._fit.x_std))

    def _judge_half(self) -> None:
        """At a falling switch of a quiet, noise-free run: stop if the period ending here agrees with the last.

        The period between two falling crossings overlaps the latest rising
        one by half; when the two agree the cycle has settled, half a period
        before the next rising crossing would say so. (With noise the
        overlapping windows are not independent estimates: only the rising
        ones are averaged.)
        """
        periods = len(self._rising) - 1
        if self._fit is not None or periods < _MIN_PERIODS or len(self._falls) < 3 or self._noisy():
            return
        ta, tb = self._falls[-2], self._falls[-1]
        usable = self._usable()
        if ta < self._since() or not usable:
            return
        raw = self._record.since(min(self._falls[-3], self._crossings[-2]))
        # A sampling gap (a stalled link) in the overlap biases both windows alike, so they agree: only the
        # disjoint rising windows may judge such a record.
        if self._longest_gap(raw.t, self._crossings[-2], raw.t[-1]) > _GAP * self._dt:
            return
        detrended = raw.y - self._drift(raw.t, raw.y, self._falls[-3:])
        candidates = [*usable, self._period_point(raw, detrended, self._falls[-3:])]
        longest = 2 + (periods - _MIN_PERIODS) // 2
        c = self.config
        tol = replace(self._tolerances(), gain_tol=c.gain_tol * _HALF_TOL, static_tol=c.static_tol * _HALF_TOL)
        self._accept(judge(candidates, self._target_deg, tol, longest, False))

    def _accept(self, verdict: Verdict | None) -> None:
        if verdict is None:
            return
        # Before accepting a quiet result, make sure the record holds no
        # disturbance that the simple means would have mixed in.
        if self._fit is None and self._look_for_disturbance():
            return
        self._succeed(verdict.point, self._fit.x if self._fit is not None else verdict.inverse_gain)

    def _period_point(self, raw: Samples, detrended: np.ndarray, bounds: list[float]) -> tuple[Point, float]:
        """The point over the last whole period of ``bounds`` (crossing times, s) and |F|/K0 over the last two.

        ``raw``: the samples from ``bounds[0]`` on; ``detrended``: their PV with its drift removed (for the
        point). The static ratio takes the means over two periods where there are two (the noise of a
        mean falls with its length), with the MV's as the slow lag has passed it on.
        """
        ta, tb = bounds[-2], bounds[-1]
        # One whole period, rectangular: a Hann window over a single period
        # would mix the fundamental with the mean and the second harmonic.
        omega = 2.0 * math.pi / (tb - ta)
        value = self._estimate(replace(raw, y=detrended), ta, tb, omega, hann=False)
        point = Point(omega, value)
        if self._fit is not None:
            return point, self._fit.x
        start = bounds[0]
        du = held_coefficient(raw.s, raw.u - self.mv0, start, tb, 0.0, hann=False).real
        dy = sampled_coefficient(raw.t, raw.y - self._sp, start, tb, 0.0, hann=False).real
        # Compare estimates through |F|/K0, which stays bounded as K0 grows.
        plain = self._sign * du / dy * abs(value) if dy != 0.0 else 0.0
        # The MV since the start: the slow lag remembers it (settled_ratio reads what its lag still holds).
        history = self._record.all()
        return point, settled_ratio(history.s, history.u, self._sign * dy, plain, point.gain, omega,
                                    self._lag(value), start, tb, *self._settling, u0=self.mv0)

    def _wide_inverse(self, samples: Samples) -> float:
        """|F|/K0 over the last two whole periods with a Hann window (the mean weighted to their middle)."""
        ta, tb = self._crossings[-3], self._crossings[-1]
        value = self._estimate(samples, ta, tb, 4.0 * math.pi / (tb - ta), hann=True)
        return self._mean_ratio(samples, ta, tb, abs(value), hann=True)

    def _mean_ratio(self, samples: Samples, ta: float, tb: float, gain: float, hann: bool = False) -> float:
        """``gain`` (|F|, PV per MV unit) over the static ratio of the means over ``[ta, tb]`` (s): |F|/K0."""
        du = held_coefficient(samples.s, samples.u - self.mv0, ta, tb, 0.0, hann).real
        dy = sampled_coefficient(samples.t, samples.y - self._sp, ta, tb, 0.0, hann).real
        return self._sign * du / dy * gain if dy != 0.0 else 0.0

    def _tolerances(self) -> Tolerances:
        c = self.config
        return Tolerances(c.phase_tol_deg, c.gain_tol, c.static_tol, c.noise_tol)

    def _noisy(self) -> bool:
        """True when the measured noise is large enough to scatter the estimates beyond gain_tol."""
        if not self._estimates:
            return False
        return self._noise > _NOISY * self._estimates[-1][0].gain * self.config.amp

    def _since(self) -> float:
        """Estimates whose window starts before this time (s) are not used: a load step, a change of the relay's
        levels or a stall came after them."""
        return max(self._discard_before, self._changed_at, self._stalled_until)

    def _usable(self) -> list[tuple[Point, float]]:
        since = self._since()
        return [e for e, start in zip(self._estimates, self._windows) if start >= since]

    @staticmethod
    def _longest_gap(tt: np.ndarray, start: float, end: float) -> float:
        """The longest time without a sample within ``[start, end]`` (s)."""
        inside = tt[(tt > start) & (tt < end)]
        return float(np.max(np.diff(np.concatenate(([start], inside, [end])))))

    def _succeed(self, point: Point, inverse_gain: float) -> None:
        # Within the resolution of the mean MV shift, a vanishing |F|/K0 is an
        # integrator, and so is a slightly negative one (within its estimate's
        # tolerance: an integrator seen through noise); a clearly negative one
        # (an open-loop unstable process) is reported as it is.
        integrating = inverse_gain * INTEGRATING_RATIO <= 1.0 and inverse_gain > -self.config.static_tol
        static = math.inf if integrating else point.gain / inverse_gain
        fit = self._fit
        static_std = math.inf
        if fit is not None and not integrating and fit.x != 0.0:
            static_std = point.gain * fit.x_std / (fit.x * fit.x)
        time = self._record.time
        duration = time(-1) - time(0)
        discarded = sum(1 for start in self._windows if start < self._discard_before) if fit is not None else 0
        self.result = Identification(
            point=point,
            static_gain=static,
            duration=duration,
            periods=duration * point.omega / (2.0 * math.pi),
            samples=len(self._record),
            hysteresis=self._eps,
            noise_std=self._noise,
            phase_target_deg=self._target_deg,
            phase_moved=self._target_deg != self.config.phase_deg,
            static_gain_std=static_std,
            disturbance=fit is not None or self._unsettled_start(point, inverse_gain),
            periods_discarded=discarded,
            load_estimate=0.0 if fit is None else fit.load_at(time(-1), time(0)),
        )
        self._finish(Code.OK, MESSAGES[Code.OK])

    def _unsettled_start(self, point: Point, x: float) -> bool:
        """True when the PV was still settling at TUNE by more than a load worth following (_LOAD_FRACTION).

        The free response the static ratio took out is ``slope·T`` at the start (T of the model ``x`` fixes).
        """
        slope = self._settling[0]
        if slope == 0.0 or not 0.0 < x < 1.0:
            return False
        tc = slow_memory(x) * 2.0 * math.pi / point.omega
        return abs(slope) * tc >= _LOAD_FRACTION * point.gain * self.config.amp

    # -- helpers ----------------------------------------------------------

    def _estimate(self, samples: Samples, ta: float, tb: float, omega: float, hann: bool) -> complex:
        """F(jω) over ``[ta, tb]`` (s): the PV as sampled, the MV as the process held it (``applied``)."""
        # Means are removed first: over a window that is not exactly whole
        # periods they would leak into the coefficient.
        t, s = samples.t, samples.s
        u = samples.u - held_coefficient(s, samples.u, ta, tb, 0.0, hann).real
        y = samples.y - sampled_coefficient(t, samples.y, ta, tb, 0.0, hann).real
        return self._sign * sampled_coefficient(t, y, ta, tb, omega, hann) / held_coefficient(s, u, ta, tb, omega, hann)

    @staticmethod
    def _lag(value: complex) -> float:
        return (-math.atan2(value.imag, value.real)) % (2.0 * math.pi)

    def _adapt(self, omega: float, lag: float) -> None:
        """Retune the filter for the next period from the period just measured.

        Two things move when the filter changes: the frequency of the cycle and
        the process phase there. The measured pairs ``(ln ω, lag)`` trace the
        process phase curve, and a secant step on it predicts the frequency
        with the requested lag; the loop's phase balance, calibrated on the
        period just measured (it absorbs hysteresis and sampling delays),
        gives the filter phase needed there.
        """
        target = math.radians(self._target_deg)
        offset = math.pi - lag - self._filter.phase(omega)
        # Not from the first whole period: its lag still carries the start's transient (133° where the cycle
        # lags 140°), and a secant through it can even have the wrong sign.
        if self._last is not None and len(self._lags) > 2:
            w_prev, lag_prev = self._last
            dlog = math.log(omega / w_prev)
            if abs(dlog) > 0.005:
                self._slope = min(max((lag - lag_prev) / dlog, 0.2), 5.0)
        self._last = (omega, lag)
        step = min(max((target - lag) / self._slope, -_MAX_LOG_STEP), _MAX_LOG_STEP)
        # Measurements a period after a change still carry its transient;
        # partial steps keep the correction from overshooting.
        omega_next = omega * math.exp(_RELAXATION * step)
        now = self._filter.phase(omega_next)
        self._set_filter(now + _RELAXATION * (math.pi - target - offset - now), omega_next)

    def _set_filter(self, theta: float, omega: float) -> None:
        self._filter.set_phase(theta, omega)
        self._omega = omega
        if self.config.hysteresis is None:
            # Keep the hysteresis at three standard deviations of the noise as
            # it comes out of the filter, so a lead never makes the relay chatter.
            self._eps = 3.0 * self._noise * self._filter.noise_gain(self._dt)

    def _check_oscillation(self, k: int) -> None:
        periods = len(self._rising) - 1
        if periods >= self.config.max_periods:
            self._not_converged(f"after {periods} periods")
            return
        if len(self._switches) < 3:
            return
        if self._record.time(k) - self._record.time(self._switches[-1]) > 5.0 * self._longest_half:
            if self._pushed_away(k):
                self._finish(
                    Code.DISTURBANCE,
                    f"{MESSAGES[Code.DISTURBANCE]}: the relay stayed at one level while the PV moved away from "
                    "the set point (a load or drift larger than amp)",
                )
                return
            self._finish(Code.NO_OSCILLATION, "the oscillation died out (increase amp or reduce hysteresis)")

    def _pushed_away(self, k: int) -> bool:
        """True when, since the last switch, the PV moved away from the set point by more than the cycle's swing.

        A relay held at one level with the error growing is a relay without
        the authority to bring the PV back: something larger than amp pushes it.
        """
        last = self._switches[-1]
        before = self._record.y[self._switches[-3]:last]
        swing = 0.5 * float(np.max(before) - np.min(before)) if len(before) else 0.0
        error = self._sign * (self._sp - self._record.pv(k))
        pushing = error * self._relay > 0.0  # the relay pushes against an error that keeps growing
        return pushing and abs(error) > swing + self._eps

    def _timeout(self) -> None:
        if len(self._switches) < 3:
            self._finish(Code.NO_OSCILLATION, MESSAGES[Code.NO_OSCILLATION] + " within the time limit")
        else:
            self._not_converged("within the time limit")

    def _not_converged(self, when: str) -> None:
        if self._fit is not None:
            self._finish(Code.DISTURBANCE, f"{MESSAGES[Code.DISTURBANCE]}: the estimates did not settle {when} "
                         f"through the load the experiment detected (last fit: step {self._fit.step:+.3g}, "
                         f"ramp {self._fit.ramp:+.3g}/s in MV units)")
            return
        usable = self._usable()[2:]
        if self._noisy() and usable:
            factor = amp_factor(usable, self._tolerances())
            if math.isfinite(factor):
                amp = self.config.amp
                share = self._noise / (usable[-1][0].gain * amp)
                self._finish(
                    Code.NOISE_TOO_HIGH,
                    f"the measurement noise (σ = {self._noise:.3g} PV units, {100 * share:.1f} % of |F|·amp) is too "
                    f"high for amp {amp:g}: the estimates did not settle {when}; raise amp to at least "
                    f"{math.ceil(factor * amp * 100) / 100:g} (× {factor:.2f}) or allow more periods",
                )
                return
        text = f"no convergence {when}"
        if self._stalls:
            # Not the process's fault: say what kept the estimates out.
            text += (f": {len(self._stalls)} estimates were left out because their windows held a time without "
                     f"samples of more than {_STALL:.0%} of a period (the longest {max(self._stalls):.3g} s): the "
                     "link or the machine is too slow for this sample time")
        elif self._estimates:
            lag = -self._estimates[-1][0].phase_deg
            text += (
                f": the process lags {lag:.1f}° where {self.config.phase_deg:g}° was requested"
                + (f" and {self._target_deg:.1f}° aimed at (an unstable process: the requested phase is out of "
                   "its reach)" if self._target_deg != self.config.phase_deg else " (out of reach of this process?)")
            )
        self._finish(Code.NOT_CONVERGED, text)

    def _period_guess(self, dt: float | None) -> float:
        """The oscillation period as well as it is known now (s).

        Measured once a whole period (or half of one) has passed; before, the
        caller's ``expected_period``, else a share of the time limit, else
        ``_SAMPLES_PER_PERIOD`` samples. Before the first switch it is at
        least twice the time since the relay started (the first switch comes
        after a quarter to half a period).
        """
        time = self._record.time
        if len(self._rising) >= 2:
            return time(self._rising[-1]) - time(self._rising[-2])
        if len(self._switches) >= 2:
            return 2.0 * (time(self._switches[-1]) - time(self._switches[-2]))
        c = self.config
        if c.expected_period is not None:
            guess = c.expected_period
        elif math.isfinite(c.time_limit):
            guess = c.time_limit / _LIMIT_SHARE
        else:
            guess = _SAMPLES_PER_PERIOD * (dt if dt else 1.0)
        if self.stage is Stage.RELAY:
            guess = max(guess, 2.0 * (time(-1) - time(self._relay_start)))
        return guess

    def _seconds_left(self) -> float:
        """Estimated seconds to the end: the noise stage's rest plus the periods the stopping rule still needs."""
        samples = len(self._record)
        elapsed = self._record.time(-1) - self._record.time(0) if samples else 0.0
        dt = self._mean_interval()
        noise_left = max(self.config.noise_samples - samples, 0) * (dt or 0.0)
        period = self._period_guess(dt)
        done = max(len(self._rising) - 1, 0)
        needed = _MIN_PERIODS + 1.0
        if len(self._rising) == 0:
            needed += 0.5  # the half period before the first rising switch
        if self._fit is not None or self._noisy():
            # Disturbed or noisy runs average more periods: at least two more.
            needed = max(needed, done + 2.0)
        needed = min(needed, float(self.config.max_periods))
        left = noise_left + max(needed - done, 0.5) * period
        if math.isfinite(self.config.time_limit):
            left = min(left, max(self.config.time_limit - elapsed, 0.0))
        return max(left, dt or period / _SAMPLES_PER_PERIOD)

    def _finish(self, code: Code, message: str) -> None:
        self.stage = Stage.DONE
        self.code = code
        self.message = message
