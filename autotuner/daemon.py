"""The daemon's core: a :class:`LoopManager` owning many loops, each with the PIDAT block's state machine.

Per loop (methods.md §3.4): TUNE on an idle loop starts a session (refused
while the loop, or another loop of its exclusion group, is busy); while it
runs ``tbsy`` is true and ``ite`` counts down the estimated plant seconds
left; at the end ``ite`` becomes the code (0 ok, see :class:`Code`) and
``te`` tells failure; TBRK aborts. The session itself is
:func:`autotuner.session.tune_link`: it saves the loop, restores it in every
outcome and writes gains only on success when asked. Each session is an
asyncio task, so loops tune concurrently and none waits for another's I/O.

Every session goes to the :class:`History`: who, when, the settings, the
loop's saved state (before the experiment touches it), the result, the gains
after and a downsampled trace. On :meth:`LoopManager.start`, a session still
recorded as running (the daemon died during it) is closed as interrupted and
its loop is put back from the saved state.

Live events go to subscribers (the API's Server-Sent Events) through bounded
queues; a slow subscriber loses events, it never delays the sampling.

A loop configured with ``handshake: true`` also obeys the device's own bits,
like the function block wired to an HMI: a task of its own polls
``read_flags`` on a link of its own every ``handshake_poll`` wall seconds
(idle or busy; the session's sampling is not involved), a rising edge of TUNE
is a TUNE from user ``plc`` with the loop's defaults, a rising edge of TBRK
aborts the running session. A TUNE the state does not allow is not run: while
the loop's own session runs it is ignored (TBSY and ``ite`` are that
session's); while another loop of the exclusion group tunes, TE is set and
``ite`` shows :data:`GROUP_BUSY_CODE`, the loop untouched. Link errors of the
poll are logged and retried with a growing pause; they never reach another
loop or the API.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers.link import Link, LinkError, LoopState, Mode, TuneFlags
from drivers.simlink import SimLink
from drivers.simplc import SimulatedPlc, run

from .config import DaemonConfig, LoopConfig, TuneRequest
from .expr import parse_process
from .gains import Gains
from .history import History, downsample
from .relay import MESSAGES, Code, RelayConfig, Stage, Status
from .remote import PLANT_TICKS_PER_SAMPLE, field_config, open_link
from .session import tune_link
from .tuning import Trace, TuneResult

# Events kept per subscriber before the oldest are dropped.
QUEUE_EVENTS = 1000
# How long :meth:`LoopManager.stop` waits for aborted sessions to restore their loops, wall seconds.
STOP_WAIT = 40.0
# Who the history records for sessions started by the device's TUNE bit.
PLC_USER = "plc"
# ``ite`` (with TE set) when the device's TUNE is refused because another loop of the exclusion group
# tunes; outside the experiment's codes (autotuner.relay.Code, 0–8).
GROUP_BUSY_CODE = 10
# Longest pause between polls of a handshake whose link fails, wall seconds.
HANDSHAKE_RETRY_MAX = 5.0

log = logging.getLogger("autotuner.daemon")


class Refused(Exception):
    """A request the loop's state does not allow. ``code``: not_found, busy, group_busy or idle."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


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


def relay_config(loop: LoopConfig, settings: Settings) -> RelayConfig:
    """The experiment's settings with the loop's safety limits and the field tolerances."""
    return field_config(RelayConfig(
        amp=settings.amp, phase_deg=settings.phase, hysteresis=settings.hysteresis,
        pv_limits=loop.limits.pv, mv_limits=loop.limits.mv, time_limit=loop.tuning.time_limit,
    ))


class _Tap:
    """A link that remembers the last PV read and MV written (for the live samples) and forwards everything."""

    def __init__(self, link: Link) -> None:
        self._link = link
        self.pv = math.nan
        self.mv = math.nan

    @property
    def pv_age(self) -> float | None:
        return self._link.pv_age

    async def read_pv(self) -> float:
        self.pv = await self._link.read_pv()
        return self.pv

    async def write_mv(self, mv: float) -> None:
        await self._link.write_mv(mv)
        self.mv = mv

    def __getattr__(self, name: str) -> Any:
        return getattr(self._link, name)


