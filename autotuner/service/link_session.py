"""One tuning of a loop in the field, in real time, through a :class:`drivers.link.Link`.

The session owns the clock. It saves the loop (mode, MV, gains), takes it
over in MAN, samples it on a deadline schedule (sample k is due at
``start + k·ts``, so delays do not accumulate), feeds the experiment the
*measured* sample times and the times its writes reached the device
(jitter and a stalled write then do not bias the identified point),
and whatever way the experiment ends — success, TBRK, PV limits, link loss,
cancellation (Ctrl-C, SIGTERM) — hands the loop back (:func:`hand_back`):
the saved MV is written, read back from the device until the PID unit has
taken it (it tracks the manual MV in MAN), and only then the saved mode is
written, so the first AUTO output is the saved MV (docs/handback.md). While
the session owns the loop the device's watchdog is armed and fed a
heartbeat, so a tuner that dies leaves a loop that falls back by itself.
New gains are written only on success and only if asked.

``speed`` runs a simulated plant's clock faster than the wall clock: the
session then samples every ``ts/speed`` wall seconds and scales the measured
times back to plant seconds.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import math
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field, replace

import numpy as np

from drivers.link import Fenced, Link, LinkError, LoopState, Mode, Sample, TuneFlags, Watchdog

from autotuner.engine.outcome import MESSAGES, Code
from autotuner.engine.experiment.relay import RelayConfig, RelayExperiment, Status
from autotuner.engine.result import Trace, TuneResult
from autotuner.engine.simulated_tuning import DesignJob
from autotuner.service.design_pool import Outcome, designed

# Handshake bits (TBSY, ite) and the watchdog's heartbeat are written this often, wall seconds.
FLAGS_PERIOD = 0.5
# Two heartbeats that may have reached the device this fraction of its watchdog's timeout apart (or more) make the
# session read the device for the watchdog's hand-back (a margin for the device's own clock and cycle).
WATCHDOG_SUSPECT = 0.5
# Pauses between read-backs while the device tracks the saved MV, wall seconds (growing from the first).
TRACK_POLL = (0.01, 0.1)
# A sample the session itself starts late (its event loop, its machine — not the link) by more than what the
# experiment tolerates (RelayExperiment.stall_tolerance: a tenth of a period, at least 3 sample intervals) leaves
# a gap its estimates cannot use. More than OVERLOAD_COUNT such samples among the last OVERLOAD_WINDOW: the session
# ends OVERLOADED (an isolated one only costs the estimates around it).
OVERLOAD_COUNT, OVERLOAD_WINDOW = 5, 100
# Codes that blame the process (or its surroundings); after an overload the tuner's lateness may be the cause.
BLAMES_PROCESS = frozenset({Code.NO_OSCILLATION, Code.NOT_CONVERGED, Code.DISTURBANCE, Code.NOISE_TOO_HIGH,
                            Code.NOT_STABILISABLE, Code.UNSTABLE_DEAD_TIME_TOO_LONG})


async def deadlines(period: float, stop: asyncio.Event | None = None,
                    beat: float | None = None) -> AsyncIterator[float | None]:
    """Sleep until each sample is due, every ``period`` wall seconds from now; yields the due time.

    Due times are ``start + k·period``: a late sample does not delay the next
    ones (no drift); several overdue samples are taken back to back. With
    ``stop``, a wait ends as soon as it is set (yielding None: TBRK acts at
    once, not a sample later); with ``beat``, no wait lasts longer than
    ``beat`` seconds (yielding None between samples: the handshake and the
    device watchdog's heartbeat go on however long the sample time). One
    waiter on ``stop`` serves every wait (no task per sample); close the
    generator (``contextlib.aclosing``) to end it.
    """
    start = time.monotonic()
    k = 0
    stopped = None if stop is None else asyncio.ensure_future(stop.wait())
    try:
        while True:
            due = start + k * period
            now = time.monotonic()
            wake = due if beat is None else min(due, now + beat)
            if wake > now:
                if stopped is None:
                    await asyncio.sleep(wake - now)
                else:
                    await asyncio.wait({stopped}, timeout=wake - now)
            if time.monotonic() >= due and not (stop is not None and stop.is_set()):
                yield due
                k += 1
            else:
                yield None
    finally:
        if stopped is not None:
            stopped.cancel()


@dataclass
class HandBack:
    """How loops are handed back; wall seconds (docs/handback.md, config key ``handback``).

    ``window``: one restore keeps trying this long (then the loop is *not
    restored*; the daemon retries it later). ``track_timeout``: longest wait,
    per try, for the device's MV to read back the saved MV before the mode is
    written. ``watchdog``: the device's watchdog timeout armed while a session
    owns the loop (0: not armed). ``cap``: a monotonic time after which no
    new try starts (set by a daemon that shuts down, so its hand-back is
    bounded); infinite normally.
    """

    window: float = 30.0
    track_timeout: float = 5.0
    watchdog: float = 0.0
    cap: float = math.inf


class NotTracking(Exception):
    """The device does not take the saved MV (its actual MV does not read it back in time)."""


async def read_back(link: Link, holds: Callable[[LoopState], bool], timeout: float) -> tuple[bool, LoopState]:
    """Read the loop until ``holds(state)`` or ``timeout`` wall seconds pass; whether it held, and the state read
    last.

    Why a loop and not one read: a write takes effect at the device's next cycle, and on a cyclic transport
    (CAN) the frames it sent before that cycle may still be on their way; one read right after a write can show
    the state before it.
    """
    deadline = time.monotonic() + timeout
    pause = TRACK_POLL[0]
    while True:
        state = await link.read_state()
        if holds(state):
            return True, state
        if time.monotonic() + pause > deadline:
            return False, state
        await asyncio.sleep(pause)
        pause = min(2.0 * pause, TRACK_POLL[1])


async def track(link: Link, mv: float, timeout: float) -> LoopState:
    """Write the manual MV ``mv`` and read the loop back until its actual MV is ``mv`` within the link's resolution.

    The state read last; NotTracking after ``timeout`` wall seconds. On a
    PLC whose PID unit tracks the manual MV in MAN, an actual MV equal to the
    written one means the unit has run with it: its state follows, and the
    next AUTO output starts from ``mv``.
    """
    await link.write_mv(mv)
    tolerance = link.mv_resolution(mv)
    held, state = await read_back(link, lambda s: abs(s.mv - mv) <= tolerance, timeout)
    if not held:
        raise NotTracking(f"the actual MV reads {state.mv:g} after {timeout:g} s, not the {mv:g} written "
                          f"(mode {Mode(state.mode).name}): the device does not take the manual MV")
    return state


async def hand_back_once(link: Link, saved: LoopState, track_timeout: float) -> None:
    """One try of the bumpless hand-back: saved MV until read back, watchdog off, saved mode until read back.

    Raises LinkError or NotTracking.
    """
    await track(link, saved.mv, track_timeout)
    await link.write_watchdog(Watchdog())
    mode = Mode(saved.mode)
    await link.write_mode(mode)
    held, state = await read_back(link, lambda s: s.mode is mode, track_timeout)
    if not held:
        raise NotTracking(f"mode reads {Mode(state.mode).name} {track_timeout:g} s after {mode.name} was written")


def not_restored(saved: LoopState, why: str) -> str:
    """The message of a loop that could not be handed back, ``why`` being the last try's error (made here, once:
    messages never nest)."""
    return f"LOOP NOT RESTORED ({why}): the daemon retries; or set mode {Mode(saved.mode).name} and MV {saved.mv:g} by hand"


def watchdog_fell_back(flags: TuneFlags) -> bool:
    """The device shows its watchdog's hand-back (TBSY cleared, TE and ite 22): that code is the device's word on
    how the loop came back, and nothing the tuner writes afterwards may overwrite it."""
    return not flags.tbsy and flags.te and flags.ite == float(Code.WATCHDOG_FALLBACK)


async def fell_back(link: Link) -> bool:
    """Whether the device shows its watchdog's hand-back now (False if its flags cannot be read)."""
    try:
        return watchdog_fell_back(await link.read_flags())
    except LinkError:
        return False


