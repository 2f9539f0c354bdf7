"""The daemon's field: everything that touches a device, behind one interface (:class:`Field`).

The loop manager decides (TUNE admitted or refused, a restore due, gains to
apply) and records; the field does the device's side: the fresh check before
a TUNE, the session itself (:func:`~autotuner.service.session_runner.run_session`),
the gains written and read back, a restore try, the watch of every loop
(monitor and handshake) and the simulated plants. It reports to a
:class:`FieldSink` (the manager): monitor readings, link failures, the
handshake's edges, each session's status and timing, and it asks the sink
for what only the manager can do — a durable record in the history, a
design in its worker pool.

:class:`LocalField` does all that on the caller's event loop (tests,
``tune --config``, a daemon with ``samplers: 0``);
:class:`~autotuner.service.daemon.sampler.SamplerField` runs LocalFields in
sampler processes of their own, so that nothing of the API's side — clients,
event streams, OPC UA, the history — can delay a sample.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any, Protocol

from drivers.link import Fenced, Link, LinkError
from drivers.simplc import SimulatedPlc, run

from autotuner.engine.control.gains import Gains
from autotuner.engine.experiment.relay import Status
from autotuner.engine.simulated_tuning import DesignJob
from autotuner.service.config import LoopConfig
from autotuner.service.daemon.analyses import AnalysisWorkers
from autotuner.service.daemon.capacity import Cost, Rates
from autotuner.service.daemon.reach import connector, fresh_check, simulated_plc
from autotuner.service.daemon.restore import Pending, Restored, restore_once
from autotuner.service.daemon.timing import FLUSH_PERIOD, TimingBatch, Timings
from autotuner.service.daemon.watch import Watch, WatchSink
from autotuner.service.design_pool import Outcome
from autotuner.service.link_session import SessionHooks, SessionPlan
from autotuner.service.session_record import SessionRecord, read_gains
from autotuner.service.session_runner import SessionOutcome, run_session

# How long the watches may take to end once halted, wall seconds.
STOP_WAIT = 10.0
log = logging.getLogger("autotuner.service.daemon")


class FieldSink(WatchSink, Protocol):
    """What the field tells (and asks) the loop manager, besides the watches' reports."""

    def status(self, loop_id: str, status: Status, pv: float, mv: float) -> None:
        """A running session's status after a sample, with the PV read (PV units) and MV written (MV units)."""

    def handed_back(self, loop_id: str, error: str) -> None:
        """The running session's hand-back is over: '' or why the loop is not handed back."""

    def timings(self, batch: TimingBatch) -> None:
        """The sessions' sample timings since the last batch (:mod:`~autotuner.service.daemon.timing`)."""

    def durable(self, loop_id: str, name: str, *args: object) -> Awaitable[str]:
        """Record ``History.<name>(*args)`` ("saved" or "intend") and wait (bounded): '' once recorded, else why not."""

    def design(self, job: DesignJob) -> Awaitable[Outcome]:
        """The design of an ended experiment."""

    def superseded(self, loop_id: str) -> None:
        """The loop's device refused a write: it was written a newer lease epoch than this daemon's (another daemon
        took the loop over). Reported once, when it happens: the field writes nothing more to the loop meanwhile."""


