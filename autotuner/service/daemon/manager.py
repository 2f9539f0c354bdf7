"""The loop manager: every loop's PIDAT state machine, its commands and its records; the field does the I/O.

Per loop (methods.md §3.4): TUNE on an idle loop starts a session (refused
while the loop, or another loop of its exclusion group, is busy, or while
the daemon tunes as many loops at once as it may); while it runs ``tbsy`` is
true and ``ite`` counts down the estimated plant seconds left; at the end
``ite`` becomes the code (0 ok, see :class:`Code`) and ``te`` tells failure;
TBRK aborts. The session itself runs in the field
(:class:`~autotuner.service.daemon.field.Field`): it saves the loop, restores
it in every outcome and writes gains only on success when asked.

Every session goes to the history: who, when, the settings, the loop's saved
state (before the experiment touches it) with the relay's MV levels, the
result, the gains after and a downsampled trace.

Restore until it holds (docs/handback.md, :mod:`~autotuner.service.daemon.restore`):
a loop whose session could not hand it back is *not restored* — recorded so,
``ite`` :attr:`Code.LOOP_NOT_RESTORED` in its status (and on the device when
it can be written), logged at ERROR — and tried again with back-off for as
long as the daemon runs, and after a restart. On :meth:`LoopManager.start`, a
session still recorded as running (the daemon died during it) is recovered
the same way.

:meth:`LoopManager.shutdown` (SIGTERM/SIGINT) aborts every session and hands
every loop back first, within a bound, then ends the event streams; loops it
could not hand back stay recorded as not restored for the next start.

A loop configured with ``handshake: true`` obeys the device's TUNE and TBRK
bits (:mod:`~autotuner.service.daemon.watch`): a rising edge of TUNE is a
TUNE from user ``plc`` with the loop's defaults, a rising edge of TBRK aborts
the running session. A TUNE the state does not allow is not run: while the
loop's own session runs it is ignored (TBSY and ``ite`` are that session's);
otherwise TE is set and ``ite`` shows the refusal's code, the loop untouched.

:meth:`LoopManager.apply` writes a finished session's designed gains to the
controller on request, reads them back and records who applied them.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import math
import time
import uuid
from collections import Counter
from dataclasses import dataclass, field, replace
from datetime import datetime
from typing import Any

from drivers.link import LinkError, Mode, TuneFlags

from autotuner.engine.control.gains import Gains
from autotuner.engine.design.analysis import model_of, usable_gains
from autotuner.engine.plant.process import Process
from autotuner.engine.experiment.relay import Stage, Status
from autotuner.engine.outcome import Code
from autotuner.engine.result import TuneResult
from autotuner.engine.simulated_tuning import DesignJob
from autotuner.service.config import DaemonConfig, HandBackConfig, TuneRequest
from autotuner.service.daemon.field import Field, Lease, LocalField
from autotuner.service.daemon.health import HealthJob, LoopHealth, run_job
from autotuner.service.daemon.fleet import Fleet
from autotuner.service.daemon.loop import Loop, Session
from autotuner.service.daemon.recorder import HISTORY_WAIT, Recorder
from autotuner.service.daemon.status import OwnerRecord
from autotuner.service.daemon.refused import Refused
from autotuner.service.daemon.restore import Pending
from autotuner.service.daemon.settings import Settings, plan_of, settings_of
from autotuner.service.daemon.timing import Histogram, TimingBatch
from autotuner.service.daemon.watch import Reading
from autotuner.service.design_pool import Outcome, close_design_pool, designed, pooled
from autotuner.service.history import History, Unavailable, downsample, state_of
from autotuner.service.link_session import NotTracking, SessionPlan
from autotuner.service.session_record import mv_hull, same_gains, waited
from autotuner.service.session_runner import SessionOutcome

# How long :meth:`LoopManager.stop` waits for the history's writes, wall seconds.
STOP_WAIT = 10.0
# Past the shutdown's bound, how long a try already under way may still finish, wall seconds.
SHUTDOWN_GRACE = 2.0
# Who the history records for sessions started by the device's TUNE bit.
PLC_USER = "plc"
# After a sample late by the daemon's own fault, new TUNEs are refused this long while sessions run, wall seconds.
OVERLOAD_HOLD = 10.0
# Longest pause between two tries of a gains write to reconcile, wall seconds.
RECONCILE_RETRY_MAX = 5.0
# How often the loops due for a health assessment are looked for, wall seconds; how many assessments may be in
# the workers at once (the others wait for the next look: a design never queues behind many).
HEALTH_TICK = 0.5
HEALTH_IN_FLIGHT = 2
# Sessions read at a start to find a loop's newest successful one (the model its health assessment uses).
MODEL_SEARCH = 50
log = logging.getLogger("autotuner.service.daemon")


@dataclass
class Sampling:
    """Every session sample's timing since the daemon started (wall seconds; :mod:`~autotuner.service.daemon.timing`):
    ``late`` behind its due time, ``own`` the daemon's own part, ``overloaded`` samples late enough by the
    daemon's fault to hurt an experiment; ``analysis`` the CPU seconds of each period's analysis."""

    late: Histogram = field(default_factory=Histogram)
    own: Histogram = field(default_factory=Histogram)
    analysis: Histogram = field(default_factory=Histogram)
    overloaded: int = 0

    def merge(self, batch: TimingBatch) -> None:
        """Add a field's batch."""
        self.late.merge(batch.late)
        self.own.merge(batch.own)
        self.analysis.merge(batch.analysis)
        self.overloaded += batch.overloaded