async def hand_back(link: Link, saved: LoopState, handback: HandBack,
                    still_held: Callable[[], Awaitable[bool]] | None = None) -> str:
    """Hand the loop back to ``saved``'s MV and mode, bumplessly; '' on success, else why it is not restored (the
    last try's error: :func:`not_restored` makes the message).

    A loop left in MAN at a relay level is the worst outcome, so it keeps
    trying, with growing pauses, for ``handback.window`` seconds (and not
    past ``handback.cap``) — but not once the daemon is fenced off the loop
    (:class:`Fenced`: its lease lost, the new owner restores it), nor once
    ``still_held()``, awaited before each try, is False (the device restarted:
    its own defaults hold the loop, nothing is written; '' is returned).
    """
    deadline = time.monotonic() + handback.window
    pause = 0.1
    while True:
        try:
            if still_held is not None and not await still_held():
                return ""
            await hand_back_once(link, saved, handback.track_timeout)
            return ""
        except Fenced as exc:  # not ours any more: the loop's new owner restores it, this daemon writes nothing
            return str(exc)
        except (LinkError, NotTracking) as exc:  # the cap is read each time: a shutdown may set it meanwhile
            if time.monotonic() + pause > min(deadline, handback.cap):
                return str(exc) or type(exc).__name__
            await asyncio.sleep(pause)
            pause = min(2.0 * pause, 2.0)


