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
import contextlib
import multiprocessing
import os
import threading
import time
import math
from collections.abc import AsyncIterator, Awaitable, Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

import numpy as np

from drivers.link import Link, LinkError, LoopState, Mode, TuneFlags, Watchdog

from autotuner.engine.outcome import MESSAGES, Code
from autotuner.engine.experiment.relay import RelayConfig, RelayExperiment, Status
from autotuner.engine.result import Trace, TuneResult
from autotuner.engine.simulated_tuning import result_of

# Handshake bits (TBSY, ite) and the watchdog's heartbeat are written this often, wall seconds.
FLAGS_PERIOD = 0.5
# Pauses between read-backs while the device tracks the saved MV, wall seconds (growing from the first).
TRACK_POLL = (0.01, 0.1)
# How often a design worker checks that the process that started it still lives, seconds.
PARENT_CHECK = 0.5
# Worker processes of the design (see _designed), started on first use, and the CPU seconds they spent.
_pool: ProcessPoolExecutor | None = None
_design_cpu = 0.0


async def deadlines(period: float, stop: asyncio.Event | None = None,
                    beat: float | None = None) -> AsyncIterator[float | None]:
    """Sleep until each sample is due, every ``period`` wall seconds from now; yields the due time.

    Due times are ``start + k·period``: a late sample does not delay the next
    ones (no drift); several overdue samples are taken back to back. With
    ``stop``, a wait ends as soon as it is set (yielding None: TBRK acts at
    once, not a sample later); with ``beat``, no wait lasts longer than
    ``beat`` seconds (yielding None between samples: the handshake and the
    device watchdog's heartbeat go on however long the sample time).
    """
    start = time.monotonic()
    k = 0
    while True:
        due = start + k * period
        now = time.monotonic()
        wake = due if beat is None else min(due, now + beat)
        if wake > now:
            if stop is None:
                await asyncio.sleep(wake - now)
            else:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), wake - now)
        if time.monotonic() >= due and not (stop is not None and stop.is_set()):
            yield due
            k += 1
        else:
            yield None


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
    """The message of a loop that could not be handed back."""
    return f"LOOP NOT RESTORED ({why}): the daemon retries; or set mode {Mode(saved.mode).name} and MV {saved.mv:g} by hand"


async def hand_back(link: Link, saved: LoopState, handback: HandBack) -> str:
    """Hand the loop back to ``saved``'s MV and mode, bumplessly; '' on success, else why it is not restored.

    A loop left in MAN at a relay level is the worst outcome, so it keeps
    trying, with growing pauses, for ``handback.window`` seconds (and not
    past ``handback.cap``).
    """
    deadline = time.monotonic() + handback.window
    pause = 0.1
    while True:
        try:
            await hand_back_once(link, saved, handback.track_timeout)
            return ""
        except (LinkError, NotTracking) as exc:  # the cap is read each time: a shutdown may set it meanwhile
            if time.monotonic() + pause > min(deadline, handback.cap):
                return not_restored(saved, str(exc))
            await asyncio.sleep(pause)
            pause = min(2.0 * pause, 2.0)


async def _publish(link: Link, flags: TuneFlags, heartbeat: int | None = None) -> None:
    try:
        await link.write_flags(flags)
        if heartbeat is not None:
            await link.write_heartbeat(heartbeat)
    except LinkError:
        pass  # the handshake is informative; the experiment's own I/O reports link faults


def _ended(restore_error: str, code: Code, ok: bool = False) -> TuneFlags:
    """The handshake bits at a session's end: TBSY off, TE unless it designed gains, ite its code (20 when the
    loop is not handed back)."""
    return TuneFlags(tbsy=False, te=bool(restore_error) or not ok,
                     ite=float(Code.LOOP_NOT_RESTORED if restore_error else code))


