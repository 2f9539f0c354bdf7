"""The daemon's core: a :class:`LoopManager` owning many loops, each with the PIDAT block's state machine.

Per loop (methods.md §3.4): TUNE on an idle loop starts a session (refused
while the loop, or another loop of its exclusion group, is busy); while it
runs ``tbsy`` is true and ``ite`` counts down the estimated plant seconds
left; at the end ``ite`` becomes the code (0 ok, see :class:`Code`) and
``te`` tells failure; TBRK aborts. The session itself is
:func:`autotuner.service.link_session.tune_link`: it saves the loop, restores it in every
outcome and writes gains only on success when asked. Each session is an
asyncio task, so loops tune concurrently and none waits for another's I/O.

Every session goes to the :class:`History`: who, when, the settings, the
loop's saved state (before the experiment touches it) with the relay's MV
levels, the result, the gains after and a downsampled trace.

Restore until it holds (docs/handback.md): a loop whose session could not
hand it back is *not restored* — recorded so in the history, ``ite``
:attr:`Code.LOOP_NOT_RESTORED` in its status (and on the device when it can
be written), logged at ERROR — and tried again with back-off for as long as
the daemon runs, and after a restart. On :meth:`LoopManager.start`, a session
still recorded as running (the daemon died during it) is recovered the same
way. Each try first reads the loop and compares it with what the session left:
MAN at an MV within the range the session may write (recorded durably before
the session writes an MV outside it: the relay's levels and the saved MV, so
also a switch sample between the levels; within the link's resolution) is
untouched and is handed back; already in its saved mode is
taken as handed back (by the device's watchdog, or by hand); anything else is
an operator's intervention, never overwritten: recorded (code
:attr:`Code.OPERATOR_INTERVENTION`) and left as found.

:meth:`LoopManager.shutdown` (SIGTERM/SIGINT) aborts every session and hands
every loop back first, within a bound, then ends the event streams; loops it
could not hand back stay recorded as not restored for the next start.

Live events go to subscribers (the API's Server-Sent Events) through bounded
queues; a slow subscriber loses events, it never delays the sampling.

Each loop has one *watch* task with a link of its own (the session's
sampling is not involved). While the loop is idle it monitors it: every
``monitor_period`` wall seconds it reads the mode, SP, MV and gains
(``read_state``) and the PV, keeps them in the status and publishes a
``sample`` event (``state`` when the mode, the gains or the link's health
change). It does not read the loop while the loop's session runs; the
session's own samples are the live values then.

A loop configured with ``handshake: true`` also obeys the device's own bits,
like the function block wired to an HMI: its watch task also reads
``read_flags`` every ``handshake_poll`` wall seconds, idle or busy; a rising
edge of TUNE is a TUNE from user ``plc`` with the loop's defaults, a rising
edge of TBRK aborts the running session. A TUNE the state does not allow is
not run: while the loop's own session runs it is ignored (TBSY and ``ite``
are that session's); while another loop of the exclusion group tunes, TE is
set and ``ite`` shows :attr:`Code.GROUP_BUSY`, the loop untouched.

Link errors of the watch task are logged once per outage, kept in the
status (``monitor_error``) and retried with a growing pause; they never
reach another loop or the API.

:meth:`LoopManager.apply` writes a finished session's designed gains to the
controller on request, reads them back and records who applied them.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import time
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any


from drivers.link import BadValue, Link, LinkError, LoopState, Mode, TuneFlags, Watchdog
from drivers.simlink import SimLink
from drivers.simplc import SimulatedPlc, run

from autotuner.engine.design.analysis import usable_gains
from autotuner.service.config import DaemonConfig, HandBackConfig, LoopConfig, TuneRequest
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.control.gains import Gains
from autotuner.service.history import History, downsample, now, state_of
from autotuner.engine.outcome import MESSAGES, Code
from autotuner.engine.experiment.relay import RelayConfig, Stage, Status
from autotuner.service.remote_tuning import PLANT_TICKS_PER_SAMPLE, field_config, open_link
from autotuner.service.link_session import (HandBack, NotTracking, close_design_pool, hand_back_once, not_restored,
                                            tune_link)
from autotuner.service.session_record import SessionRecord, Tap, mv_hull, read_gains, same_gains, waited
from autotuner.service.trend import Trend
from autotuner.engine.result import ResultRecord, TuneResult

# Events kept per subscriber before the oldest are dropped.
QUEUE_EVENTS = 1000
# How long :meth:`LoopManager.stop` waits for the watch tasks to end, wall seconds.
STOP_WAIT = 10.0
# Past the shutdown's bound, how long a try already under way may still finish, wall seconds.
SHUTDOWN_GRACE = 2.0
# Who the history records for sessions started by the device's TUNE bit.
PLC_USER = "plc"
# Longest pause between two tries of a watch task whose link fails, wall seconds.
LINK_RETRY_MAX = 5.0
log = logging.getLogger("autotuner.service.daemon")


class Refused(Exception):
    """A request the loop's state does not allow.

    ``code``: not_found, busy, group_busy, idle, nothing_to_apply, not_restored
    (the loop is not handed back yet), stopping (the daemon shuts down), link
    (the device could not be written), history_unavailable (a gains intent
    could not be recorded first), invalid (a setting outside the loop's
    bounds, e.g. ``amp`` above its largest relay amplitude), or — TUNE on a
    fresh read of the loop (:meth:`LoopManager.request_tune`) —
    pv_out_of_limits, pv_invalid (not finite, or stale), link_unhealthy,
    device_busy (the device already shows TBSY: another tuner owns the loop).
    """

    def __init__(self, code: str, message: str, ite: Code | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.ite = ite  # what a refused TUNE from the device shows it (TE set); None: nothing written


@dataclass
class Settings:
    """The settings of one session: the loop's defaults overridden by the request."""

    controller: str
    amp: float
    hysteresis: float | None
    phase: float
    ms: float
    apply: bool

    def as_json(self) -> dict[str, Any]:
        """The settings as recorded in the history (``request``)."""
        return dict(self.__dict__)