async def _publish(link: Link, flags: TuneFlags, heartbeat: int | None = None) -> None:
    try:
        await link.write_flags(flags)
        if heartbeat is not None:
            await link.write_heartbeat(heartbeat)
    except LinkError:
        pass  # the handshake is informative; the experiment's own I/O reports link faults


async def _end_handshake(link: Link, restore_error: str, code: Code, ok: bool = False) -> None:
    """The handshake bits at a session's end (:func:`_ended`); a loop not handed back whose device shows its
    watchdog's hand-back keeps the device's 22 (the device did hand it back)."""
    if restore_error and await fell_back(link):
        return
    await _publish(link, _ended(restore_error, code, ok))


def _ended(restore_error: str, code: Code, ok: bool = False) -> TuneFlags:
    """The handshake bits at a session's end: TBSY off, TE unless it designed gains, ite its code (20 when the
    loop is not handed back)."""
    return TuneFlags(tbsy=False, te=bool(restore_error) or not ok,
                     ite=float(Code.LOOP_NOT_RESTORED if restore_error else code))


@dataclass(frozen=True)
class SessionPlan:
    """What one session on a live loop runs: the experiment's settings, its clock and what is designed.

    ``relay``: the experiment (with the loop's limits and the field
    tolerances); ``ts``: sample time, plant seconds; ``controller`` "PI" or
    "PID" designed for maximum sensitivity ``ms``; ``apply``: write the gains
    on success; ``speed``: plant seconds per wall second (a simulated plant
    runs faster); ``handback``: how the loop is handed back (its watchdog time
    is wall seconds, written to the device as ``speed`` times as many device
    seconds).
    """

    relay: RelayConfig
    ts: float
    controller: str = "PI"
    ms: float = 1.4
    apply: bool = False
    speed: float = 1.0
    handback: HandBack = field(default_factory=HandBack)

    def __post_init__(self) -> None:
        if not self.ts > 0.0 or not self.speed > 0.0:
            raise ValueError(f"sample time and speed must be positive, got ts={self.ts}, speed={self.speed}")


def analysed(experiment: RelayExperiment) -> tuple[RelayExperiment, float]:
    """Run the pending analysis of ``experiment`` (in a worker thread or process); it and the CPU seconds it took."""
    start = time.thread_time()
    experiment.analyse()
    return experiment, time.thread_time() - start


#: How a session has a period's analysis run off its event loop (:attr:`SessionHooks.analyse`).
Analyse = Callable[[RelayExperiment], Awaitable[tuple[RelayExperiment, float]]]


async def analysed_in_thread(experiment: RelayExperiment) -> tuple[RelayExperiment, float]:
    """:func:`analysed` in a thread of this process (the analysis holds its GIL most of the time)."""
    return await asyncio.to_thread(analysed, experiment)


