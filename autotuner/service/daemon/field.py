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
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Protocol

from drivers.link import Link, LinkError
from drivers.simplc import SimulatedPlc, run

from autotuner.engine.control.gains import Gains
from autotuner.engine.experiment.relay import Status
from autotuner.engine.simulated_tuning import DesignJob
from autotuner.service.config import LoopConfig
from autotuner.service.daemon.capacity import Cost
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


class Field(Protocol):
    """The device's side of every loop (see the module's docstring); loops named by id."""

    def bind(self, sink: FieldSink) -> None:
        """Report to ``sink`` (the loop manager) from now on."""

    async def start(self) -> None:
        """Start the simulated plants."""

    def watch(self) -> None:
        """Start the watch of every loop (monitor, handshake)."""

    async def check(self, loop_id: str) -> None:
        """The fresh check before a TUNE touches the loop (raises Refused)."""

    async def run(self, loop_id: str, sid: str, user: str, plan: SessionPlan) -> SessionOutcome:
        """Session ``sid`` asked by ``user``: the loop taken over, sampled, handed back; its outcome."""

    def abort(self, loop_id: str) -> None:
        """TBRK: abort the loop's running session (nothing if none runs)."""

    def load(self, loop_id: str, plan: SessionPlan | None = None) -> float:
        """The share of a core the loop's sampler is predicted to need (:mod:`~autotuner.service.daemon.capacity`),
        with a session of ``plan`` on the loop added (None: as it runs now)."""

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


def nominal_rate(loops: list[LoopConfig], sessions: dict[str, SessionPlan]) -> float:
    """Samples per second (wall) of ``sessions`` (by loop id) and of the monitor of the other ``loops``."""
    rate = 0.0
    for loop in loops:
        plan = sessions.get(loop.id)
        rate += 1.0 / loop.monitor_period if plan is None else plan.speed / plan.ts
    return rate


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

    def __init__(self, configs: list[LoopConfig]) -> None:
        self.reaches = {c.id: Reach.of(c) for c in configs}
        self._idle = {c.id: asyncio.Event() for c in configs}
        for idle in self._idle.values():
            idle.set()
        self._sessions: dict[str, tuple[asyncio.Event, SessionPlan]] = {}
        self._halt = asyncio.Event()
        self._plants_halt = asyncio.Event()
        self._watches: list[asyncio.Task[None]] = []
        self._plants: list[asyncio.Task[None]] = []
        self._sink: FieldSink | None = None
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
        sink = self._sink
        assert sink is not None, "the field is not started"
        for loop_id, reach in self.reaches.items():
            # The reach's connector is read at each use: a test may replace it.
            watch = Watch(reach.config, lambda r=reach: r.connect(), sink, self._idle[loop_id], self._halt,
                          self._timings.read)
            self._watches.append(asyncio.create_task(watch.run()))

    async def check(self, loop_id: str) -> None:
        reach = self.reaches[loop_id]
        await fresh_check(reach.config, reach.connect)

    async def run(self, loop_id: str, sid: str, user: str, plan: SessionPlan) -> SessionOutcome:
        sink = self._sink
        assert sink is not None, "the field is not started"
        stop = asyncio.Event()
        self._sessions[loop_id] = (stop, plan)
        self._idle[loop_id].clear()
        try:
            record = SessionRecord(lambda name, *args: sink.durable(loop_id, name, *args), sid, loop_id, user)

            def status(s: Status) -> None:
                tap = record.tap
                sink.status(loop_id, s, tap.pv if tap else float("nan"), tap.mv if tap else float("nan"))

            hooks = SessionHooks(stop=stop, on_status=status,
                                 on_handed_back=lambda error: sink.handed_back(loop_id, error),
                                 on_timing=lambda late, own, tolerance: self._timings.add(loop_id, late, own,
                                                                                          tolerance),
                                 on_analysis=self._timings.analysed, design=sink.design)
            return await run_session(self.reaches[loop_id].connect, plan, record, hooks)
        finally:
            del self._sessions[loop_id]
            self._idle[loop_id].set()

    def running(self) -> list[str]:
        """The loops whose session runs now."""
        return list(self._sessions)

    def load(self, loop_id: str, plan: SessionPlan | None = None) -> float:
        sessions = {loop: p for loop, (_, p) in self._sessions.items()}
        if plan is not None:
            sessions[loop_id] = plan
        return self.cost.load(nominal_rate([r.config for r in self.reaches.values()], sessions))

    def abort(self, loop_id: str) -> None:
        if loop_id in self._sessions:
            self._sessions[loop_id][0].set()

    def cap(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        for _, plan in self._sessions.values():
            plan.handback.cap = deadline

    async def write_gains(self, loop_id: str, gains: Gains) -> Gains:
        link = self.reaches[loop_id].connect()
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
            link = self.reaches[loop_id].connect()
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
        return await restore_once(self.reaches[loop_id].connect(), pending, track_timeout)

    async def halt_watches(self) -> None:
        self._halt.set()
        for watch in self._watches:
            watch.cancel()
        if self._watches:
            await asyncio.wait(self._watches, timeout=STOP_WAIT)
        self._watches = []

    async def _flush(self) -> None:
        """Every :data:`FLUSH_PERIOD`: the sessions' timings since the last batch, to the sink."""
        while True:
            await asyncio.sleep(FLUSH_PERIOD)
            batch = self._timings.take()
            self.cost.update(batch.cpu, batch.late.count + batch.readings)
            batch.cost = self.cost.per_sample
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