def settings_of(loop: LoopConfig, request: TuneRequest) -> Settings:
    """``request`` completed with the defaults of ``loop``."""
    d = loop.tuning
    return Settings(
        controller=request.controller or d.controller,
        amp=request.amp if request.amp is not None else d.amp,
        hysteresis=request.hysteresis if request.hysteresis is not None else d.hysteresis,
        phase=request.phase if request.phase is not None else d.phase,
        ms=request.ms if request.ms is not None else d.ms,
        apply=request.apply if request.apply is not None else loop.apply,
    )


def simulated_plc(loop: LoopConfig) -> SimulatedPlc | None:
    """The simulated PLC of a ``sim:`` loop (its plant ticks ``PLANT_TICKS_PER_SAMPLE`` times per sample), else None."""
    if loop.sim is None:
        return None
    return SimulatedPlc(parse_process(loop.sim.plant), ts=loop.ts / PLANT_TICKS_PER_SAMPLE,
                        noise_std=loop.sim.noise, seed=loop.sim.seed)


def connector(loop: LoopConfig, plc: SimulatedPlc | None) -> Callable[[], Link]:
    """How to reach ``loop``: a new link to ``plc`` if it is simulated, else to its configured URL."""
    if plc is not None:
        return lambda: SimLink(plc)

    def connect() -> Link:
        try:
            return open_link(str(loop.link), _str(loop.map), _str(loop.dbc))
        except ValueError as exc:  # load_config checked it; a map file removed since is a link fault, not a crash
            raise LinkError(f"cannot open the link {loop.link}: {exc}") from None

    return connect


def relay_config(loop: LoopConfig, settings: Settings) -> RelayConfig:
    """The experiment's settings with the loop's safety limits and the field tolerances."""
    return field_config(RelayConfig(
        amp=settings.amp, phase_deg=settings.phase, hysteresis=settings.hysteresis,
        pv_limits=loop.limits.pv, mv_limits=loop.limits.mv, time_limit=loop.tuning.time_limit,
    ))


async def fresh_check(config: LoopConfig, connect: Callable[[], Link]) -> None:
    """Before a TUNE touches the loop: read its PV and handshake bits on a new link (``connect()``), and close it.

    Refused — with the code a device's TUNE is answered with (``ite``) — if the
    PV is not finite or stale (pv_invalid, 24), the link fails or reports
    itself disconnected (``Link.health``; link_unhealthy, 25), the PV is
    outside ``config.limits.pv`` (pv_out_of_limits, 23), or the device already
    shows TBSY (device_busy, 26: another tuner owns the loop). Nothing is
    written. The one check of the daemon's TUNE and of ``tune --config``.
    """
    loop_id = config.id
    link: Link | None = None
    try:
        link = connect()
        await link.open()
        pv = await link.read_pv()
        flags = await link.read_flags()
        health = link.health()
    except BadValue as exc:
        raise Refused("pv_invalid", f"loop {loop_id!r} not tuned: {exc}", Code.REFUSED_BAD_PV) from None
    except LinkError as exc:
        raise Refused("link_unhealthy", f"loop {loop_id!r} not tuned: {exc}", Code.REFUSED_LINK) from None
    finally:
        if link is not None:
            await link.close()
    if not health.get("connected", True):
        raise Refused("link_unhealthy", f"loop {loop_id!r} not tuned: its link reports {health}", Code.REFUSED_LINK)
    low, high = config.limits.pv
    if not low <= pv <= high:
        raise Refused("pv_out_of_limits", f"loop {loop_id!r} not tuned: PV {pv:g} is outside its limits "
                      f"[{low:g}, {high:g}]", Code.REFUSED_PV_LIMITS)
    if flags.tbsy:
        raise Refused("device_busy", f"loop {loop_id!r} not tuned: the device already shows TBSY (another "
                      "tuner owns the loop)", Code.REFUSED_DEVICE_BUSY)


@dataclass
class Pending:
    """A loop not handed back yet: session ``sid`` saved ``saved`` and wrote MVs within ``mv_range`` only.

    ``code`` and ``final``: the result code and history state the session gets
    once the loop is back. ``since``: UTC, ISO 8601. ``attempts``: tries that
    failed so far (the session's own hand-back counts as one).
    """

    sid: str
    saved: LoopState
    mv_range: tuple[float, float]
    code: Code
    final: str
    error: str
    since: str = field(default_factory=now)
    attempts: int = 1

    def as_json(self) -> dict[str, Any]:
        """The ``restore`` member of the loop's status."""
        return {"session": self.sid, "mode": Mode(self.saved.mode).name, "mv": self.saved.mv, "since": self.since,
                "attempts": self.attempts, "last_error": self.error}


def found(state: LoopState, pending: Pending, tolerance: float) -> str:
    """How the loop is now, against what the interrupted session left (``tolerance``: the link's MV resolution).

    ``left``: MAN at an MV within the range the session may have written (the
    relay's levels, a switch sample between them, the saved MV: untouched, hand
    it back); ``back``: in its saved mode (AUTO, or MAN at the saved MV): handed
    back already; ``changed``: anything else (an operator's intervention).
    """
    low, high = pending.mv_range
    if state.mode is Mode.MAN and low - tolerance <= state.mv <= high + tolerance:
        return "left"
    if state.mode is Mode(pending.saved.mode) is Mode.AUTO:
        return "back"
    return "changed"