@dataclass
class SessionHooks:
    """How a session reports to whoever runs it; every member optional.

    ``stop``: set to abort (TBRK), at once. ``on_status(status)``: after each
    sample. ``on_saved(saved, relay_levels)``: awaited once the loop's state
    is read, before it is touched; it records the saved state durably and
    returns '' — or why it could not, and the session then ends without
    touching the loop (HISTORY_UNAVAILABLE): a loop taken over without its
    saved state on record could not be restored after a crash.
    ``on_handed_back(error)``: once the hand-back is over ('' or why not).
    ``on_timing(late, own, tolerance)``: per sample, wall seconds its PV read
    completed behind its due time, the part of that the session's own process
    caused (not the link: the event loop, the analysis, a starved CPU), and the
    own lateness the experiment tolerates now (:class:`Overload`).
    ``on_analysis(cpu, elsewhere)``: per period, the CPU seconds its analysis
    took, and whether in another process. ``design(job)``: the design of the
    ended experiment (default: the design pool of this process).
    ``analyse()``: at each period's end, how to analyse it: a function that
    runs a period's pending analysis (:func:`analysed`) in another process —
    the experiment analysed (a copy) and the CPU seconds it took —, not
    awaited: the reads go on meanwhile; or None (also when ``analyse`` is
    None): in a thread of this process, awaited before the next read (the
    thread holds the GIL the reads need: reading on while it runs only delays
    the switches).
    """

    stop: asyncio.Event | None = None
    on_status: Callable[[Status], None] | None = None
    on_saved: Callable[[LoopState, tuple[float, ...]], Awaitable[str]] | None = None
    on_handed_back: Callable[[str], None] | None = None
    on_timing: Callable[[float, float, float], None] | None = None
    on_analysis: Callable[[float, bool], None] | None = None
    design: Callable[[DesignJob], Awaitable[Outcome]] = designed
    analyse: Callable[[], Analyse | None] | None = None


class Overload:
    """The session's own lateness, sample by sample, judged against what the experiment tolerates.

    A sample whose read the session started late for reasons of its own (not
    waiting on the link) by more than ``tolerance`` (wall seconds: the
    experiment's stall tolerance) is late by the session's fault; the session
    can no longer keep its schedule when more than :data:`OVERLOAD_COUNT` of
    the last :data:`OVERLOAD_WINDOW` samples are. ``count``: such samples so
    far; ``longest``: the longest own delay of any sample, whatever the tolerance then (early in a
    run the period is not known yet, and the tolerance is wider than the
    experiment's at its end), wall seconds.
    """

    def __init__(self) -> None:
        self.count = 0
        self.longest = 0.0
        self.io_end = -math.inf  # when the session's last link call ended (monotonic)
        self._samples = 0
        self._late: collections.deque[int] = collections.deque()  # the numbers of the late samples in the window

    def sample(self, due: float, read_start: float, tolerance: float) -> float:
        """The session's own part of the lateness of the read started at ``read_start`` for ``due`` (monotonic
        wall seconds), judged against ``tolerance`` (wall seconds)."""
        self._samples += 1
        own = max(read_start - max(due, self.io_end), 0.0)
        self.delayed(own, tolerance)
        while self._late and self._late[0] <= self._samples - OVERLOAD_WINDOW:
            self._late.popleft()
        return own

    def delayed(self, delay: float, tolerance: float) -> None:
        """Something of the latest sample's the session did ``delay`` wall seconds late by its own fault — its
        read, or its MV's write (a relay switch, stepped only once the last period's analysis was over) —, judged
        against ``tolerance`` (wall seconds)."""
        self.longest = max(self.longest, delay)
        if delay > tolerance:
            self.count += 1
            self._late.append(self._samples)

    @property
    def exceeded(self) -> bool:
        """True when the session can no longer keep its schedule within the experiment's tolerance."""
        return len(self._late) > OVERLOAD_COUNT

    def message(self, speed: float) -> str:
        """The overload's message (what the experiment saw, in plant seconds)."""
        late = (f"{self.count} samples were taken (or their relay switches written)" if self.count else
                "a sample was taken (or its relay switch written)")
        return (f"{MESSAGES[Code.OVERLOADED]}: {late} "
                f"later than the experiment tolerates by the tuner itself (the longest {self.longest * speed:.3g} s "
                "late, not the link's delay): its "
                "machine or process is loaded beyond what the experiment tolerates; the loop was handed back — "
                "retry when fewer loops tune at once")