@dataclass
class Loop:
    """One loop at run time: its config, how to reach it, and its tuning state."""

    config: LoopConfig
    connect: Callable[[], Link]
    plc: SimulatedPlc | None = None
    task: asyncio.Task[None] | None = None
    poller: asyncio.Task[None] | None = None
    handshake_error: str | None = None
    stop: asyncio.Event = field(default_factory=asyncio.Event)
    session: str | None = None
    status: Status | None = None
    result: dict[str, Any] | None = None
    subscribers: set[asyncio.Queue[dict[str, Any]]] = field(default_factory=set)

    @property
    def busy(self) -> bool:
        """TBSY: a session is running."""
        return self.task is not None

    def as_json(self) -> dict[str, Any]:
        """The status of design.md: tbsy, te, ite, stage, progress, last point and gains."""
        c, s, r = self.config, self.status, self.result
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
            "tbsy": running,
            "te": bool(r["te"]) if r is not None and not running else False,
            "ite": ite,
            "stage": None if s is None else s.stage.value,
            "progress": 0.0 if s is None else s.progress,
            "message": "tuning" if running else (r["message"] if r else "idle"),
            "session": self.session,
            "controller": None if r is None else r["controller"],
            "point": None if r is None else r["point"],
            "static_gain": None if r is None else r["static_gain"],
            "gains": None if r is None else r["gains"],
        }


def _empty_trace() -> Trace:
    return Trace(np.zeros(0), np.zeros(0), np.zeros(0))