class LoopManager:
    """All loops of ``config``; sessions recorded in ``history``; their devices reached through ``field``
    (default: a :class:`~autotuner.service.daemon.field.LocalField` on this event loop); with ``fleet``, only the
    loops whose leases this daemon holds are served (the others' commands refused as not_owner)."""

    def __init__(self, config: DaemonConfig, history: History, field: Field | None = None,
                 fleet: Fleet | None = None) -> None:
        self.history = history
        self.fleet = fleet
        self._fleet_task: asyncio.Task[None] | None = None
        if fleet is not None:
            fleet.idle = self._releasable
        self.recorder = Recorder(history, config.record_wait)
        self.recorder.on_health = self._history_health
        self.field: Field = LocalField(config.loops) if field is None else field
        reaches = getattr(self.field, "reaches", {})
        origin = time.time()  # plant time 0 of every loop's health record
        self.loops: dict[str, Loop] = {
            c.id: Loop(c, reaches.get(c.id), history=self.recorder.health,
                       health=LoopHealth(c, origin, phase=i / len(config.loops)))
            for i, c in enumerate(config.loops)}
        self.handback_config: HandBackConfig = config.handback
        self._stopping = False
        self._shutdown: asyncio.Task[list[str]] | None = None
        self._streams_closed = False
        self._reconcilers: list[asyncio.Task[None]] = []
        self.max_sessions, self.sampler_load = config.max_sessions, config.sampler_load
        self.sampling = Sampling()
        self.outcomes: Counter[int] = Counter()  # sessions ended since the start, by code
        self._overloaded_until = -math.inf
        self.health_cpu = 0.0  # CPU seconds of the health assessments in the workers, since the start
        self.health_assessed = 0  # assessments made since the start
        self._health_task: asyncio.Task[None] | None = None
        self._health_jobs: set[asyncio.Task[None]] = set()
        self._health_order = list(self.loops.values())
        self._health_cursor = 0
        self.field.bind(self)

    # -- life cycle ---------------------------------------------------------------------------------------------

    async def start(self) -> None:
        """Start the field (simulated plants); put back the loops of sessions a crash left running or not restored;
        then watch every loop. In a fleet, only the loops whose leases this daemon takes (a first round of
        :class:`~autotuner.service.daemon.fleet.Fleet`, then one every ``renew`` seconds).

        One try each, at once and together; a loop that cannot be handed back
        yet (its device offline) is retried in the background: the start
        never waits for a device.
        """
        await self.field.start()
        self._health_task = asyncio.create_task(self._health_rounds())
        if self.fleet is None:
            await self._take_over(set(self.loops), orphans=True)
            self.field.watch()  # after the restores: a watch never reads a loop a restore is still putting back
            return
        await self._fleet_round(orphans=True)
        self._fleet_task = asyncio.create_task(self._fleet_rounds())

    async def _take_over(self, loop_ids: set[str], orphans: bool = False) -> None:
        """Take ``loop_ids`` over: recover their sessions left running or not restored (one restore try each, the
        failed ones retried in the background), reconcile their open gains intents, read their newest session.
        ``orphans``: also close the sessions of loops no longer configured (at the start)."""
        left = await self.recorder.record(lambda: (*self.history.running(), *self.history.not_restored()))
        mine = [record for record in left
                if record["loop"] in loop_ids or (orphans and record["loop"] not in self.loops)]
        recovered = [loop for record in mine if (loop := self._recover(record)) is not None]
        done = await asyncio.gather(*(self._try_restore(loop) for loop in recovered))
        for loop, ok in zip(recovered, done):
            if not ok:
                loop.restorer = asyncio.create_task(self._restore_until_held(loop))
        for record in await self.recorder.record(self.history.open_intents):
            if record["loop"] in loop_ids:
                self._reconcilers.append(asyncio.create_task(self._reconcile(record)))
        for loop_id in loop_ids:
            loop = self.loops[loop_id]
            loop.latest = await self.recorder.record(self.history.latest, loop_id)
            if loop.latest is not None:  # its trace, so a page opened after the restart draws the last experiment
                record = await self.recorder.record(self.history.get, loop.latest["id"])
                if record is not None:
                    loop.events.trend.seed(record, loop.config.speed)
            await self._restore_health(loop)

    async def _fleet_rounds(self) -> None:
        """A fleet round every ``renew`` seconds until the daemon stops (a round that fails is logged and retried:
        meanwhile the leases held run out, and their loops' writes with them)."""
        assert self.fleet is not None
        while not self._stopping:
            await asyncio.sleep(self.fleet.renew)
            try:
                await self._fleet_round()
            except Exception as exc:  # the database unreachable: the leases run out, writes are fenced meanwhile
                log.error("fleet: the leases could not be renewed (%s: %s); retrying", type(exc).__name__, exc)

    async def _fleet_round(self, orphans: bool = False) -> None:
        """Renew, give up and take leases (:meth:`Fleet.round`); serve what was gained, stop serving what was lost
        (``orphans``: see :meth:`_take_over`)."""
        fleet = self.fleet
        assert fleet is not None
        done = await fleet.round()
        for loop_id in done.lost | done.released:
            self.field.unserve(loop_id)  # fenced at once: a session on it ends without another write
        if done.released:
            log.info("fleet: released %d idle loop(s) to the other daemons (%s): %s", len(done.released),
                     "drained" if fleet.draining else "evening the loops out", ", ".join(sorted(done.released)))
        for loop_id, epoch in fleet.held.items():
            self.field.grant(loop_id, Lease(done.valid_until, epoch))
        if done.gained:
            log.info("fleet: took over %d loop(s): %s", len(done.gained), ", ".join(sorted(done.gained)))
            await self._take_over(set(done.gained), orphans)
            for loop_id in done.gained:
                if loop_id in fleet.held:  # (not superseded meanwhile)
                    self.field.serve(loop_id, Lease(done.valid_until, fleet.held[loop_id]))
        for loop_id, loop in self.loops.items():
            owner = fleet.owners.get(loop_id)
            record = None if owner is None or not owner.live else OwnerRecord(owner.name, owner.url, owner.epoch)
            if record != loop.owner:
                loop.owner = record
                self._publish(loop, "state", loop.as_json())

    def _releasable(self, loop_id: str) -> bool:
        """The loop may go to another daemon now: no session, no restore pending, no gains being written."""
        loop = self.loops[loop_id]
        return not loop.busy and loop.pending is None and not loop.applying

    def _check_owner(self, loop: Loop) -> None:
        """Refused('not_owner') unless this daemon holds the loop's lease (always, without a fleet)."""
        if self.fleet is None or self.fleet.valid(loop.config.id):
            return
        owner = loop.owner
        if owner is None:
            raise Refused("not_owner", f"no daemon of the fleet holds loop {loop.config.id!r} right now (its lease "
                          "is free or being taken over): retry in a few seconds")
        raise Refused("not_owner", f"loop {loop.config.id!r} is served by daemon {owner.name} at {owner.url} "
                      f"(lease epoch {owner.epoch}): ask it", owner_url=owner.url)

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
        watches = asyncio.create_task(self.field.halt_watches())
        restorers = [loop.restorer for loop in self.loops.values() if loop.restorer is not None]
        for restorer in restorers:
            restorer.cancel()
        tasks = [loop.running.task for loop in self.loops.values() if loop.running and loop.running.task]
        for loop_id, loop in self.loops.items():
            if loop.running is not None:
                self.field.abort(loop_id, loop.running.sid)
        self.field.cap(bound)  # no hand-back try of a session starts past the bound
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
        await watches
        unrestored: list[str] = []
        for loop in self.loops.values():
            loop.restorer = None
            if loop.running is not None:  # its hand-back did not end within the bound
                # In the history's thread after the session's earlier records; stop() waits for it before the exit.
                self.recorder.record(self.history.finish, loop.running.sid, TuneResult.failed(
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

    @property
    def stopping(self) -> bool:
        """The daemon shuts down: no new session."""
        return self._stopping

    async def stop(self) -> None:
        """:meth:`shutdown` (if not done yet), then give up the fleet's leases (another daemon takes the loops at
        once), stop the field (its plants) and the design's workers."""
        await self.shutdown()
        if self._fleet_task is not None:
            self._fleet_task.cancel()
        if self._health_task is not None:
            self._health_task.cancel()
        for job in list(self._health_jobs):
            job.cancel()
        if self.fleet is not None:
            try:
                await self.fleet.leave()
            except Exception as exc:  # the leases then run out by themselves
                log.warning("fleet: the leases could not be released (%s); they expire", exc)
        for reconciler in self._reconcilers:
            reconciler.cancel()
        await self.recorder.drain(STOP_WAIT)  # what the sessions' ends still have to record
        self.recorder.close()
        await self.field.stop()
        await asyncio.to_thread(close_design_pool)

    # -- commands -----------------------------------------------------------------------------------------------

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
        if self._stopping:
            raise Refused("stopping", "the daemon is stopping")
        await self.field.check(loop_id)
        return self.tune(loop_id, request, user)

    def _admit(self, loop: Loop, request: TuneRequest) -> Settings:
        """The settings of a TUNE of ``loop``; Refused if the loop or its group is busy or a setting is out of bounds."""
        loop_id = loop.config.id
        if self._stopping:
            raise Refused("stopping", "the daemon is stopping")
        self._check_owner(loop)
        if loop.busy:
            raise Refused("busy", f"loop {loop_id!r} is tuning (session {loop.session})")
        if loop.pending is not None:
            raise Refused("not_restored", f"loop {loop_id!r} is not handed back yet (session {loop.pending.sid}): "
                                          f"{loop.pending.error}")
        if loop.applying:
            raise Refused("busy", f"gains are being written to loop {loop_id!r}")
        settings = settings_of(loop.config, request)
        self._check_capacity(loop_id, plan_of(loop.config, settings))
        group = loop.config.group
        if group is not None:
            for other in self.loops.values():
                if other.busy and other.config.group == group:
                    raise Refused("group_busy", f"loop {other.config.id!r} of exclusion group {group!r} is tuning",
                                  Code.GROUP_BUSY)
        if settings.amp > loop.config.max_amp:
            raise Refused("invalid", f"amp: {settings.amp:g} is above loop {loop_id!r}'s largest relay amplitude "
                          f"{loop.config.max_amp:g} MV units (the span of its MV limits, else its tuning.max_amp; "
                          "its status' bounds.amp)")
        if settings.hysteresis is not None and settings.hysteresis > loop.config.max_hysteresis:
            raise Refused("invalid", f"hysteresis: {settings.hysteresis:g} is above loop {loop_id!r}'s largest "
                          f"hysteresis {loop.config.max_hysteresis:g} PV units (its tuning.max_hysteresis, else a "
                          "quarter of the span of its PV limits; its status' bounds.hysteresis)")
        return settings

    def _check_capacity(self, loop_id: str, plan: SessionPlan) -> None:
        """Refused('overloaded') while the daemon tunes ``max_sessions`` loops, while the loop's sampler would need
        more than ``sampler_load`` of a core with ``plan``'s session added (:mod:`~autotuner.service.daemon.capacity`),
        or while its samples are late by its own fault (:data:`OVERLOAD_HOLD` seconds after the last such sample,
        while any session runs)."""
        tuning = sum(loop.busy for loop in self.loops.values())
        if self.max_sessions is not None and tuning >= self.max_sessions:
            raise Refused("overloaded", f"loop {loop_id!r} not tuned: the daemon tunes {tuning} loops, its "
                          f"max_sessions; retry when one has ended", Code.REFUSED_OVERLOADED)
        # Every session started, the ones whose task has not reached its sampler yet too: a hundred TUNEs asked at
        # once are each judged with the others.
        sessions = {other.config.id: other.running.plan for other in self.loops.values()
                    if other.running is not None}
        if (load := self.field.load(loop_id, {**sessions, loop_id: plan})) > self.sampler_load:
            raise Refused("overloaded", f"loop {loop_id!r} not tuned: with it, its sampler would need {load:.0%} of "
                          f"a core, beyond its sampler_load {self.sampler_load:.0%} ({tuning} loops tuning); retry "
                          "when fewer tune", Code.REFUSED_OVERLOADED)
        if tuning and time.monotonic() < self._overloaded_until:
            raise Refused("overloaded", f"loop {loop_id!r} not tuned: the daemon's samples of the {tuning} loops "
                          "it tunes are late by its own fault (a loaded machine); retry when fewer tune",
                          Code.REFUSED_OVERLOADED)

    def tune(self, loop_id: str, request: TuneRequest, user: str) -> str:
        """TUNE: start a session on an idle loop now; its id. Refused if the loop or its group is busy.

        Without the fresh read of :meth:`request_tune` (tests, and code that has just read the loop).
        """
        loop = self.get(loop_id)
        settings = self._admit(loop, request)
        sid = uuid.uuid4().hex
        self.recorder.record(self.history.begin, sid, loop_id, user, settings.as_json())  # before the session's
        loop.session, loop.status, loop.result = sid, None, None
        loop.events.trend.start(sid)
        loop.health.restart(sid)  # new gains make the samples before it another loop's
        self._publish(loop, "health", {"loop": loop_id, **loop.health.summary()})
        loop.running = Session(sid, plan_of(loop.config, settings, self.handback_config.session()),
                               start=time.monotonic())
        loop.running.task = asyncio.create_task(self._session(loop, loop.running, user, settings))
        self._publish(loop, "state", loop.as_json())
        return sid

    def abort(self, loop_id: str) -> str:
        """TBRK: abort the running session (the loop is restored); its id. Refused('idle') if none runs."""
        loop = self.get(loop_id)
        if loop.running is None:
            self._check_owner(loop)  # another daemon's session: asked of the wrong daemon
            raise Refused("idle", f"loop {loop_id!r} is not tuning")
        self.field.abort(loop_id, loop.running.sid)
        return loop.running.sid

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
        self._check_owner(loop)
        if loop.busy or loop.applying:
            raise Refused("busy", f"loop {loop_id!r} is tuning or being written")
        loop.applying = True  # before the first await: a TUNE or another apply meanwhile is refused
        deadline = time.monotonic() + HISTORY_WAIT  # the call waits behind the history this long at most
        try:
            sid, gains = await self._designed_gains(loop_id, sid, deadline)
            why = await self.recorder.guard(self.history.intend, sid, user, gains, wait=deadline - time.monotonic(),
                                            undo=functools.partial(self.history.withdraw, sid, gains))
            if why:
                raise Refused("history_unavailable", f"gains not written to loop {loop_id!r}: the intent to "
                              f"write them must be recorded first; {why}")
            after = await self.field.write_gains(loop_id, gains)
        except LinkError as exc:  # the intent stays open: reconciled with the device at the next start
            raise Refused("link", f"gains not written to loop {loop_id!r}: {exc}") from None
        finally:
            loop.applying = False
        # Written: the record must land (retried until it does); the answer waits for it only what is left.
        why = await self.recorder.durable(self.history.applied, sid, user, after, wait=deadline - time.monotonic())
        if why:
            log.error("loop %s: gains of session %s written, their record delayed: %s", loop_id, sid, why)
        loop.gains = after
        # Awaited (bounded): whoever reads the loop next — the REST client, the OPC UA reply's status — sees the
        # session applied (pending_gains false), not the record from before until the next refresh.
        await waited(self._refresh_latest(loop), deadline - time.monotonic())
        log.info("loop %s: gains of session %s applied by %s", loop_id, sid, user)
        self._publish(loop, "state", loop.as_json())
        return {"loop": loop_id, "session": sid, "gains": after.as_json()}

    async def _designed_gains(self, loop_id: str, sid: str | None, deadline: float) -> tuple[str, Gains]:
        """The session (None: the loop's newest finished one) whose gains an apply writes, and those gains; read
        after the history's writes before (a session just ended is recorded first), by ``deadline`` (monotonic).
        Refused if there are none, or history_unavailable if the history does not answer in time."""
        try:
            record = await self.recorder.read(self.history.latest if sid is None else self.history.get,
                                              loop_id if sid is None else sid, wait=deadline - time.monotonic())
        except (TimeoutError, Unavailable) as exc:
            why = self.recorder.health.error or str(exc) or "writes ahead of the read"
            raise Refused("history_unavailable", f"gains not written to loop {loop_id!r}: the history did not "
                          f"answer within {HISTORY_WAIT:g} s ({why}): which session's gains to write is not "
                          "known") from None
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
        running = self.get(loop_id).running
        if running is not None and running.task is not None:
            await asyncio.shield(running.task)
        await self.recorder.drain()

    # -- events -------------------------------------------------------------------------------------------------

    def subscribe(self, loop_id: str) -> asyncio.Queue[dict[str, Any]]:
        """A queue receiving the loop's events ``{"event": "sample"|"state"|"end", "data": {...}}``."""
        return self.get(loop_id).events.subscribe()

    def unsubscribe(self, loop_id: str, queue: asyncio.Queue[dict[str, Any]]) -> None:
        """Stop sending events to ``queue``."""
        self.get(loop_id).events.unsubscribe(queue)

    def replay(self, loop_id: str) -> dict[str, Any]:
        """The loop's trend kept in memory (:class:`~autotuner.service.trend.Trend`): the running or last
        session's samples from its start, then the monitor's; as columns."""
        return self.get(loop_id).events.trend.replay()

    def _history_health(self) -> None:
        """The history's outage began or ended: every loop's status says so (``history_error``)."""
        for loop in self.loops.values():
            self._publish(loop, "state", loop.as_json())

    @staticmethod
    def _publish(loop: Loop, event: str, data: dict[str, Any]) -> None:
        loop.events.publish(event, data)

    def _refresh_latest(self, loop: Loop) -> asyncio.Future[Any]:
        """Read the loop's newest session in the history's thread (after the writes before), then publish; the
        read's future, which a caller may await (:func:`waited`): ``loop.latest`` is set by then (the callback
        setting it was added first)."""
        future = self.recorder.record(self.history.latest, loop.config.id)

        def done(f: asyncio.Future[Any]) -> None:
            if not f.cancelled() and f.exception() is None:
                loop.latest = f.result()
                loop.health.model = _model(loop.latest) or loop.health.model
                self._publish(loop, "state", loop.as_json())

        future.add_done_callback(done)
        return future

    # -- health -------------------------------------------------------------------------------------------------

    async def _restore_health(self, loop: Loop) -> None:
        """At a start (or a take-over): the loop's newest successful session's model, its newest stored health
        assessment (current unless the loop was tuned after it) and the newest stored before its newest tuning."""
        health, loop_id = loop.health, loop.config.id
        sessions = await self.recorder.record(self.history.of_loop, loop_id, MODEL_SEARCH)
        health.model = next((model for record in sessions if (model := _model(record)) is not None), None)
        health.session = None if loop.latest is None else loop.latest["id"]
        latest = await self.recorder.record(self.history.health_of, loop_id, 1)
        before = None
        if loop.latest is not None:
            started = datetime.fromisoformat(loop.latest["started_at"]).timestamp()
            before = await self.recorder.record(self.history.health_of, loop_id, 1, started)
        health.restore(_stored(latest), _stored(before))

    async def _health_rounds(self) -> None:
        """Every :data:`HEALTH_TICK` s: the idle loops due for a health assessment go to the workers
        (:meth:`_submit_due`; also whenever an assessment comes back)."""
        while not self._stopping:
            await asyncio.sleep(HEALTH_TICK)
            self._submit_due()

    def _submit_due(self) -> None:
        """The idle loops due for a health assessment (their record ready, their grid's time reached) to the
        workers, at most :data:`HEALTH_IN_FLIGHT` at once, in turn from where the last look stopped."""
        order = self._health_order
        wall = time.time()
        for k in range(len(order)):
            if len(self._health_jobs) >= HEALTH_IN_FLIGHT or self._stopping:
                return
            loop = order[(self._health_cursor + k) % len(order)]
            served = self.fleet is None or self.fleet.valid(loop.config.id)
            if served and not loop.busy and loop.health.is_due(wall):
                job = asyncio.create_task(self._assess(loop, loop.health.job(wall), loop.health.generation))
                self._health_jobs.add(job)
                job.add_done_callback(self._health_done)
                self._health_cursor = (self._health_cursor + k + 1) % len(order)

    def _health_done(self, job: asyncio.Task[None]) -> None:
        """An assessment came back: the next due one goes to the workers at once."""
        self._health_jobs.discard(job)
        if not job.cancelled():
            self._submit_due()

    async def _assess(self, loop: Loop, job: HealthJob, generation: int) -> None:
        """Assess ``job`` in a worker; keep, record and publish the result (dropped if the loop's record restarted
        meanwhile: a tuning began)."""
        health = loop.health
        try:
            result, cpu = await pooled(run_job, job)
        except Exception as exc:  # a worker's failure: the loop is tried again at its next time
            health.busy = False
            log.warning("loop %s: health assessment failed (%s: %s)", loop.config.id, type(exc).__name__, exc)
            return
        self.health_cpu += cpu
        if not health.done(result, time.time(), generation):
            if "error" in result:
                log.debug("loop %s: not assessed: %s", loop.config.id, result["error"])
            return
        self.health_assessed += 1
        summary = health.summary()
        assert health.assessment is not None
        self.recorder.record(self.history.add_health, loop.config.id, health.assessment, summary["severity"],
                             health.session)
        self._publish(loop, "health", {"loop": loop.config.id, **summary})
        self._publish(loop, "state", loop.as_json())

    # -- the session --------------------------------------------------------------------------------------------

    async def _session(self, loop: Loop, running: Session, user: str, settings: Settings) -> None:
        """Run the session in the field; record its end (:meth:`_ended`), whatever way it ends."""
        sid, loop_id = running.sid, loop.config.id
        plan = running.plan
        outcome: SessionOutcome | None = None
        state, why_none = "finished", "aborted: the daemon stopped"
        try:
            outcome = await self.field.run(loop_id, sid, user, plan)
        except asyncio.CancelledError:
            state = "interrupted"
            raise
        except Exception as exc:  # the field lost the session (a sampler process ended): recovered as after a crash
            log.error("loop %s: session %s lost: %s", loop_id, sid, exc)
            state, why_none = "interrupted", f"interrupted: {exc}"
        finally:
            if self.fleet is not None and not self.fleet.valid(loop_id):
                # The lease is gone: the loop's new owner recovers this session from the history and restores the
                # loop; this daemon records and writes nothing more for it.
                log.warning("loop %s: session %s ended after this daemon lost the loop's lease; its new owner "
                            "recovers it", loop_id, sid)
                loop.running = None
                self._publish(loop, "state", loop.as_json())
            else:
                if outcome is None:  # cancelled (the field has handed the loop back, or said why not) or lost
                    outcome = self._unfinished(running, settings, state, why_none)
                await self._ended(loop, running, outcome, state)

    @staticmethod
    def _unfinished(running: Session, settings: Settings, state: str, why: str) -> SessionOutcome:
        """The outcome of a session cancelled or lost in the field: aborted, ``why``; handed back as its hand-back
        reported (not known to be handed back if it never did, unless it ended normally)."""
        restore_error = running.restore_error
        if restore_error is None:  # the hand-back never reported: not known to be done
            restore_error = "" if state == "finished" else why
        return SessionOutcome(TuneResult.failed(Code.ABORTED, why, settings.controller), None, restore_error, None,
                              running.intended)

    async def _ended(self, loop: Loop, running: Session, outcome: SessionOutcome, state: str) -> None:
        """Record the session's end; the loop idle again — or pending its restore, retried — whatever fails here."""
        sid, loop_id = running.sid, loop.config.id
        pending: Pending | None = None
        try:
            result = loop.result = outcome.result.record()
            self.outcomes[result.ite] += 1
            if result.ite == Code.LINK_FAULT:
                loop.link_errors += 1
            if outcome.restore_error and running.saved is not None:  # shown with the idle loop, not while busy
                pending = Pending(sid, running.saved, running.mv_range or mv_hull(running.saved.mv, *running.levels),
                                  Code(result.ite), state, outcome.restore_error)
                log.error("loop %s: LOOP NOT RESTORED at the end of session %s (%s); retrying", loop_id, sid,
                          outcome.restore_error)
            trace = downsample(outcome.result.trace) if len(outcome.result.trace.t) else None
            end = (self.history.finish, sid, result, outcome.gains_after, trace,
                   "not_restored" if pending is not None else state, outcome.applied_by)
            if self._stopping:  # the shutdown's bound is for the hand-back: the record goes on in its thread
                self.recorder.record(*end)
            elif why := await self.recorder.durable(*end):
                log.error("loop %s: the end of session %s is not recorded yet: %s", loop_id, sid, why)
            if outcome.intended is not None and outcome.gains_after is None:  # unknown whether it was written
                self._reconcilers.append(asyncio.create_task(self._reconcile(
                    {"id": sid, "loop": loop_id, "gains_intent": {"gains": outcome.intended.as_json()}})))
            refreshed = self._refresh_latest(loop)
            if not self._stopping:
                # Awaited (bounded) before the loop shows idle: a client that sees TBSY fall reads this session as
                # the last one (last_outcome, pending_gains), not the one before it.
                await waited(refreshed, self.recorder.wait)
            if running.saved is not None and pending is None:  # what the session left: its mode, the gains
                loop.mode, loop.gains, loop.sp = Mode(running.saved.mode), outcome.gains_after, running.saved.sp
            if math.isfinite(running.pv):  # the session's last values, not the monitor's
                loop.pv = running.pv
                loop.mv = running.mv if math.isfinite(running.mv) else loop.mv
        finally:  # whatever failed above, the loop is idle again (TUNE accepted, TBRK refused)
            loop.running = None
            loop.pending = pending
            if pending is not None and not self._stopping:
                loop.restorer = asyncio.create_task(self._restore_until_held(loop))
            self._publish(loop, "state", loop.as_json())

    # -- what the field reports (FieldSink) ---------------------------------------------------------------------

    def status(self, loop_id: str, status: Status, pv: float, mv: float) -> None:
        """A running session's status after a sample (the field's report)."""
        loop = self.loops[loop_id]
        running = loop.running
        if running is None:
            return
        stage_changed = loop.status is None or loop.status.stage is not status.stage
        loop.status = status
        running.pv, running.mv = pv, mv
        if status.stage is not Stage.DONE and math.isfinite(pv):
            self._publish(loop, "sample", {
                "t": (time.monotonic() - running.start) * loop.config.speed, "time": time.time(), "pv": pv,
                "sp": None if running.saved is None else running.saved.sp, "mv": mv, "relay": status.relay,
                "filter_phase_deg": status.filter_phase_deg, "stage": status.stage.value,
                "progress": status.progress, "ite": status.ite, "periods": status.periods,
            })
        if stage_changed:
            self._publish(loop, "state", loop.as_json())

    def superseded(self, loop_id: str) -> None:
        """The loop's device holds a newer lease epoch than this daemon's (the field's report, logged there): the
        lease is lost, as if a renewal had found it another's — the loop is no longer served here."""
        if self.fleet is not None:
            self.fleet.drop(loop_id)
        self.field.unserve(loop_id)

    def handed_back(self, loop_id: str, error: str) -> None:
        """The running session's hand-back is over (the field's report)."""
        running = self.loops[loop_id].running
        if running is not None:
            running.restore_error = error

    def timings(self, batch: TimingBatch) -> None:
        """The sessions' sample timings since the last batch (the field's report): kept, and a sample late by the
        daemon's own fault holds new TUNEs off for :data:`OVERLOAD_HOLD` seconds."""
        self.sampling.merge(batch)
        if batch.overloaded:
            if time.monotonic() >= self._overloaded_until:
                worst = max(batch.worst.items(), key=lambda item: item[1])
                log.warning("the daemon is overloaded: a sample of loop %s was %.3g s late by the daemon's own "
                            "fault (%d loop(s) tuning); new TUNEs are refused for %g s", worst[0], worst[1],
                            sum(loop.busy for loop in self.loops.values()), OVERLOAD_HOLD)
            self._overloaded_until = time.monotonic() + OVERLOAD_HOLD

    async def durable(self, loop_id: str, name: str, *args: Any) -> str:
        """A running session's durable record (its saved state and MV range, or a gains intent)."""
        why = await self.recorder.session_record(name, *args)
        running = self.loops[loop_id].running
        if not why and running is not None:
            if name == "saved":
                running.saved, running.levels, running.mv_range = args[1], args[2], args[3]
            elif name == "intend":
                running.intended = args[2]
        return why

    async def design(self, job: DesignJob) -> Outcome:
        """An ended experiment's design, in the daemon's worker pool."""
        return await designed(job)

    def reading(self, loop_id: str, reading: Reading) -> None:
        """A monitor reading of the idle loop: kept in the status, published (a state too if mode or gains changed)."""
        loop = self.loops[loop_id]
        if loop.busy:
            return  # a session started meanwhile: its samples are the live values
        sample = reading.sample
        gains = loop.gains if reading.gains is None else reading.gains  # None: not read this time, as before
        changed = (loop.mode, loop.gains) != (sample.mode, gains)
        loop.mode, loop.gains = Mode(sample.mode), gains
        loop.pv, loop.sp, loop.mv = sample.pv, sample.sp, sample.mv
        loop.health.add(reading.time, sample.sp, sample.pv, sample.mv, loop.mode is Mode.AUTO)
        self._publish(loop, "sample", {"time": reading.time, "pv": sample.pv, "sp": sample.sp, "mv": sample.mv,
                                       "mode": loop.mode.name})
        if changed:
            self._publish(loop, "state", loop.as_json())

    def link_failed(self, loop_id: str, error: str) -> None:
        """The watch's link failed: logged once per outage, kept as ``monitor_error``; the mode is unknown."""
        loop = self.loops[loop_id]
        loop.link_errors += 1
        if loop.monitor_error is None:
            log.warning("loop %s: %s link failed (%s); retrying", loop_id, _watching(loop), error)
        changed = loop.monitor_error != error or loop.mode is not None
        loop.monitor_error = error
        if not loop.busy:
            loop.mode = None
        if changed:
            self._publish(loop, "state", loop.as_json())

    def link_back(self, loop_id: str) -> None:
        """The watch's link works again."""
        loop = self.loops[loop_id]
        if loop.monitor_error is not None:
            log.info("loop %s: %s link back", loop_id, _watching(loop))
            loop.monitor_error = None
            self._publish(loop, "state", loop.as_json())

    async def edges(self, loop_id: str, last: TuneFlags, flags: TuneFlags) -> TuneFlags | None:
        """The device's bits changed: TBRK first (a break wins), then TUNE; a TUNE edge while TBRK is held is
        ignored. The flags to write back: a refused TUNE's TE and code (None: nothing to write)."""
        loop = self.loops[loop_id]
        if self._stopping:
            return None  # the daemon is stopping: no new session
        if flags.tbrk and not last.tbrk and loop.busy:
            log.info("loop %s: TBRK from the device aborts session %s", loop_id, loop.session)
            self.abort(loop_id)
        if not flags.tune or last.tune:
            return None
        if flags.tbrk:
            log.info("loop %s: TUNE from the device ignored while TBRK is set", loop_id)
            return None
        try:
            sid = await self.request_tune(loop_id, TuneRequest(), user=PLC_USER)
        except Refused as refused:
            log.info("loop %s: TUNE from the device refused: %s", loop_id, refused.message)
            if refused.ite is not None and refused.code != "device_busy":  # TBSY/ite then belong to the other tuner
                return TuneFlags(tbsy=False, te=True, ite=float(refused.ite))
            return None
        log.info("loop %s: TUNE from the device started session %s", loop_id, sid)
        return None

    # -- gains writes and restores after a crash ----------------------------------------------------------------

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
        while (read_back := await self.field.read_gains(loop.config.id)) is None:
            log.info("loop %s: gains write of session %s unconfirmed, the device is unreachable; retrying",
                     loop.config.id, sid)
            await asyncio.sleep(pause)
            pause = min(2.0 * pause, RECONCILE_RETRY_MAX)
        applied = same_gains(read_back, intended)
        why = await self.recorder.durable(self.history.resolve_intent, sid, read_back, applied)
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
            self.recorder.record(self.history.finish, record["id"], result, None, None,
                                 "not_restored" if saved is not None and loop is not None else "interrupted")
            code = Code.ABORTED
        else:
            result = record["result"]
            code = result.code if result else Code.ABORTED
            if loop is None:
                log.critical("loop %s: session %s left it not restored, and it is no longer configured: check it "
                             "by hand", record["loop"], record["id"])
        if loop is None or saved is None:
            return None
        loop.session, loop.result = record["id"], result
        # The MVs the session may have written: its recorded range (older records: the relay levels and saved MV).
        mv_range = mv_hull(saved["mv"], *saved.get("relay_levels", ()), *saved.get("mv_range", ()))
        loop.pending = Pending(record["id"], state_of(saved), mv_range, code, "interrupted",
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
        try:
            done = await self.field.restore(loop_id, p, self.handback_config.track_timeout)
        except (LinkError, NotTracking) as exc:
            p.attempts += 1
            p.error = str(exc) or type(exc).__name__
            log.error("loop %s: LOOP NOT RESTORED (session %s, %d tries): %s", loop_id, p.sid, p.attempts, p.error)
            self._publish(loop, "state", loop.as_json())
            return False
        log.log(logging.WARNING if done.warning else logging.INFO, "loop %s: %s (session %s, try %d)", loop_id,
                done.message, p.sid, p.attempts)
        # In the history's thread, after the session's end (a write queued before it, e.g. one retried while the
        # database is locked): the event loop never waits on the database, and the records keep their order.
        written = self.recorder.record(self.history.restored, p.sid, p.final, done.message, int(done.code))
        try:  # shown restored once recorded (bounded; not during a shutdown, whose bound is for the hand-backs)
            if not self._stopping and (why := await waited(written, self.recorder.wait)):
                log.error("loop %s: the restore of session %s is not recorded yet: %s", loop_id, p.sid, why)
        finally:  # cancelled while waiting (a shutdown): the loop is dealt with all the same
            loop.pending = None
            if loop.result is not None:
                loop.result = replace(loop.result, ite=int(done.code), te=True,
                                      message=f"{loop.result.message}; {done.message}")
            self._refresh_latest(loop)
            self._publish(loop, "state", loop.as_json())
        return True


def _model(record: dict[str, Any] | None) -> Process | None:
    """The process model a session identified, if it succeeded (None otherwise)."""
    if record is None or record["outcome"] != "success" or record["result"] is None or record["result"].point is None:
        return None
    try:
        return model_of(record["result"])
    except ValueError:
        return None


def _stored(rows: list[dict[str, Any]]) -> dict[str, Any] | None:
    """A stored assessment (the newest of ``rows``) as the loop keeps it: its JSON with ``time`` and ``session``."""
    if not rows:
        return None
    return {**rows[0]["assessment"], "time": rows[0]["time"], "session": rows[0]["session"]}


def _watching(loop: Loop) -> str:
    """What a loop's watch is called in the log."""
    return "handshake" if loop.config.handshake else "monitor"