async def tune_link(link: Link, plan: SessionPlan, hooks: SessionHooks | None = None) -> TuneResult:
    """Run the experiment of ``plan`` on the loop behind ``link``, hand the loop back, design; the result.

    The loop is sampled every ``plan.ts`` plant seconds (``plan.ts /
    plan.speed`` wall seconds); ``hooks`` report and abort (:class:`SessionHooks`).
    A session whose own lateness exceeds what the experiment tolerates
    (:class:`Overload`) ends with OVERLOADED, and a verdict about the process
    reached after such lateness (no oscillation, a disturbance, an unstable
    process, …) is reported as OVERLOADED too: the tuner's lateness, not the
    process, may be its cause.
    """
    hooks = SessionHooks() if hooks is None else hooks
    controller = plan.controller
    try:
        saved = await link.read_state()
    except LinkError as exc:
        return TuneResult.failed(Code.LINK_FAULT, f"cannot read the loop: {exc}", controller)
    experiment = RelayExperiment(plan.relay, mv0=saved.mv)
    if hooks.on_saved is not None and (why := await hooks.on_saved(saved, experiment.levels)):
        return TuneResult.failed(Code.HISTORY_UNAVAILABLE, f"{MESSAGES[Code.HISTORY_UNAVAILABLE]}: {why}", controller)
    if hooks.stop is not None and hooks.stop.is_set():
        return TuneResult.failed(Code.ABORTED, f"{MESSAGES[Code.ABORTED]} before the loop was touched", controller)
    if experiment.done:  # refused before it starts (the relay cannot move the MV): the loop is not touched
        await _publish(link, _ended("", experiment.code))
        return TuneResult.failed(experiment.code, experiment.message, controller)
    sampling = _Sampling(link, experiment, plan, hooks)
    del experiment  # an analysis in a worker process returns its own copy: sampling.experiment is the one
    failed = False
    try:
        await _take_over(link, saved, plan)
        await sampling.run()
    except LinkError as exc:
        sampling.experiment.fail(Code.LINK_FAULT, f"{MESSAGES[Code.LINK_FAULT]}: {exc}")
    except (asyncio.CancelledError, Exception):  # cancelled, or a bug: handed back below, TBSY must not stay set
        await sampling.settled()
        sampling.experiment.abort()
        failed = True
        raise
    finally:
        # A loop the device's watchdog has handed back is not handed back again (it is in its saved mode, its
        # MV the controller's: the hand-back's tracking could never succeed, and its writes would overwrite 22);
        # nor one that restarted or someone took (the session writes nothing more to it).
        restore_error = "" if sampling.fell_back or sampling.hands_off else await hand_back(
            link, saved, plan.handback, sampling.not_restarted)
        if hooks.on_handed_back is not None:
            hooks.on_handed_back(restore_error)
        if failed and not sampling.hands_off:  # no result follows to end the handshake with
            await _end_handshake(link, restore_error, Code.ABORTED)
    result = _restored(await _result(hooks, sampling.design_job(), sampling.trace()), saved, restore_error)
    if sampling.hands_off:
        if hooks.on_status is not None:
            hooks.on_status(sampling.experiment.status())
        return result if sampling.restarted in result.message else replace(
            result, message=f"{result.message}; then {sampling.restarted}")
    if result.ok and plan.apply:
        try:
            await link.write_gains(result.design.gains)
        except LinkError as exc:
            result = TuneResult(Code.LINK_FAULT, f"gains not written: {exc}", controller,
                                result.identification, result.design, result.trace)
    await _end_handshake(link, restore_error, result.code, result.ok)
    if hooks.on_status is not None:
        hooks.on_status(sampling.experiment.status())
    return result


async def _take_over(link: Link, saved: LoopState, plan: SessionPlan) -> None:
    """TBSY, the saved MV as the manual one, the watchdog armed (if asked) with the saved state, then MAN."""
    await _publish(link, TuneFlags(tbsy=True, te=False, ite=0.0))
    await link.write_mv(saved.mv)
    if plan.handback.watchdog > 0.0:
        await link.write_watchdog(Watchdog(timeout=plan.handback.watchdog * plan.speed, mv=saved.mv,
                                           mode=saved.mode))
    await link.write_mode(Mode.MAN)