async def tune_link(
    link: Link,
    config: RelayConfig,
    ts: float,
    controller: str = "PI",
    ms: float = 1.4,
    apply: bool = False,
    speed: float = 1.0,
    stop: asyncio.Event | None = None,
    on_status: Callable[[Status], None] | None = None,
    handback: HandBack | None = None,
    on_saved: Callable[[LoopState, tuple[float, ...]], Awaitable[str]] | None = None,
    on_handed_back: Callable[[str], None] | None = None,
) -> TuneResult:
    """Run the experiment on the loop behind ``link`` every ``ts`` plant seconds and design ``controller``.

    ``handback``: how the loop is handed back (default :class:`HandBack`());
    its watchdog time is wall seconds, written to the device as ``speed``
    times as many device seconds. ``on_saved(saved, relay_levels)`` is awaited
    once the loop's state is read, before the loop is touched: it records the
    saved state durably and returns '' — or why it could not, and the session
    then ends without touching the loop (HISTORY_UNAVAILABLE): a loop taken
    over without its saved state on record could not be restored after a
    crash. A ``stop`` set by then also ends it untouched (ABORTED).
    """
    handback = HandBack() if handback is None else handback
    if not ts > 0.0 or not speed > 0.0:
        raise ValueError(f"sample time and speed must be positive, got ts={ts}, speed={speed}")
    try:
        saved = await link.read_state()
    except LinkError as exc:
        return TuneResult.failed(Code.LINK_FAULT, f"cannot read the loop: {exc}", controller)

    experiment = RelayExperiment(config, mv0=saved.mv)
    if on_saved is not None and (why := await on_saved(saved, experiment.levels)):
        return TuneResult.failed(Code.HISTORY_UNAVAILABLE, f"{MESSAGES[Code.HISTORY_UNAVAILABLE]}: {why}", controller)
    if stop is not None and stop.is_set():
        return TuneResult.failed(Code.ABORTED, f"{MESSAGES[Code.ABORTED]} before the loop was touched", controller)
    if experiment.done:  # refused before it starts (the relay cannot move the MV): the loop is not touched
        await _publish(link, _ended("", experiment.code))
        return TuneResult.failed(experiment.code, experiment.message, controller)
    times: list[float] = []
    pvs: list[float] = []
    mvs: list[float] = []
    failed = False
    beats = 0
    try:
        await _publish(link, TuneFlags(tbsy=True, te=False, ite=0.0))
        await link.write_mv(saved.mv)
        if handback.watchdog > 0.0:
            await link.write_watchdog(Watchdog(timeout=handback.watchdog * speed, mv=saved.mv, mode=saved.mode))
        await link.write_mode(Mode.MAN)
        start = time.monotonic()
        flags_due = start

        async def handshake(status: Status) -> None:  # TBSY, ite and the heartbeat every FLAGS_PERIOD
            nonlocal flags_due, beats
            if time.monotonic() >= flags_due:
                flags_due = time.monotonic() + FLAGS_PERIOD
                beats += 1  # the heartbeat only feeds an armed watchdog: no extra request otherwise
                await _publish(link, TuneFlags(tbsy=True, te=False, ite=status.ite),
                               beats if handback.watchdog > 0.0 else None)

        async for due in deadlines(ts / speed, stop, FLAGS_PERIOD):
            if stop is not None and stop.is_set():
                experiment.abort()
                break
            if due is None:  # between samples: only the handshake and the heartbeat may be due
                await handshake(experiment.status())
                continue
            before = time.monotonic()
            pv = await link.read_pv()
            after = time.monotonic()
            age = link.pv_age
            t = ((0.5 * (before + after) if age is None else after - age) - start) * speed
            if times and t <= times[-1]:
                continue  # the same time-stamped value again: nothing new to act on
            mv = experiment.step(t, pv)
            if experiment.done:
                break
            before = time.monotonic()
            await link.write_mv(mv)
            # When the MV reached the device: a write the link or a busy machine delayed left the previous MV
            # on the process meanwhile, and the estimates must integrate the MV as the process held it.
            experiment.applied((0.5 * (before + time.monotonic()) - start) * speed)
            times.append(t)
            pvs.append(pv)
            mvs.append(mv)
            if experiment.analysis_pending:
                # A period ended: its analysis (a load fit: tens of ms of CPU) runs off the event loop, so the
                # daemon's other loops, the handshake and an in-process simulated PLC keep their time.
                await asyncio.to_thread(experiment.analyse)
                if experiment.done:
                    break
            status = experiment.status()
            if on_status is not None:
                on_status(status)
            await handshake(status)
    except LinkError as exc:
        experiment.fail(Code.LINK_FAULT, f"{MESSAGES[Code.LINK_FAULT]}: {exc}")
    except (asyncio.CancelledError, Exception):  # cancelled, or a bug: handed back below, TBSY must not stay set
        experiment.abort()
        failed = True
        raise
    finally:
        restore_error = await hand_back(link, saved, handback)
        if on_handed_back is not None:
            on_handed_back(restore_error)
        if failed:  # no result follows to end the handshake with
            await _publish(link, _ended(restore_error, Code.ABORTED))
    result = await _designed(experiment, controller, ms, _trace(times, pvs, mvs), restore_error)
    if result.ok and apply:
        try:
            await link.write_gains(result.design.gains)
        except LinkError as exc:
            result = TuneResult(Code.LINK_FAULT, f"gains not written: {exc}", controller,
                                result.identification, result.design, result.trace)
    await _publish(link, _ended(restore_error, result.code, result.ok))
    if on_status is not None:
        on_status(experiment.status())
    return result