class Field(Protocol):
    """The device's side of every loop (see the module's docstring); loops named by id."""

    def bind(self, sink: FieldSink) -> None:
        """Report to ``sink`` (the loop manager) from now on."""

    async def start(self) -> None:
        """Start the simulated plants."""

    def watch(self) -> None:
        """Serve every loop: start its watch (monitor, handshake); its writes never fenced (one daemon, no leases)."""

    def serve(self, loop_id: str, lease: Lease) -> None:
        """Serve the loop (a lease taken): start its watch, allow writes to it under ``lease``."""

    def grant(self, loop_id: str, lease: Lease) -> None:
        """Allow writes to a loop served under ``lease`` (renewed, or taken)."""

    def unserve(self, loop_id: str) -> None:
        """Stop serving the loop at once (its lease lost or released): its watch ends, every write to it is refused
        (:class:`~autotuner.service.link_session.Fenced`), a session on it ends without writing another word."""

    async def check(self, loop_id: str) -> None:
        """The fresh check before a TUNE touches the loop (raises Refused)."""

    async def run(self, loop_id: str, sid: str, user: str, plan: SessionPlan) -> SessionOutcome:
        """Session ``sid`` asked by ``user``: the loop taken over, sampled, handed back; its outcome."""

    def abort(self, loop_id: str, sid: str) -> None:
        """TBRK: abort session ``sid`` of the loop, at once or as soon as it starts here (an abort may arrive
        before the session's own start, never after its end matters)."""

    def load(self, loop_id: str, sessions: dict[str, SessionPlan]) -> float:
        """The share of a core the sampler of ``loop_id`` is predicted to need (:mod:`~autotuner.service.daemon.capacity`)
        with ``sessions`` running (loop id → plan: every session of the daemon; those of the sampler's loops count)."""

    def cap(self, seconds: float) -> None:
        """No hand-back try of a running session starts later than ``seconds`` wall seconds from now."""

    async def write_gains(self, loop_id: str, gains: Gains) -> Gains:
        """Write ``gains`` to the controller and read them back (the written ones if the read fails); LinkError."""

    async def read_gains(self, loop_id: str) -> Gains | None:
        """The controller's gains; None if the device cannot be reached."""

    async def restore(self, loop_id: str, pending: Pending, track_timeout: float) -> Restored:
        """One try at the loop's pending restore (:func:`~autotuner.service.daemon.restore.restore_once`)."""

    async def halt_watches(self) -> None:
        """End the watches (a daemon that stops: no more readings, no TUNE from a device)."""

    async def stop(self) -> None:
        """End everything: the watches, then the simulated plants (after the sessions have ended)."""


def nominal_rate(loops: list[LoopConfig], sessions: dict[str, SessionPlan]) -> Rates:
    """Samples per second (wall) of the ``sessions`` (by loop id) of ``loops``, and readings per second of the monitor
    of their other loops."""
    ours = {loop.id for loop in loops}
    samples = sum(plan.speed / plan.ts for loop_id, plan in sessions.items() if loop_id in ours)
    readings = sum(1.0 / loop.monitor_period for loop in loops if loop.id not in sessions)
    return Rates(samples, readings)


@dataclass(frozen=True)
class Lease:
    """A loop's lease as held here: valid ``until`` (monotonic), its ``epoch`` (written to the device)."""

    until: float
    epoch: int


class Fence(Protocol):
    """Whether a loop may be written, with which lease epoch, and who hears that its device fenced this daemon off."""

    def writable(self, loop_id: str) -> bool:
        """The loop may be written now."""

    def epoch(self, loop_id: str) -> int | None:
        """The epoch of the loop's lease held here (None: no leases)."""

    def superseded(self, loop_id: str, error: str) -> None:
        """The loop's device refused a write (``error``): it holds a newer epoch; nothing more may be written."""


class FencedLink:
    """``link`` with every write refused (:class:`~drivers.link.Fenced`) unless ``fence`` lets loop ``loop_id`` be
    written, each write carrying the lease's epoch to the device: a daemon that lost the loop's lease — on its
    own clock, or as the device sees it — writes nothing more to it; reads go through."""

    WRITES = frozenset({"write_mv", "write_mode", "write_gains", "write_flags", "write_watchdog", "write_heartbeat"})

    def __init__(self, link: Link, fence: Fence, loop_id: str) -> None:
        self._link, self._fence, self._loop_id = link, fence, loop_id

    def __getattr__(self, name: str) -> Any:
        attribute = getattr(self._link, name)
        if name not in self.WRITES:
            return attribute

        async def fenced(*args: Any) -> Any:
            if not self._fence.writable(self._loop_id):
                raise Fenced(f"loop {self._loop_id}: this daemon's lease on it has expired or was taken over; "
                             "nothing more is written to it (its owner restores it)")
            self._link.epoch = self._fence.epoch(self._loop_id)
            try:
                return await attribute(*args)
            except Fenced as exc:  # the device's fence: the same as a lease lost here, from now on
                self._fence.superseded(self._loop_id, str(exc))
                raise

        return fenced


def _carries_epoch(reach: Reach) -> bool:
    """Whether the loop's device has a place for the lease's epoch (a link made to see; False if none can be)."""
    try:
        return reach.connect().carries_epoch
    except LinkError:
        return False