class _Sampling:
    """The experiment driven through ``link`` on the schedule of ``plan``, reported through ``hooks``; the
    samples it took (``t`` plant seconds, ``pv``, ``mv``) and its own lateness (``overload``, judged against
    ``tolerance``: :meth:`observe`)."""

    def __init__(self, link: Link, experiment: RelayExperiment, plan: SessionPlan, hooks: SessionHooks) -> None:
        self.link, self.experiment, self.plan, self.hooks = link, experiment, plan, hooks
        self.t: list[float] = []
        self.pv: list[float] = []
        self.mv: list[float] = []
        self.overload = Overload()
        self._start = 0.0
        self._flags_due = 0.0
        self._beats = 0
        self._beat_sent = 0.0  # when the last heartbeat write started, or the watchdog was armed (monotonic)
        self._suspect_until = -math.inf  # the device is read for its watchdog's hand-back until then
        self.fell_back = False  # the device's watchdog handed the loop back during the experiment
        self.hands_off = False  # the device restarted, or someone took the loop: nothing more may be written
        self.restarted = ""  # how the device was seen to restart
        self._boot: int | None = None  # the device's boot token at the session's first sample
        self._in_man = False  # a sample of this session has read the loop in MAN
        self._read: collections.deque[tuple[float, float]] = collections.deque()  # (t, PV) read, not stepped yet
        self._last_t = -math.inf  # the time of the latest sample read, plant seconds
        self._written = experiment.mv0  # the MV last written to the device (the saved one at the take-over)
        self._analysis: asyncio.Future[tuple[RelayExperiment, float]] | None = None  # the period's, off the loop
        self._elsewhere = False  # whether that analysis runs in another process
        self._status: Status  # the experiment's status after its latest step outside an analysis (observe)
        self.tolerance = 0.0  # the own lateness it tolerated then, wall seconds (observe)
        self.observe()

    async def run(self) -> None:
        """Sample until the experiment ends (or ``hooks.stop`` aborts it); LinkError if the link fails."""
        self._start = self._flags_due = self._beat_sent = time.monotonic()  # the watchdog was armed just before
        stop = self.hooks.stop
        schedule = deadlines(self.plan.ts / self.plan.speed, stop, FLAGS_PERIOD)
        try:
            async with contextlib.aclosing(schedule):
                async for due in schedule:
                    if stop is not None and stop.is_set():
                        await self.settled()
                        self.experiment.abort()
                        return
                    if due is None:  # between samples: only the handshake and the heartbeat may be due
                        await self._handshake(self._status)
                        if self.experiment.done:
                            return
                    elif not await self._sample(due) or self.experiment.done:
                        return
        finally:
            await self.settled()

    async def _sample(self, due: float) -> bool:
        """One sample due at ``due``: its PV read, then (unless the last period's analysis still runs) the
        experiment's steps and the MV written; False once the experiment has ended."""
        link, speed, hooks = self.link, self.plan.speed, self.hooks
        before = time.monotonic()
        own = self.overload.sample(due, before, self.tolerance)
        sample = await link.read_sample()
        after = time.monotonic()
        if hooks.on_timing is not None:
            hooks.on_timing(after - due, own, self.tolerance)
        if self.overload.exceeded:
            await self._fail(Code.OVERLOADED, self.overload.message(speed))
            return False
        if not await self._still_held(sample):
            return False
        age = link.pv_age
        t = ((0.5 * (before + after) if age is None else after - age) - self._start) * speed
        self.overload.io_end = time.monotonic()
        if t <= self._last_t:
            return True  # the same time-stamped value again: nothing new to act on
        self._last_t = t
        self._read.append((t, sample.pv))
        if self._analysis is not None:
            if not self._analysis.done():
                return True  # stepped once the analysis is over: the reads keep their schedule meanwhile
            await self.settled()
            if self.experiment.done:
                return False
        return await self._catch_up()

    async def _catch_up(self) -> bool:
        """Step the experiment through the samples read and not stepped yet, write the MV it asks for, start the
        analysis of a period that ended (in a worker process, not awaited: the next samples are read on time
        while it runs; in a thread of this process, awaited); False once the experiment has ended.

        The MV reaches the device once the samples read during an analysis are stepped: when one of them changed
        it, the experiment is told when (``applied``), and from then on of every later one (their MV arrived no
        sooner), and the delay counts as the session's own lateness."""
        experiment, speed = self.experiment, self.plan.speed
        moved = None  # the time of the first sample whose MV has not reached the device yet (plant seconds)
        while self._read:
            t, pv = self._read.popleft()
            mv = experiment.step(t, pv)
            if experiment.done:
                return False
            self.t.append(t)
            self.pv.append(pv)
            self.mv.append(mv)
            if moved is None and mv != self._written:
                moved = t
            if self._read and not experiment.analysis_pending:
                if moved is not None:
                    experiment.applied((time.monotonic() - self._start) * speed)
                continue
            before = time.monotonic()
            await self.link.write_mv(mv)
            self.overload.io_end = time.monotonic()
            # When the MV reached the device: a write the link or a busy machine delayed left the previous MV on
            # the process meanwhile, and the estimates must integrate the MV as the process held it.
            arrived = (0.5 * (before + self.overload.io_end) - self._start) * speed
            experiment.applied(arrived)
            self._written = mv
            if moved is not None:
                self.overload.delayed((arrived - moved) / speed, self.tolerance)
                moved = None
            if experiment.analysis_pending:
                # A period ended: its analysis runs off the event loop, so the other loops of this process and
                # the handshake keep their time, and so do this loop's reads when it runs in another process.
                analyse = None if self.hooks.analyse is None else self.hooks.analyse()
                self._analysis = asyncio.ensure_future((analyse or analysed_in_thread)(experiment))
                self._elsewhere = analyse is not None
                if analyse is None:
                    await self.settled()
                    experiment = self.experiment
                    if experiment.done:
                        return False
                break
        if self._analysis is None:
            self.observe()
        if self.hooks.on_status is not None:
            self.hooks.on_status(self._status)
        await self._handshake(self._status)
        return True

    def observe(self) -> None:
        """Read the experiment after its latest steps, outside an analysis: its status (what the handshake
        publishes) and the own lateness it tolerates now (``tolerance``, wall seconds: its stall tolerance, wide
        while the period is not known, narrower once it is measured)."""
        self._status = self.experiment.status()
        self.tolerance = self.experiment.stall_tolerance / self.plan.speed

    async def settled(self) -> None:
        """Wait for the period's analysis in flight, if any: nothing else touches the experiment while a worker
        thread analyses it (a thread cannot be interrupted; an analysis is bounded: docs/experiment.md)."""
        if self._analysis is None:
            return
        self.experiment, cpu = await asyncio.shield(self._analysis)
        self._analysis = None
        if self.hooks.on_analysis is not None:
            self.hooks.on_analysis(cpu, self._elsewhere)

    async def _fail(self, code: Code, message: str) -> None:
        """End the experiment with ``code`` and ``message`` once no analysis runs."""
        await self.settled()
        self.experiment.fail(code, message)

    async def _handshake(self, status: Status) -> None:
        """TBSY, ite and the heartbeat every :data:`FLAGS_PERIOD` (the heartbeat only to an armed watchdog).

        Once two heartbeats may have reached the device a good part of the
        watchdog's timeout apart (:data:`WATCHDOG_SUSPECT` of it, between the
        start of one write and the end of the next: a slow link), the device is
        read first, over the next timeout: when it shows its watchdog's hand-back
        the experiment ends with its code 22, never overwritten by TBSY and a
        countdown, and the loop is left as the device handed it back. (Not read
        otherwise: a heartbeat on time cannot have let the watchdog fall back.)
        """
        if time.monotonic() < self._flags_due:
            return
        self._flags_due = time.monotonic() + FLAGS_PERIOD
        timeout = self.plan.handback.watchdog
        if time.monotonic() < self._suspect_until and await self._taken_back():
            self.fell_back = True
            await self._fail(Code.WATCHDOG_FALLBACK, f"{MESSAGES[Code.WATCHDOG_FALLBACK]}: its heartbeat came "
                             f"more than {timeout:g} s apart (a slow link); the loop is as the device handed it back")
            return
        self._beats += 1
        sent = time.monotonic()
        await _publish(self.link, TuneFlags(tbsy=True, te=False, ite=status.ite), self._beats if timeout > 0 else None)
        self.overload.io_end = time.monotonic()
        if timeout > 0.0 and self.overload.io_end - self._beat_sent >= WATCHDOG_SUSPECT * timeout:
            self._suspect_until = self.overload.io_end + timeout
        self._beat_sent = sent

    async def _still_held(self, sample: Sample) -> bool:
        """Whether the loop is still as the session holds it (read with each sample, no request of its own); else
        the experiment ends at once and the session writes nothing more: the device restarted (its boot token
        changed: a link fault, its registers at their defaults), or the loop left MAN after a sample had read it
        in MAN (the device's watchdog: 22, its own code kept; anyone else: an intervention, 21)."""
        if self._restarted(sample):
            await self._fail(Code.LINK_FAULT, f"{MESSAGES[Code.LINK_FAULT]}: {self.restarted}")
            return False
        if sample.mode is Mode.MAN:
            self._in_man = True
            return True
        if not self._in_man:
            return True  # (the session's MAN may not have reached the device's scan yet)
        if self.plan.handback.watchdog > 0.0 and await fell_back(self.link):
            self.fell_back = True
            await self._fail(Code.WATCHDOG_FALLBACK, f"{MESSAGES[Code.WATCHDOG_FALLBACK]}: the loop is as the "
                             "device handed it back")
            return False
        self.hands_off = True
        await self._fail(Code.OPERATOR_INTERVENTION, f"{MESSAGES[Code.OPERATOR_INTERVENTION]}: the loop left MAN "
                         f"during the session ({Mode(sample.mode).name} read), taken by someone else: nothing more "
                         "was written to it")
        return False

    def _restarted(self, sample: Sample) -> bool:
        """Whether ``sample``'s boot token shows the device restarted since the session's first sample (then
        ``hands_off`` and ``restarted`` say so)."""
        if self._boot is None:
            self._boot = sample.boot
        elif sample.boot is not None and sample.boot != self._boot:
            self.hands_off = True
            self.restarted = (f"the device restarted during the session (its boot token went from {self._boot} to "
                              f"{sample.boot}), its registers back at their defaults: nothing more was written to it")
        return self.hands_off

    async def not_restarted(self) -> bool:
        """Whether the device has not restarted since the session's first sample (read now; True when it cannot be
        read: the hand-back's own try reports that)."""
        try:
            return not self._restarted(await self.link.read_sample())
        except LinkError:
            return True

    async def _taken_back(self) -> bool:
        """Whether the armed watchdog has handed the loop back: the device shows it (TE, ite 22), or the loop is
        out of MAN — a mode the session did not write, and the flags may not show it: a flag write of the
        session's own, in flight on a slow link, can land after the device's and overwrite its 22. False when
        the device cannot be read (the experiment's own I/O reports link faults)."""
        try:
            return watchdog_fell_back(await self.link.read_flags()) or \
                (await self.link.read_state()).mode is not Mode.MAN
        except LinkError:
            return False

    def design_job(self) -> DesignJob:
        """What the design gets: the ended experiment's, or an overload's when the verdict may be the tuner's."""
        plan, overload = self.plan, self.overload
        job = DesignJob.of(self.experiment, plan.controller, plan.ms)
        # (Also a delay the tolerance of its moment let pass, beyond what the experiment tolerates at its end.)
        if job.code in BLAMES_PROCESS and (overload.count or overload.longest > self.tolerance):
            job = DesignJob(None, Code.OVERLOADED, f"{overload.message(plan.speed)} (the experiment had ended: "
                            f"{job.message})", plan.controller, plan.ms, plan.relay.amp)
        return job

    def trace(self) -> Trace:
        """The samples taken."""
        return Trace(np.asarray(self.t, dtype=float), np.asarray(self.pv, dtype=float),
                     np.asarray(self.mv, dtype=float))


async def _result(hooks: SessionHooks, job: DesignJob, trace: Trace) -> TuneResult:
    """The experiment's result with its design (``hooks.design``: a worker process; nothing to design without an
    identification)."""
    code, message, design = job.run() if job.identification is None else await hooks.design(job)
    return TuneResult(code, message, job.controller, job.identification, design, trace)


def _restored(result: TuneResult, saved: LoopState, restore_error: str) -> TuneResult:
    """``result`` as the hand-back leaves it: a loop not handed back is a failure (LINK_FAULT if it was ok)."""
    if not restore_error:
        return result
    code = Code.LINK_FAULT if result.code is Code.OK else result.code
    return TuneResult(code, f"{result.message}; {not_restored(saved, restore_error)}", result.controller,
                      result.identification, result.design, result.trace)