async def _designed(experiment: RelayExperiment, controller: str, ms: float, trace: Trace,
                    restore_error: str) -> TuneResult:
    """The result with its design, computed in a worker process.

    The design takes 0.1 s (PI) to 0.4 s (PID) of CPU. In a thread it would
    hold the GIL most of that time, and many sessions of a daemon ending
    together would stall every other loop's sampling.
    """
    global _pool, _design_cpu
    args = (experiment, controller, ms, trace, restore_error)
    if experiment.result is None:  # nothing identified, nothing to design: no worker needed
        return _result(*args)
    if _pool is None:
        # spawn: a worker inherits none of the daemon's sockets or its event loop; one core left for sampling.
        _pool = ProcessPoolExecutor(max(1, (os.cpu_count() or 2) - 1), mp_context=multiprocessing.get_context("spawn"),
                                    initializer=_follow_parent, initargs=(os.getpid(),))
    try:
        result, cpu = await asyncio.get_running_loop().run_in_executor(_pool, _timed_result, *args)
    except BrokenProcessPool:  # a worker was killed: the result still comes, from a thread
        _pool = None
        return await asyncio.to_thread(_result, *args)
    _design_cpu += cpu
    return result


def _follow_parent(parent: int) -> None:
    """In a design worker: exit when the daemon is gone (killed by a signal, it never shuts its pool down)."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_CHECK)
        os._exit(0)

    threading.Thread(target=watch, name="follow-parent", daemon=True).start()


def close_design_pool() -> None:
    """Stop the design's worker processes (a daemon that stops; the next design starts them again)."""
    global _pool
    if _pool is not None:
        _pool.shutdown(wait=True)
        _pool = None


def design_cpu() -> float:
    """CPU seconds the design's worker processes have spent in this process's sessions so far."""
    return _design_cpu


def _timed_result(experiment: RelayExperiment, controller: str, ms: float, trace: Trace,
                  restore_error: str) -> tuple[TuneResult, float]:
    cpu0 = time.process_time()
    return _result(experiment, controller, ms, trace, restore_error), time.process_time() - cpu0


def _trace(t: list[float], pv: list[float], mv: list[float]) -> Trace:
    return Trace(np.asarray(t, dtype=float), np.asarray(pv, dtype=float), np.asarray(mv, dtype=float))


def _result(experiment: RelayExperiment, controller: str, ms: float, trace: Trace, restore_error: str) -> TuneResult:
    result = result_of(experiment, trace, controller, ms)
    if not restore_error:
        return result
    code = Code.LINK_FAULT if result.code is Code.OK else result.code
    return TuneResult(code, f"{result.message}; {restore_error}", controller, result.identification,
                      result.design, trace)