class LoopManager:
    """All loops of ``config``; sessions recorded in ``history``."""

    def __init__(self, config: DaemonConfig, history: History) -> None:
        self.history = history
        self.loops: dict[str, Loop] = {c.id: self._loop(c) for c in config.loops}
        self._halt = asyncio.Event()
        self._polling = False
        self._plants: list[asyncio.Task[None]] = []

    @staticmethod
    def _loop(config: LoopConfig) -> Loop:
        if config.sim is None:
            return Loop(config, lambda: open_link(config.link, _str(config.map), _str(config.dbc)))
        plc = SimulatedPlc(parse_process(config.sim.plant), ts=config.ts / PLANT_TICKS_PER_SAMPLE,
                           noise_std=config.sim.noise, seed=config.sim.seed)
        return Loop(config, lambda: SimLink(plc), plc=plc)

    async def start(self) -> None:
        """Start the simulated plants and put back the loops of sessions a crash left running."""
        for loop in self.loops.values():
            if loop.plc is not None:
                self._plants.append(asyncio.create_task(run(loop.plc, loop.config.speed, self._halt)))
        for record in self.history.running():
            await self._recover(record)
        self._polling = True
        for loop in self.loops.values():
            if loop.config.handshake:
                loop.poller = asyncio.create_task(self._handshake(loop))

    async def stop(self) -> None:
        """Stop the handshake polls, abort every running session (TBRK), wait until their loops are restored, stop
        the plants."""
        self._polling = False  # also ends a poll whose link call swallowed the cancellation (3.11's wait_for)
        pollers = [loop.poller for loop in self.loops.values() if loop.poller is not None]
        for poller in pollers:
            poller.cancel()
        if pollers:
            await asyncio.wait(pollers, timeout=STOP_WAIT)
        for loop in self.loops.values():
            loop.poller = None
        tasks = [loop.task for loop in self.loops.values() if loop.task is not None]
        for loop in self.loops.values():
            loop.stop.set()
        if tasks:
            await asyncio.wait(tasks, timeout=STOP_WAIT)
        self._halt.set()
        await asyncio.gather(*self._plants)

    def get(self, loop_id: str) -> Loop:
        """The loop ``loop_id``; Refused('not_found') if there is none."""
        loop = self.loops.get(loop_id)
        if loop is None:
            raise Refused("not_found", f"no loop {loop_id!r}")
        return loop

    def tune(self, loop_id: str, request: TuneRequest, user: str) -> str:
        """TUNE: start a session on an idle loop; its id. Refused if the loop or its group is busy."""
        loop = self.get(loop_id)
        if loop.busy:
            raise Refused("busy", f"loop {loop_id!r} is tuning (session {loop.session})")
        group = loop.config.group
        if group is not None:
            for other in self.loops.values():
                if other.busy and other.config.group == group:
                    raise Refused("group_busy", f"loop {other.config.id!r} of exclusion group {group!r} is tuning")
        settings = settings_of(loop.config, request)
        config = relay_config(loop.config, settings)
        sid = uuid.uuid4().hex
        self.history.begin(sid, loop_id, user, settings.as_json())
        loop.session, loop.status, loop.result = sid, None, None
        loop.stop = asyncio.Event()
        loop.task = asyncio.create_task(self._session(loop, sid, settings, config))
        self._publish(loop, "state", loop.as_json())
        return sid

    def abort(self, loop_id: str) -> str:
        """TBRK: abort the running session (the loop is restored); its id. Refused('idle') if none runs."""
        loop = self.get(loop_id)
        if not loop.busy:
            raise Refused("idle", f"loop {loop_id!r} is not tuning")
        loop.stop.set()
        return loop.session

    async def wait(self, loop_id: str) -> None:
        """Until the running session of ``loop_id`` (if any) has ended and been recorded."""
        task = self.get(loop_id).task
        if task is not None:
            await asyncio.shield(task)

    def subscribe(self, loop_id: str) -> asyncio.Queue[dict[str, Any]]:
        """A queue receiving the loop's events ``{"event": "sample"|"state", "data": {...}}``."""
        queue: asyncio.Queue[dict[str, Any]] = asyncio.Queue(QUEUE_EVENTS)
        self.get(loop_id).subscribers.add(queue)
        return queue

    def unsubscribe(self, loop_id: str, queue: asyncio.Queue[dict[str, Any]]) -> None:
        """Stop sending events to ``queue``."""
        self.get(loop_id).subscribers.discard(queue)

    @staticmethod
    def _publish(loop: Loop, event: str, data: dict[str, Any]) -> None:
        for queue in loop.subscribers:
            if queue.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    queue.get_nowait()
            queue.put_nowait({"event": event, "data": data})

    async def _session(self, loop: Loop, sid: str, settings: Settings, config: RelayConfig) -> None:
        link = loop.connect()
        tap = _Tap(link)
        start = time.monotonic()
        speed = loop.config.speed

        def on_status(status: Status) -> None:
            stage_changed = loop.status is None or loop.status.stage is not status.stage
            loop.status = status
            if status.stage is not Stage.DONE:
                self._publish(loop, "sample", {
                    "t": (time.monotonic() - start) * speed, "pv": tap.pv, "mv": tap.mv, "relay": status.relay,
                    "filter_phase_deg": status.filter_phase_deg, "stage": status.stage.value,
                    "progress": status.progress, "ite": status.ite, "periods": status.periods,
                })
            if stage_changed:
                self._publish(loop, "state", loop.as_json())

        result: TuneResult | None = None
        gains_after: Gains | None = None
        state = "finished"
        try:
            await link.open()
            saved = await link.read_state()
            self.history.saved(sid, saved)
            result = await tune_link(tap, config, loop.config.ts, settings.controller, settings.ms, settings.apply,
                                     speed, loop.stop, on_status)
            gains_after = await _gains(link, saved, result, settings.apply)
        except LinkError as exc:
            result = TuneResult(Code.LINK_FAULT, f"{MESSAGES[Code.LINK_FAULT]}: {exc}", settings.controller, None,
                                None, _empty_trace())
        except asyncio.CancelledError:
            state = "interrupted"
            raise
        finally:
            await link.close()
            if result is None:  # cancelled: tune_link has restored the loop
                result = TuneResult(Code.ABORTED, "aborted: the daemon stopped", settings.controller, None, None,
                                    _empty_trace())
            loop.result = result.as_json()
            self.history.finish(sid, loop.result, gains_after, downsample(result.trace), state)
            loop.task = None
            self._publish(loop, "state", loop.as_json())

    async def _handshake(self, loop: Loop) -> None:
        """Poll the device's TUNE/TBRK bits of ``loop`` and act on their rising edges, until cancelled.

        The first reading after (re)connecting is only a reference: a bit
        already true then is no edge, so a TUNE left set across a restart or a
        link outage never starts an experiment by itself.
        """
        period = loop.config.handshake_poll
        pause = period
        link: Link | None = None
        last: TuneFlags | None = None
        try:
            while self._polling:
                try:
                    if link is None:
                        link = loop.connect()
                        await link.open()
                    flags = await link.read_flags()
                    if last is not None:
                        await self._edges(loop, link, last, flags)
                    last = flags
                except (LinkError, OSError) as exc:
                    self._handshake_failed(loop, str(exc) or type(exc).__name__)
                except Exception as exc:  # a bug must not end the handshake (nor reach the event loop)
                    log.exception("loop %s: handshake poll failed", loop.config.id)
                    self._handshake_failed(loop, f"{type(exc).__name__}: {exc}")
                else:
                    if loop.handshake_error is not None:
                        log.info("loop %s: handshake link back", loop.config.id)
                    loop.handshake_error = None
                    pause = period
                    await asyncio.sleep(period)
                    continue
                last = None
                if link is not None:
                    await link.close()
                    link = None
                await asyncio.sleep(pause)
                pause = min(2.0 * pause, max(period, HANDSHAKE_RETRY_MAX))
        finally:
            if link is not None:
                await link.close()

    @staticmethod
    def _handshake_failed(loop: Loop, error: str) -> None:
        if loop.handshake_error is None:
            log.warning("loop %s: handshake link failed (%s); retrying", loop.config.id, error)
        loop.handshake_error = error

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
            sid = self.tune(loop_id, TuneRequest(), user=PLC_USER)
        except Refused as refused:
            log.info("loop %s: TUNE from the device refused: %s", loop_id, refused.message)
            if refused.code == "group_busy":
                await link.write_flags(TuneFlags(tbsy=False, te=True, ite=float(GROUP_BUSY_CODE)))
            return
        log.info("loop %s: TUNE from the device started session %s", loop_id, sid)

    async def _recover(self, record: dict[str, Any]) -> None:
        """Close a session a crash left running; put its loop back from the saved state if it was touched."""
        loop = self.loops.get(record["loop"])
        message = "interrupted: the daemon stopped during the session"
        if record["saved"] is not None and loop is not None:
            message += await _restore(loop.connect(), record["saved"])
        elif record["saved"] is not None:
            message += f"; loop {record['loop']!r} is no longer configured: check it by hand"
        result = TuneResult(Code.ABORTED, message, record["request"].get("controller", "PI"), None, None,
                            _empty_trace()).as_json()
        self.history.finish(record["id"], result, None, None, "interrupted")
        if loop is not None:
            loop.session, loop.result = record["id"], result


async def _gains(link: Link, saved: LoopState, result: TuneResult, apply: bool) -> Gains:
    """The controller's gains after a session: read back, else what the session should have left."""
    try:
        return (await link.read_state()).gains
    except LinkError:
        return result.design.gains if result.ok and apply else saved.gains


async def _restore(link: Link, saved: dict[str, Any]) -> str:
    """Write the saved MV and mode back and clear TBSY (TE set, ite = ABORTED); '' or why it failed."""
    try:
        await link.open()
        try:
            await link.write_mv(saved["mv"])
            await link.write_mode(Mode[saved["mode"]])
            await link.write_flags(TuneFlags(tbsy=False, te=True, ite=float(Code.ABORTED)))
        finally:
            await link.close()
    except LinkError as exc:
        return f"; LOOP NOT RESTORED ({exc}): set mode {saved['mode']} and MV {saved['mv']:g} by hand"
    return f"; loop restored to {saved['mode']} with MV {saved['mv']:g}"


def _str(path: Any) -> str | None:
    return None if path is None else str(path)
