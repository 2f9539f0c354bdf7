"""One tuning of a loop in the field, in real time, through a :class:`drivers.link.Link`.

The session owns the clock. It saves the loop (mode, MV, gains), takes it
over in MAN, samples it on a deadline schedule (sample k is due at
``start + k·ts``, so delays do not accumulate), feeds the experiment the
*measured* sample times (jitter then does not bias the identified point),
and whatever way the experiment ends — success, TBRK, PV limits, link loss,
cancellation (Ctrl-C, SIGTERM) — writes the saved MV back and returns the
loop to its saved mode (the PID unit tracks the manual MV, so the return to
AUTO is bumpless). New gains are written only on success and only if asked.

``speed`` runs a simulated plant's clock faster than the wall clock: the
session then samples every ``ts/speed`` wall seconds and scales the measured
times back to plant seconds.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import threading
import time
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

import numpy as np

from drivers.link import Link, LinkError, LoopState, Mode, TuneFlags

from autotuner.engine.outcome import MESSAGES, Code
from autotuner.engine.experiment.relay import RelayConfig, RelayExperiment, Status
from autotuner.engine.simulated_tuning import Trace, TuneResult, result_of

# How long a failing link is retried to put the loop back, wall seconds.
RESTORE_WINDOW = 30.0
# Handshake bits (TBSY, ite) are refreshed this often, wall seconds.
FLAGS_PERIOD = 0.5
# How often a design worker checks that the process that started it still lives, seconds.
PARENT_CHECK = 0.5
# Worker processes of the design (see _designed), started on first use, and the CPU seconds they spent.
_pool: ProcessPoolExecutor | None = None
_design_cpu = 0.0


async def deadlines(period: float) -> AsyncIterator[float]:
    """Sleep until each sample is due, every ``period`` wall seconds from now; yields the due time.

    Due times are ``start + k·period``: a late sample does not delay the next
    ones (no drift); several overdue samples are taken back to back.
    """
    start = time.monotonic()
    k = 0
    while True:
        due = start + k * period
        delay = due - time.monotonic()
        if delay > 0.0:
            await asyncio.sleep(delay)
        yield due
        k += 1


async def _restore(link: Link, saved: LoopState) -> str:
    """Saved MV, then saved mode; '' on success, else why the loop is not restored.

    A loop left in MAN at a relay level is the worst outcome, so the restore
    keeps trying, with growing pauses, for ``RESTORE_WINDOW`` seconds.
    """
    deadline = time.monotonic() + RESTORE_WINDOW
    pause = 0.1
    while True:
        try:
            await link.write_mv(saved.mv)
            await link.write_mode(Mode(saved.mode))
            return ""
        except LinkError as exc:
            if time.monotonic() + pause > deadline:
                return f"LOOP NOT RESTORED ({exc}): set mode {Mode(saved.mode).name} and MV {saved.mv:g} by hand"
            await asyncio.sleep(pause)
            pause = min(2.0 * pause, 2.0)


async def _publish(link: Link, flags: TuneFlags) -> None:
    try:
        await link.write_flags(flags)
    except LinkError:
        pass  # the handshake is informative; the experiment's own I/O reports link faults


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
) -> TuneResult:
    """Run the experiment on the loop behind ``link`` every ``ts`` plant seconds and design ``controller``."""
    if not ts > 0.0 or not speed > 0.0:
        raise ValueError(f"sample time and speed must be positive, got ts={ts}, speed={speed}")
    try:
        saved = await link.read_state()
    except LinkError as exc:
        return TuneResult.failed(Code.LINK_FAULT, f"cannot read the loop: {exc}", controller)

    experiment = RelayExperiment(config, mv0=saved.mv)
    times: list[float] = []
    pvs: list[float] = []
    mvs: list[float] = []
    restore_error = ""
    try:
        await _publish(link, TuneFlags(tbsy=True, te=False, ite=0.0))
        await link.write_mv(saved.mv)
        await link.write_mode(Mode.MAN)
        start = time.monotonic()
        flags_due = start
        async for _ in deadlines(ts / speed):
            if stop is not None and stop.is_set():
                experiment.abort()
                break
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
            await link.write_mv(mv)
            times.append(t)
            pvs.append(pv)
            mvs.append(mv)
            status = experiment.status()
            if on_status is not None:
                on_status(status)
            if time.monotonic() >= flags_due:
                flags_due += FLAGS_PERIOD
                await _publish(link, TuneFlags(tbsy=True, te=False, ite=status.ite))
    except LinkError as exc:
        experiment.fail(Code.LINK_FAULT, f"{MESSAGES[Code.LINK_FAULT]}: {exc}")
    except asyncio.CancelledError:
        experiment.abort()
        restore_error = await _restore(link, saved)
        raise
    finally:
        if not restore_error:
            restore_error = await _restore(link, saved)
    result = await _designed(experiment, controller, ms, _trace(times, pvs, mvs), restore_error)
    if result.ok and apply:
        try:
            await link.write_gains(result.design.gains)
        except LinkError as exc:
            result = TuneResult(Code.LINK_FAULT, f"gains not written: {exc}", controller,
                                result.identification, result.design, result.trace)
    await _publish(link, TuneFlags(tbsy=False, te=not result.ok, ite=float(result.code)))
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