@dataclass
class Loop:
    """One loop at run time: its config, how to reach it, its tuning state and its last monitored values.

    ``mode``, ``pv``, ``sp``, ``mv`` and ``gains`` are the watch task's last
    reading (None: not read yet); ``latest`` the newest finished session in
    the history; ``saved`` and ``tap`` the running session's saved state and
    live values.
    """

    config: LoopConfig
    connect: Callable[[], Link]
    plc: SimulatedPlc | None = None
    task: asyncio.Task[None] | None = None
    watcher: asyncio.Task[None] | None = None
    monitor_error: str | None = None
    stop: asyncio.Event = field(default_factory=asyncio.Event)
    session: str | None = None
    status: Status | None = None
    result: ResultRecord | None = None
    subscribers: set[asyncio.Queue[dict[str, Any]]] = field(default_factory=set)
    mode: Mode | None = None
    pv: float | None = None
    sp: float | None = None
    mv: float | None = None
    gains: Gains | None = None
    latest: dict[str, Any] | None = None
    saved: LoopState | None = None
    tap: Tap | None = None
    applying: bool = False
    pending: Pending | None = None
    restorer: asyncio.Task[None] | None = None
    handback: HandBack | None = None
    trend: Trend = field(default_factory=Trend)
    # ``result``'s JSON, encoded once per record: as_json runs for every loop at the monitor's rate (OPC UA, the
    # page), and encoding a record (dataclasses.asdict) took ~0.1 ms, 5 ms on the event loop for 50 loops.
    _result_json: tuple[ResultRecord, dict[str, Any]] | None = field(default=None, repr=False, compare=False)

    @property
    def busy(self) -> bool:
        """TBSY: a session is running."""
        return self.task is not None

    def live(self) -> dict[str, Any]:
        """Mode (MAN, AUTO or None), PV, SP and MV now: the session's while it runs, else the monitor's."""
        mode, pv, sp, mv = self.mode, self.pv, self.sp, self.mv
        if self.busy and self.saved is not None:
            mode, sp = Mode.MAN, self.saved.sp  # the session holds the loop in MAN; its SP is the saved one
            if self.tap is not None and math.isfinite(self.tap.pv):
                pv, mv = self.tap.pv, self.tap.mv
        return {"mode": None if mode is None else Mode(mode).name, "pv": _finite(pv), "sp": _finite(sp),
                "mv": _finite(mv)}

    @property
    def pending_gains(self) -> bool:
        """Idle, and the newest session succeeded with gains nobody has applied yet."""
        last = self.latest
        return (not self.busy and last is not None and last["outcome"] == "success"
                and last["applied_at"] is None and last["result"] is not None and last["result"].gains is not None)

    def as_json(self) -> dict[str, Any]:
        """The status of design.md: tbsy, te, ite, stage, progress, last point and gains."""
        c, s, r = self.config, self.status, self._result()
        running = self.busy
        if running:
            ite = 0.0 if s is None else s.ite
        else:
            ite = 0 if r is None else r["ite"]
        return {
            "id": c.id,
            "description": c.description,
            "group": c.group,
            "link": c.link if c.link is not None else f"sim:{c.sim.plant}",
            "speed": c.speed,
            "tbsy": running,
            "te": bool(r["te"]) if r is not None and not running else False,
            "ite": ite,
            "stage": None if s is None else s.stage.value,
            "progress": 0.0 if s is None else s.progress,
            "message": "tuning" if running else (r["message"] if r else "idle"),
            "session": self.session,
            "controller": None if r is None else r["controller"],
            "point": None if r is None else _copy(r["point"]),
            "static_gain": None if r is None else r["static_gain"],
            "gains": None if r is None else _copy(r["gains"]),
            **self.live(),
            "current_gains": None if self.gains is None else self.gains.as_json(),
            "last_tuned_at": None if self.latest is None else self.latest["finished_at"],
            "last_outcome": None if self.latest is None else self.latest["outcome"],
            "pending_gains": self.pending_gains,
            "monitor_error": self.monitor_error,
            "defaults": settings_of(c, TuneRequest()).as_json(),
            "units": c.units.as_json(),
        } | self._restore_status()

    def _result(self) -> dict[str, Any] | None:
        """``result``'s JSON (None: no result), from the cache while the record is the same (records are frozen)."""
        record = self.result
        if record is None:
            return None
        if self._result_json is None or self._result_json[0] is not record:
            self._result_json = (record, record.to_json())
        return self._result_json[1]

    def _restore_status(self) -> dict[str, Any]:
        """While the loop is not handed back: te, ite 20 and the message override the session's, plus ``restore``."""
        p = self.pending
        if p is None:
            return {"restore": None}
        return {"te": True, "ite": float(Code.LOOP_NOT_RESTORED), "message": not_restored(p.saved, p.error),
                "session": p.sid, "restore": p.as_json()}


def _copy(member: dict[str, Any] | None) -> dict[str, Any] | None:
    """A copy of a member of the cached result JSON, so that no status shares it with the cache."""
    return None if member is None else dict(member)