@dataclass
class Reach:
    """How a loop is reached: its config, a connector for new links and its simulated PLC (None: a real one)."""

    config: LoopConfig
    connect: Callable[[], Link]
    plc: SimulatedPlc | None

    @classmethod
    def of(cls, config: LoopConfig) -> Reach:
        """The reach of ``config``: its simulated PLC if it is a ``sim:`` loop, else its link's URL and map."""
        plc = simulated_plc(config)
        return cls(config, connector(config, plc), plc)


class LocalField:
    """The field of ``configs`` on the running event loop (:class:`Field`)."""

    def __init__(self, configs: list[LoopConfig], analyses: AnalysisWorkers | None = None) -> None:
        self.reaches = {c.id: Reach.of(c) for c in configs}
        self._analyses = analyses
        self._idle = {c.id: asyncio.Event() for c in configs}
        for idle in self._idle.values():
            idle.set()
        self._sessions: dict[str, tuple[asyncio.Event, SessionPlan]] = {}
        self._sids: dict[str, str] = {}  # the session id running on each loop
        self._aborted: set[str] = set()  # sessions aborted before they started here
        self._halt = asyncio.Event()
        self._plants_halt = asyncio.Event()
        self._watches: dict[str, asyncio.Task[None]] = {}
        # The lease under which each loop may be written; None: every loop always (no leases).
        self._grants: dict[str, Lease] | None = None
        self._plants: list[asyncio.Task[None]] = []
        self._sink: FieldSink | None = None
        self._told: set[str] = set()  # loops whose device was said to have no place for the epoch
        self._timings = Timings()
        self._flusher: asyncio.Task[None] | None = None
        self.cost = Cost()

    def bind(self, sink: FieldSink) -> None:
        self._sink = sink

    async def start(self) -> None:
        self._flusher = asyncio.create_task(self._flush())
        for reach in self.reaches.values():
            if reach.plc is not None:
                self._plants.append(asyncio.create_task(run(reach.plc, reach.config.speed, self._plants_halt)))

    def watch(self) -> None:
        for loop_id in self.reaches:
            self._start_watch(loop_id)

    def serve(self, loop_id: str, lease: Lease) -> None:
        self.grant(loop_id, lease)
        self._start_watch(loop_id)
        reach = self.reaches[loop_id]
        if loop_id not in self._told and not _carries_epoch(reach):
            self._told.add(loop_id)
            log.warning("loop %s: its device has no place for the lease's epoch (%s): nothing on the device's side "
                        "refuses the writes of a daemon that lost the lease, only that daemon's own clock "
                        "(docs/fleet.md)", loop_id, "a simulated PLC of this process" if reach.plc is not None
                        else "no epoch register in its map" if str(reach.config.link).startswith("modbus")
                        else "no Epoch signals in its DBC")

    def grant(self, loop_id: str, lease: Lease) -> None:
        if self._grants is None:
            self._grants = {}
        self._grants[loop_id] = lease

    def unserve(self, loop_id: str) -> None:
        if self._grants is None:
            self._grants = {}
        self._grants.pop(loop_id, None)
        watch = self._watches.pop(loop_id, None)
        if watch is not None:
            watch.cancel()

    def _start_watch(self, loop_id: str) -> None:
        sink = self._sink
        assert sink is not None, "the field is not bound to its loop manager"
        if loop_id not in self._watches:
            watch = Watch(self.reaches[loop_id].config, lambda: self._connect(loop_id), sink, self._idle[loop_id],
                          self._halt, self._timings.read)
            self._watches[loop_id] = asyncio.create_task(watch.run())

    def writable(self, loop_id: str) -> bool:
        """The loop may be written now (no leases, or its lease valid here)."""
        if self._grants is None:
            return True
        lease = self._grants.get(loop_id)
        return lease is not None and time.monotonic() < lease.until

    def epoch(self, loop_id: str) -> int | None:
        """The epoch of the loop's lease held here (None: no leases, or none held)."""
        lease = None if self._grants is None else self._grants.get(loop_id)
        return None if lease is None else lease.epoch

    def superseded(self, loop_id: str, error: str) -> None:
        """The loop's device refused a write, holding a newer epoch: nothing more is written to it (its grant is
        withdrawn at once), logged and told to the loop manager once per lease."""
        lease = None if self._grants is None else self._grants.pop(loop_id, None)
        if lease is None:
            return  # withdrawn already (told once)
        log.error("loop %s: its device refused this daemon's write under lease epoch %d: %s", loop_id, lease.epoch,
                  error)
        if self._sink is not None:
            self._sink.superseded(loop_id)

    def _connect(self, loop_id: str) -> Link:
        """A new link to the loop, its writes fenced by the loop's lease. (The reach's connector is read at each
        use: a test may replace it.)"""
        return FencedLink(self.reaches[loop_id].connect(), self, loop_id)

    async def check(self, loop_id: str) -> None:
        await fresh_check(self.reaches[loop_id].config, lambda: self._connect(loop_id))

    async def run(self, loop_id: str, sid: str, user: str, plan: SessionPlan) -> SessionOutcome:
        sink = self._sink
        assert sink is not None, "the field is not started"
        stop = asyncio.Event()
        if sid in self._aborted:
            self._aborted.discard(sid)
            stop.set()  # aborted before it started: it ends before it touches the loop
        self._sessions[loop_id] = (stop, plan)
        self._sids[loop_id] = sid
        self._idle[loop_id].clear()
        if self._analyses is not None:
            self._analyses.want()
        try:
            record = SessionRecord(lambda name, *args: sink.durable(loop_id, name, *args), sid, loop_id, user)

            def status(s: Status) -> None:
                tap = record.tap
                sink.status(loop_id, s, tap.pv if tap else float("nan"), tap.mv if tap else float("nan"))

            hooks = SessionHooks(stop=stop, on_status=status,
                                 on_handed_back=lambda error: sink.handed_back(loop_id, error),
                                 on_timing=lambda late, own, tolerance: self._timings.add(loop_id, late, own,
                                                                                          tolerance),
                                 on_analysis=self._timings.analysed, design=sink.design,
                                 analyse=None if self._analyses is None else self._analyses.analyse)
            return await run_session(lambda: self._connect(loop_id), plan, record, hooks)
        finally:
            del self._sessions[loop_id]
            del self._sids[loop_id]
            self._idle[loop_id].set()

    def running(self) -> dict[str, str]:
        """The sessions running now: session id by loop id."""
        return dict(self._sids)

    def load(self, loop_id: str, sessions: dict[str, SessionPlan]) -> float:
        return self.cost.load(nominal_rate([r.config for r in self.reaches.values()], sessions))

    def abort(self, loop_id: str, sid: str) -> None:
        if self._sids.get(loop_id) == sid:
            self._sessions[loop_id][0].set()
        else:
            self._aborted.add(sid)

    def cap(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        for _, plan in self._sessions.values():
            plan.handback.cap = deadline

    async def write_gains(self, loop_id: str, gains: Gains) -> Gains:
        link = self._connect(loop_id)
        try:
            await link.open()
            await link.write_gains(gains)
            read_back = await read_gains(link)
            if read_back is None:
                log.warning("loop %s: gains written but not read back", loop_id)
            return gains if read_back is None else read_back
        finally:
            await link.close()

    async def read_gains(self, loop_id: str) -> Gains | None:
        try:
            link = self._connect(loop_id)
        except LinkError:
            return None
        try:
            await link.open()
            return await read_gains(link)
        except LinkError:
            return None
        finally:
            await link.close()

    async def restore(self, loop_id: str, pending: Pending, track_timeout: float) -> Restored:
        return await restore_once(self._connect(loop_id), pending, track_timeout)

    async def halt_watches(self) -> None:
        self._halt.set()
        watches, self._watches = list(self._watches.values()), {}
        for watch in watches:
            watch.cancel()
        if watches:
            await asyncio.wait(watches, timeout=STOP_WAIT)

    async def _flush(self) -> None:
        """Every :data:`FLUSH_PERIOD`: the sessions' timings since the last batch, to the sink."""
        while True:
            await asyncio.sleep(FLUSH_PERIOD)
            batch = self._timings.take()
            self.cost.update(batch.cpu, batch.late.count, batch.readings)
            batch.cost = dataclasses.replace(self.cost)
            if self._sink is not None:
                self._sink.timings(batch)

    async def stop(self) -> None:
        await self.halt_watches()
        if self._flusher is not None:
            self._flusher.cancel()
        self._plants_halt.set()
        with contextlib.suppress(Exception):
            await asyncio.gather(*self._plants)
        self._plants = []