def _finite(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None


class LoopManager:
    """All loops of ``config``; sessions recorded in ``history``."""

    def __init__(self, config: DaemonConfig, history: History) -> None:
        self.history = history
        self.loops: dict[str, Loop] = {c.id: self._loop(c) for c in config.loops}
        self.handback_config: HandBackConfig = config.handback
        self._halt = asyncio.Event()
        self._polling = False
        self._plants: list[asyncio.Task[None]] = []
        # The history's own thread: writes run there in order, off the event loop (a busy database is retried).
        self._recorder = ThreadPoolExecutor(1, thread_name_prefix="history")
        self._writes: set[asyncio.Future[Any]] = set()
        self._reconcilers: list[asyncio.Task[None]] = []
        self._stopping = False
        self._shutdown: asyncio.Task[list[str]] | None = None
        self._streams_closed = False

    def _handback(self) -> HandBack:
        """The hand-back of a new session (its watchdog time is wall seconds; the session scales it)."""
        return self.handback_config.session()

    @staticmethod
    def _loop(config: LoopConfig) -> Loop:
        plc = simulated_plc(config)
        return Loop(config, connector(config, plc), plc=plc)

    async def start(self) -> None:
        """Start the simulated plants; put back the loops of sessions a crash left running or not restored.

        One try each, at once and together; a loop that cannot be handed back
        yet (its device offline) is retried in the background: the start
        never waits for a device.
        """
        for loop in self.loops.values():
            if loop.plc is not None:
                self._plants.append(asyncio.create_task(run(loop.plc, loop.config.speed, self._halt)))
        left = await self._record(lambda: (*self.history.running(), *self.history.not_restored()))
        recovered = [loop for record in left if (loop := self._recover(record)) is not None]
        done = await asyncio.gather(*(self._try_restore(loop) for loop in recovered))
        for loop, ok in zip(recovered, done):
            if not ok:
                loop.restorer = asyncio.create_task(self._restore_until_held(loop))
        for record in await self._record(self.history.open_intents):
            self._reconcilers.append(asyncio.create_task(self._reconcile(record)))
        self._polling = True
        for loop_id, loop in self.loops.items():
            loop.latest = await self._record(self.history.latest, loop_id)
            if loop.latest is not None:  # its trace, so a page opened after the restart draws the last experiment
                record = await self._record(self.history.get, loop.latest["id"])
                if record is not None:
                    loop.trend.seed(record, loop.config.speed)
        for loop in self.loops.values():  # no await between these and the return: a subscriber sees the first reading
            loop.watcher = asyncio.create_task(self._watch(loop))

    async def shutdown(self) -> list[str]:
        """Abort every session (TBRK) and hand every loop back first, within ``handback.shutdown`` seconds, then
        end the event streams; the ids of the loops not handed back (recorded so, logged CRITICAL: the next start
        resumes their restore). Once: later calls wait for the first one."""
        if self._shutdown is None:
            self._shutdown = asyncio.create_task(self._hand_back_all())
        return await asyncio.shield(self._shutdown)

    async def _hand_back_all(self) -> list[str]:
        bound = self.handback_config.shutdown
        deadline = time.monotonic() + bound
        self._stopping = True
        self._polling = False  # also ends a watch whose link call swallowed the cancellation (3.11's wait_for)
        watchers = [loop.watcher for loop in self.loops.values() if loop.watcher is not None]
        for watcher in watchers:
            watcher.cancel()
        restorers = [loop.restorer for loop in self.loops.values() if loop.restorer is not None]
        for restorer in restorers:
            restorer.cancel()
        tasks = [loop.task for loop in self.loops.values() if loop.task is not None]
        for loop in self.loops.values():
            loop.stop.set()
        for loop in self.loops.values():
            if loop.handback is not None:
                loop.handback.cap = deadline  # no hand-back try of a session starts past the bound
        log.log(logging.WARNING if tasks or restorers else logging.INFO,
                "stopping: %d experiment(s) aborted, every loop handed back first (at most %g s)", len(tasks), bound)
        if tasks:
            await asyncio.wait(tasks, timeout=bound + SHUTDOWN_GRACE)
        if restorers:
            await asyncio.wait(restorers, timeout=SHUTDOWN_GRACE)
        last = [loop for loop in self.loops.values() if loop.pending is not None]  # a last try for each
        if last and time.monotonic() < deadline:
            tries = [asyncio.create_task(self._try_restore(loop)) for loop in last]
            await asyncio.wait(tries, timeout=max(deadline - time.monotonic(), 0.0) + SHUTDOWN_GRACE)
        if watchers:
            await asyncio.wait(watchers, timeout=STOP_WAIT)
        unrestored: list[str] = []
        for loop in self.loops.values():
            loop.watcher = loop.restorer = None
            if loop.task is not None and loop.session is not None:  # its hand-back did not end within the bound
                # In the history's thread after the session's earlier records; stop() waits for it before the exit.
                self._record(self.history.finish, loop.session, TuneResult.failed(
                    Code.LOOP_NOT_RESTORED, "the daemon stopped before the loop was handed back",
                    "PI").record(), None, None, "not_restored")
                unrestored.append(loop.config.id)
            elif loop.pending is not None:
                unrestored.append(loop.config.id)
        for loop_id in unrestored:
            loop = self.loops[loop_id]
            what = "its hand-back did not end" if loop.pending is None else loop.pending.error
            log.critical("loop %s: LOOP NOT RESTORED at shutdown (%s); recorded: the next start resumes the "
                         "restore", loop_id, what)
        self.close_streams()
        return unrestored

    def close_streams(self) -> None:
        """End every event stream (the daemon stops): a last ``state`` event, then the end."""
        self._streams_closed = True
        for loop in self.loops.values():
            self._publish(loop, "state", loop.as_json())
            self._publish(loop, "end", {})

    @property
    def streams_closed(self) -> bool:
        """The event streams have ended (a new one ends at once)."""
        return self._streams_closed

    async def stop(self) -> None:
        """:meth:`shutdown` (if not done yet), then stop the plants and the design's workers."""
        await self.shutdown()
        for reconciler in self._reconcilers:
            reconciler.cancel()
        if self._writes:  # what the sessions' ends still have to record (a busy database: retried meanwhile)
            await asyncio.wait(set(self._writes), timeout=STOP_WAIT)
        self._recorder.shutdown(wait=False)
        self._halt.set()
        await asyncio.gather(*self._plants)
        await asyncio.to_thread(close_design_pool)

    def _record(self, method: Callable[..., Any], *args: Any) -> asyncio.Future[Any]:
        """Run the history's ``method(*args)`` in the history's thread, after the writes before it; its future.

        A write that fails after the history's own retries is logged here; the
        caller may await the future (bounded: :meth:`_durable`) or not.
        """
        future = asyncio.get_running_loop().run_in_executor(self._recorder, functools.partial(method, *args))
        self._writes.add(future)
        future.add_done_callback(self._recorded)
        return future

    def _recorded(self, future: asyncio.Future[Any]) -> None:
        self._writes.discard(future)
        if not future.cancelled() and future.exception() is not None:
            log.error("history: a write failed for good (%s: %s)", type(future.exception()).__name__,
                      future.exception())

    async def _durable(self, method: Callable[..., Any], *args: Any) -> str:
        """Record ``method(*args)`` and wait up to ``RECORD_WAIT`` s (:mod:`~autotuner.service.session_record`); ''
        once recorded, else why not."""
        return await waited(self._record(method, *args))

    def _refresh_latest(self, loop: Loop) -> asyncio.Future[Any]:
        """Read the loop's newest session in the history's thread (after the writes before), then publish; the
        read's future, which a caller may await (:func:`waited`): ``loop.latest`` is set by then (the callback
        setting it was added first)."""
        future = self._record(self.history.latest, loop.config.id)

        def done(f: asyncio.Future[Any]) -> None:
            if not f.cancelled() and f.exception() is None:
                loop.latest = f.result()
                self._publish(loop, "state", loop.as_json())

        future.add_done_callback(done)
        return future

    def get(self, loop_id: str) -> Loop:
        """The loop ``loop_id``; Refused('not_found') if there is none."""
        loop = self.loops.get(loop_id)
        if loop is None:
            raise Refused("not_found", f"no loop {loop_id!r}")
        return loop

    async def request_tune(self, loop_id: str, request: TuneRequest, user: str) -> str:
        """TUNE as the API and the device's handshake ask it: :meth:`tune` after a fresh read of the loop.

        Before anything is written to the loop, a link of its own reads the PV
        and the handshake bits: refused (the loop untouched) if the PV is
        outside the loop's PV limits, not finite or stale, if the link fails or
        reports itself disconnected (``Link.health``), or if the device already
        shows TBSY. The state checks of :meth:`tune` come first (no I/O for a
        busy loop) and again after the read (another TUNE may have won meanwhile).
        """
        loop = self.get(loop_id)
        self._admit(loop, request)
        await self._fresh_check(loop)
        return self.tune(loop_id, request, user)

    async def _fresh_check(self, loop: Loop) -> None:
        """:func:`fresh_check` of the loop, unless the daemon is stopping."""
        if self._stopping:
            raise Refused("stopping", "the daemon is stopping")
        await fresh_check(loop.config, loop.connect)

    def _admit(self, loop: Loop, request: TuneRequest) -> Settings:
        """The settings of a TUNE of ``loop``; Refused if the loop or its group is busy or a setting is out of bounds."""
        loop_id = loop.config.id
        if self._stopping:
            raise Refused("stopping", "the daemon is stopping")
        if loop.busy:
            raise Refused("busy", f"loop {loop_id!r} is tuning (session {loop.session})")
        if loop.pending is not None:
            raise Refused("not_restored", f"loop {loop_id!r} is not handed back yet (session {loop.pending.sid}): "
                                          f"{loop.pending.error}")
        if loop.applying:
            raise Refused("busy", f"gains are being written to loop {loop_id!r}")
        group = loop.config.group
        if group is not None:
            for other in self.loops.values():
                if other.busy and other.config.group == group:
                    raise Refused("group_busy", f"loop {other.config.id!r} of exclusion group {group!r} is tuning",
                                  Code.GROUP_BUSY)
        settings = settings_of(loop.config, request)
        if settings.amp > loop.config.max_amp:
            raise Refused("invalid", f"amp: {settings.amp:g} is above loop {loop_id!r}'s largest relay amplitude "
                          f"{loop.config.max_amp:g} MV units (the span of its MV limits, else its tuning.max_amp)")
        return settings

    def tune(self, loop_id: str, request: TuneRequest, user: str) -> str:
        """TUNE: start a session on an idle loop now; its id. Refused if the loop or its group is busy.

        Without the fresh read of :meth:`request_tune` (tests, and code that has just read the loop).
        """
        loop = self.get(loop_id)
        settings = self._admit(loop, request)
        config = relay_config(loop.config, settings)
        sid = uuid.uuid4().hex
        self._record(self.history.begin, sid, loop_id, user, settings.as_json())  # in order before the session's
        loop.session, loop.status, loop.result = sid, None, None
        loop.stop = asyncio.Event()
        loop.trend.start(sid)
        loop.task = asyncio.create_task(self._session(loop, sid, user, settings, config))
        self._publish(loop, "state", loop.as_json())
        return sid

    def abort(self, loop_id: str) -> str:
        """TBRK: abort the running session (the loop is restored); its id. Refused('idle') if none runs."""
        loop = self.get(loop_id)
        if not loop.busy:
            raise Refused("idle", f"loop {loop_id!r} is not tuning")
        loop.stop.set()
        return loop.session

    async def apply(self, loop_id: str, sid: str | None, user: str) -> dict[str, Any]:
        """Write the designed gains of session ``sid`` (None: the loop's newest) to the idle loop ``loop_id``.

        The gains are read back (if that read fails, the written ones are
        taken), recorded in the history as applied by ``user`` with the gains
        after, and become the loop's current gains. ``{"loop", "session",
        "gains"}``. Refused: not_found (loop, or a session of this loop),
        busy (the loop tunes, or is being written), nothing_to_apply (no
        session yet, or it failed or has no gains), link (the write failed;
        nothing recorded).
        """
        loop = self.get(loop_id)
        if loop.busy or loop.applying:
            raise Refused("busy", f"loop {loop_id!r} is tuning or being written")
        loop.applying = True  # before the first await: a TUNE or another apply meanwhile is refused
        try:
            sid, gains = await self._designed_gains(loop_id, sid)
            why = await self._durable(self.history.intend, sid, user, gains)
            if why:
                raise Refused("history_unavailable", f"gains not written to loop {loop_id!r}: the intent to "
                              f"write them must be recorded first; {why}")
            after = await _write_gains(loop.connect(), gains)
        except LinkError as exc:  # the intent stays open: reconciled with the device at the next start
            raise Refused("link", f"gains not written to loop {loop_id!r}: {exc}") from None
        finally:
            loop.applying = False
        why = await self._durable(self.history.applied, sid, user, after)
        if why:
            log.error("loop %s: gains of session %s written, their record delayed: %s", loop_id, sid, why)
        loop.gains = after
        # Awaited (bounded): whoever reads the loop next — the REST client, the OPC UA reply's status — sees the
        # session applied (pending_gains false), not the record from before until the next refresh.
        await waited(self._refresh_latest(loop))
        log.info("loop %s: gains of session %s applied by %s", loop_id, sid, user)
        self._publish(loop, "state", loop.as_json())
        return {"loop": loop_id, "session": sid, "gains": after.as_json()}

    async def _designed_gains(self, loop_id: str, sid: str | None) -> tuple[str, Gains]:
        """The session (None: the loop's newest finished one) whose gains an apply writes, and those gains; read
        after the history's writes before (a session just ended is recorded first). Refused if there are none."""
        record = await self._record(self.history.latest, loop_id) if sid is None else \
            await self._record(self.history.get, sid)
        if record is None and sid is None:
            raise Refused("nothing_to_apply", f"loop {loop_id!r} has no finished session")
        if record is None or record["loop"] != loop_id:
            raise Refused("not_found", f"no session {sid!r} of loop {loop_id!r}")
        sid = record["id"]
        if record["outcome"] != "success":
            raise Refused("nothing_to_apply", f"session {sid} did not succeed: {record['message']}")
        gains = None if record["result"] is None else usable_gains(record["result"].gains)
        if gains is None:
            raise Refused("nothing_to_apply", f"session {sid} has no usable gains")
        return sid, gains

    async def wait(self, loop_id: str) -> None:
        """Until the running session of ``loop_id`` (if any) has ended and the history's pending writes are done."""
        task = self.get(loop_id).task
        if task is not None:
            await asyncio.shield(task)
        if self._writes:
            await asyncio.wait(set(self._writes))

    def subscribe(self, loop_id: str) -> asyncio.Queue[dict[str, Any]]:
        """A queue receiving the loop's events ``{"event": "sample"|"state", "data": {...}}``."""
        queue: asyncio.Queue[dict[str, Any]] = asyncio.Queue(QUEUE_EVENTS)
        self.get(loop_id).subscribers.add(queue)
        return queue

    def replay(self, loop_id: str) -> dict[str, Any]:
        """The loop's trend kept in memory (:class:`~autotuner.service.trend.Trend`): the running or last
        session's samples from its start, then the monitor's; as columns."""
        return self.get(loop_id).trend.replay()

    def unsubscribe(self, loop_id: str, queue: asyncio.Queue[dict[str, Any]]) -> None:
        """Stop sending events to ``queue``."""
        self.get(loop_id).subscribers.discard(queue)

    @staticmethod
    def _publish(loop: Loop, event: str, data: dict[str, Any]) -> None:
        if event == "sample":
            loop.trend.add(data)
        for queue in loop.subscribers:
            if queue.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    queue.get_nowait()
            queue.put_nowait({"event": event, "data": data})

    async def _session(self, loop: Loop, sid: str, user: str, settings: Settings, config: RelayConfig) -> None:
        link: Link | None = None
        loop.tap, loop.saved = None, None
        start = time.monotonic()
        speed = loop.config.speed

        def on_status(status: Status) -> None:
            stage_changed = loop.status is None or loop.status.stage is not status.stage
            loop.status = status
            tap = loop.tap
            if status.stage is not Stage.DONE and tap is not None:
                self._publish(loop, "sample", {
                    "t": (time.monotonic() - start) * speed, "time": time.time(), "pv": tap.pv,
                    "sp": None if loop.saved is None else loop.saved.sp, "mv": tap.mv, "relay": status.relay,
                    "filter_phase_deg": status.filter_phase_deg, "stage": status.stage.value,
                    "progress": status.progress, "ite": status.ite, "periods": status.periods,
                })
            if stage_changed:
                self._publish(loop, "state", loop.as_json())

        record = SessionRecord(self._durable, self.history, sid, loop.config.id, user)
        restore_error = ""
        pending: Pending | None = None

        async def on_saved(saved: LoopState, relay_levels: tuple[float, ...]) -> str:
            """Durably, before the session touches the loop (after the begin, in the history's thread)."""
            why = await record.on_saved(saved, relay_levels)
            if not why:
                loop.saved = saved
            return why

        def on_handed_back(error: str) -> None:
            nonlocal restore_error
            restore_error = error

        result: TuneResult | None = None
        gains_after: Gains | None = None
        state = "finished"
        loop.handback = self._handback()

        tap: Tap | None = None
        try:
            link = loop.connect()
            tap = loop.tap = record.link(link)
            await link.open()
            result = await tune_link(tap, config, loop.config.ts, settings.controller, settings.ms, settings.apply,
                                     speed, loop.stop, on_status, loop.handback, on_saved, on_handed_back)
            gains_after = await record.gains_after(link, result, settings.apply)
        except LinkError as exc:
            result = TuneResult.failed(Code.LINK_FAULT, f"{MESSAGES[Code.LINK_FAULT]}: {exc}", settings.controller)
        except asyncio.CancelledError:
            state = "interrupted"
            raise
        except Exception as exc:  # a bug: tune_link's own finally has restored the loop; the loop must not stay busy
            log.exception("loop %s: session %s failed", loop.config.id, sid)
            result = TuneResult.failed(Code.ABORTED, f"aborted: internal error ({type(exc).__name__}: {exc}); "
                                       "see the daemon's log", settings.controller)
        finally:
            try:
                if link is not None:
                    await link.close()
                if result is None:  # cancelled: tune_link has handed the loop back (or said why not)
                    result = TuneResult.failed(Code.ABORTED, "aborted: the daemon stopped", settings.controller)
                loop.result = result.record()
                if restore_error and loop.saved is not None:  # shown with the idle loop, not while still busy
                    pending = Pending(sid, loop.saved, record.mv_range or mv_hull(loop.saved.mv, *record.levels),
                                      result.code, state, restore_error)
                    log.error("loop %s: LOOP NOT RESTORED at the end of session %s (%s); retrying",
                              loop.config.id, sid, restore_error)
                end = (self.history.finish, sid, loop.result, gains_after, downsample(result.trace),
                       "not_restored" if pending is not None else state, record.applied_by(gains_after))
                if self._stopping:  # the shutdown's bound is for the hand-back: the record goes on in its thread
                    self._record(*end)
                elif why := await self._durable(*end):
                    log.error("loop %s: the end of session %s is not recorded yet: %s", loop.config.id, sid, why)
                intended = record.intended
                if intended is not None and gains_after is None:  # unknown whether the write happened: ask later
                    self._reconcilers.append(asyncio.create_task(self._reconcile(
                        {"id": sid, "loop": loop.config.id, "gains_intent": {"gains": intended.as_json()}})))
                refreshed = self._refresh_latest(loop)
                if not self._stopping:
                    # Awaited (bounded) before the loop shows idle: a client that sees TBSY fall reads this
                    # session as the last one (last_outcome, pending_gains), not the one before it.
                    await waited(refreshed)
                if loop.saved is not None and pending is None:  # what the session left: its mode, the gains
                    loop.mode, loop.gains = Mode(loop.saved.mode), gains_after
                    loop.sp = loop.saved.sp
                if tap is not None and math.isfinite(tap.pv):  # the session's last values, not the monitor's
                    loop.pv = tap.pv
                    loop.mv = tap.mv if math.isfinite(tap.mv) else loop.mv
            finally:  # whatever failed above, the loop is idle again (TUNE accepted, TBRK refused)
                loop.task, loop.tap, loop.saved, loop.handback = None, None, None, None
                loop.pending = pending
                if pending is not None and not self._stopping:
                    loop.restorer = asyncio.create_task(self._restore_until_held(loop))
                self._publish(loop, "state", loop.as_json())

    async def _watch(self, loop: Loop) -> None:
        """The loop's watch task, until cancelled: monitor it while idle, poll its handshake bits (if configured).

        One link of its own, opened on first use and after a failure. Every
        ``monitor_period`` wall seconds while the loop is idle: its state and
        PV (:meth:`_monitor`). With a handshake, every ``handshake_poll``
        seconds, idle or busy: the TUNE/TBRK bits, acting on their rising
        edges. The first reading of the bits after (re)connecting is only a
        reference: a bit already true then is no edge, so a TUNE left set
        across a restart or a link outage never starts an experiment by
        itself. Without a handshake the link is closed while the loop's
        session runs. A failure closes the link and is retried after a pause
        growing from the period to :data:`LINK_RETRY_MAX`.
        """
        config = loop.config
        period = min(config.handshake_poll, config.monitor_period) if config.handshake else config.monitor_period
        pause = period
        link: Link | None = None
        last: TuneFlags | None = None
        monitor_due = 0.0
        try:
            while self._polling:
                try:
                    if not config.handshake and loop.task is not None:
                        if link is not None:
                            await link.close()
                            link = None
                        await asyncio.wait([loop.task])  # nothing to read while the session runs
                        monitor_due = 0.0
                        continue
                    if link is None:
                        link = loop.connect()
                        await link.open()
                    if config.handshake:
                        flags = await link.read_flags()
                        if last is not None:
                            await self._edges(loop, link, last, flags)
                        last = flags
                    if not loop.busy and time.monotonic() >= monitor_due:
                        monitor_due = time.monotonic() + config.monitor_period
                        await self._monitor(loop, link)
                except (LinkError, OSError) as exc:
                    self._link_failed(loop, str(exc) or type(exc).__name__)
                except Exception as exc:  # a bug must not end the watch (nor reach the event loop)
                    log.exception("loop %s: watch failed", config.id)
                    self._link_failed(loop, f"{type(exc).__name__}: {exc}")
                else:
                    if loop.monitor_error is not None:
                        log.info("loop %s: %s link back", config.id, _watching(config))
                        loop.monitor_error = None
                        self._publish(loop, "state", loop.as_json())
                    pause = period
                    await asyncio.sleep(period)
                    continue
                last, monitor_due = None, 0.0
                if link is not None:
                    await link.close()
                    link = None
                await asyncio.sleep(pause)
                pause = min(2.0 * pause, max(period, LINK_RETRY_MAX))
        finally:
            if link is not None:
                await link.close()

    async def _monitor(self, loop: Loop, link: Link) -> None:
        """Read the idle loop's state and PV; keep them, publish a ``sample`` (``state`` if mode or gains changed)."""
        state = await link.read_state()
        pv = await link.read_pv()
        if loop.busy:
            return  # a session started meanwhile: its samples are the live values
        changed = (loop.mode, loop.gains) != (state.mode, state.gains)
        loop.mode, loop.gains = Mode(state.mode), state.gains
        loop.pv, loop.sp, loop.mv = pv, state.sp, state.mv
        self._publish(loop, "sample", {"time": time.time(), "pv": pv, "sp": state.sp, "mv": state.mv,
                                       "mode": loop.mode.name})
        if changed:
            self._publish(loop, "state", loop.as_json())

    def _link_failed(self, loop: Loop, error: str) -> None:
        """The watch link failed: logged once per outage, kept as ``monitor_error``; the mode is unknown."""
        if loop.monitor_error is None:
            log.warning("loop %s: %s link failed (%s); retrying", loop.config.id, _watching(loop.config), error)
        changed = loop.monitor_error != error or loop.mode is not None
        loop.monitor_error = error
        if not loop.busy:
            loop.mode = None
        if changed:
            self._publish(loop, "state", loop.as_json())

    async def _edges(self, loop: Loop, link: Link, last: TuneFlags, flags: TuneFlags) -> None:
        """TBRK first (a break wins), then TUNE; a TUNE edge while TBRK is held is ignored."""
        loop_id = loop.config.id
        if not self._polling:
            return  # the daemon is stopping: no new session
        if flags.tbrk and not last.tbrk and loop.busy:
            log.info("loop %s: TBRK from the device aborts session %s", loop_id, loop.session)
            self.abort(loop_id)
        if not flags.tune or last.tune:
            return
        if flags.tbrk:
            log.info("loop %s: TUNE from the device ignored while TBRK is set", loop_id)
            return
        try:
            sid = await self.request_tune(loop_id, TuneRequest(), user=PLC_USER)
        except Refused as refused:
            log.info("loop %s: TUNE from the device refused: %s", loop_id, refused.message)
            if refused.ite is not None and refused.code != "device_busy":  # TBSY/ite then belong to the other tuner
                await link.write_flags(TuneFlags(tbsy=False, te=True, ite=float(refused.ite)))
            return
        log.info("loop %s: TUNE from the device started session %s", loop_id, sid)

    async def _reconcile(self, record: dict[str, Any]) -> None:
        """Close an open gains intent (a crash between the write and its record) with the gains the device holds.

        Retried (growing pauses) until the device answers: the history then
        records the gains read back, as applied by whoever intended the write
        if they are the intended gains, else as not applied.
        """
        loop = self.loops.get(record["loop"])
        sid, intended = record["id"], Gains.from_json(record["gains_intent"]["gains"])
        if loop is None:
            log.warning("session %s: its gains write is unconfirmed and loop %r is no longer configured", sid,
                        record["loop"])
            return
        pause = 0.5
        while True:
            read_back = await _read_gains_opened(loop.connect())
            if read_back is not None:
                break
            log.info("loop %s: gains write of session %s unconfirmed, the device is unreachable; retrying",
                     loop.config.id, sid)
            await asyncio.sleep(pause)
            pause = min(2.0 * pause, LINK_RETRY_MAX)
        applied = same_gains(read_back, intended)
        why = await self._durable(self.history.resolve_intent, sid, read_back, applied)
        log.warning("loop %s: the gains write of session %s was interrupted; the device %s the intended gains%s",
                    loop.config.id, sid, "holds" if applied else "does not hold",
                    f" (not recorded yet: {why})" if why else "")
        self._refresh_latest(loop)

    def _recover(self, record: dict[str, Any]) -> Loop | None:
        """A session the last run left running or not restored: its loop, now pending a restore (None: nothing to
        restore — the session never touched its loop, or the loop is no longer configured)."""
        loop = self.loops.get(record["loop"])
        saved = record["saved"]
        if record["state"] == "running":
            message = "interrupted: the daemon stopped during the session"
            if saved is None:
                message += " (before it touched the loop)"
            elif loop is None:
                message += f"; loop {record['loop']!r} is no longer configured: check it by hand"
            result = TuneResult.failed(Code.ABORTED, message, record["request"].get("controller", "PI")).record()
            self._record(self.history.finish, record["id"], result, None, None,
                         "not_restored" if saved is not None and loop is not None else "interrupted")
            code, final = Code.ABORTED, "interrupted"
        else:
            result = record["result"]
            code, final = result.code if result else Code.ABORTED, "interrupted"
            if loop is None:
                log.critical("loop %s: session %s left it not restored, and it is no longer configured: check it "
                             "by hand", record["loop"], record["id"])
        if loop is None or saved is None:
            return None
        loop.session, loop.result = record["id"], result
        # The MVs the session may have written: its recorded range (older records: the relay levels and saved MV).
        mv_range = mv_hull(saved["mv"], *saved.get("relay_levels", ()), *saved.get("mv_range", ()))
        loop.pending = Pending(record["id"], state_of(saved), mv_range, code, final,
                               "not tried since the daemon started", attempts=0)
        return loop

    async def _restore_until_held(self, loop: Loop) -> None:
        """Try the pending restore of ``loop`` again and again, the pause doubling from ``retry_first`` up to
        ``retry_max`` seconds, until it is dealt with (or the daemon stops)."""
        pause = self.handback_config.retry_first
        while loop.pending is not None and not self._stopping:
            await asyncio.sleep(pause)
            if await self._try_restore(loop):
                return
            pause = min(2.0 * pause, self.handback_config.retry_max)

    async def _try_restore(self, loop: Loop) -> bool:
        """One try at the pending restore of ``loop``; True when it is dealt with (handed back, found back, or
        left as an operator set it), False when it must be tried again."""
        p = loop.pending
        assert p is not None
        loop_id = loop.config.id
        saved = p.saved
        link = loop.connect()
        try:
            await link.open()
            state = await link.read_state()
            how = found(state, p, link.mv_resolution(saved.mv))
            if how == "left":
                await hand_back_once(link, saved, self.handback_config.track_timeout)
                code, message = p.code, f"loop restored to {Mode(saved.mode).name} with MV {saved.mv:g}"
                log.info("loop %s: %s (session %s, try %d)", loop_id, message, p.sid, p.attempts)
            else:
                await link.write_watchdog(Watchdog())  # it must not override what is there now, later
                if how == "back":
                    flags = await link.read_flags()
                    by_watchdog = flags.ite == float(Code.WATCHDOG_FALLBACK)
                    code = Code.WATCHDOG_FALLBACK if by_watchdog else p.code
                    message = (f"found back in {state.mode.name} with MV {state.mv:g}: "
                               + ("handed back by the device's watchdog" if by_watchdog else "nothing written"))
                    log.warning("loop %s: %s (session %s)", loop_id, message, p.sid)
                else:
                    code = Code.OPERATOR_INTERVENTION
                    message = (f"left as found: mode {state.mode.name}, MV {state.mv:g}, not MAN within the "
                               f"session's MV range {p.mv_range[0]:g}-{p.mv_range[1]:g} or the saved "
                               f"{Mode(saved.mode).name} at MV {saved.mv:g} (an operator's intervention): "
                               "not restored")
                    log.warning("loop %s: %s (session %s)", loop_id, message, p.sid)
            await link.write_flags(TuneFlags(tbsy=False, te=True, ite=float(code)))
        except (LinkError, NotTracking) as exc:
            p.attempts += 1
            p.error = str(exc) or type(exc).__name__
            log.error("loop %s: LOOP NOT RESTORED (session %s, %d tries): %s", loop_id, p.sid, p.attempts, p.error)
            with contextlib.suppress(LinkError):  # TE and ite 20 on the device, when it can be written
                await link.write_flags(TuneFlags(tbsy=False, te=True, ite=float(Code.LOOP_NOT_RESTORED)))
            self._publish(loop, "state", loop.as_json())
            return False
        finally:
            await link.close()
        # In the history's thread, after the session's end (a write queued before it, e.g. one retried while the
        # database is locked): the event loop never waits on the database, and the records keep their order.
        written = self._record(self.history.restored, p.sid, p.final, message, int(code))
        try:  # shown restored once recorded (bounded; not during a shutdown, whose bound is for the hand-backs)
            if not self._stopping and (why := await waited(written)):
                log.error("loop %s: the restore of session %s is not recorded yet: %s", loop_id, p.sid, why)
        finally:  # cancelled while waiting (a shutdown): the loop is dealt with all the same
            loop.pending = None
            if loop.result is not None:
                loop.result = replace(loop.result, ite=int(code), te=True, message=f"{loop.result.message}; {message}")
            self._refresh_latest(loop)
            self._publish(loop, "state", loop.as_json())
        return True


def _watching(config: LoopConfig) -> str:
    """What a loop's watch task is called in the log."""
    return "handshake" if config.handshake else "monitor"


async def _write_gains(link: Link, gains: Gains) -> Gains:
    """Open ``link``, write ``gains``, read them back (the written ones if the read-back fails), close."""
    try:
        await link.open()
        await link.write_gains(gains)
        try:
            return (await link.read_state()).gains
        except LinkError as exc:
            log.warning("gains written but not read back (%s)", exc)
            return gains
    finally:
        await link.close()


async def _read_gains_opened(link: Link) -> Gains | None:
    """Open ``link``, read the controller's gains, close; None if the device cannot be reached."""
    try:
        await link.open()
        return await read_gains(link)
    except LinkError:
        return None
    finally:
        await link.close()


def _str(path: Any) -> str | None:
    return None if path is None else str(path)
