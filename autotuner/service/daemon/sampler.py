"""The field in sampler processes of its own: nothing of the API's side can delay a sample.

A daemon with ``samplers: N`` (N ≥ 1) runs its loops' field — the sessions,
the monitor and handshake, the hand-backs and restores, the simulated plants
(:class:`~autotuner.service.daemon.field.LocalField`) — in N processes
(``python -m autotuner.service.daemon.sampler FD``), each with the loops of
some devices (a device's loops stay in one process). The API's process keeps
the loop manager, the history, the event streams and OPC UA; it talks to each
sampler over a socket pair (:class:`~autotuner.service.channel.Peer`):

front → sampler
    calls ``start``, ``check``, ``run``, ``write_gains``, ``read_gains``,
    ``restore``, ``halt_watches``, ``stop``; notifications ``watch``,
    ``serve``, ``grant``, ``unserve`` (a fleet's leases), ``abort``, ``cap``.
sampler → front
    calls ``durable`` (a session's record in the history), ``design`` (in the
    daemon's worker pool), ``edges`` (the device's TUNE/TBRK bits changed);
    notifications ``status``, ``handed_back``, ``timings``, ``reading``,
    ``link_failed``, ``link_back``, ``superseded`` (a device fenced the
    daemon off a loop); its log records.

A sampler ends when the daemon says stop, and when its channel closes (the
daemon died, even by SIGKILL): then it aborts every session, hands every loop
back (within :data:`LOST_HANDBACK` seconds) and exits. A sampler that dies is
started again by the daemon; its sessions end as interrupted and their loops
are restored as after a crash of the daemon (docs/handback.md).
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import subprocess
import sys
from collections.abc import Awaitable
from dataclasses import dataclass
from typing import Any

from drivers.link import LinkError, TuneFlags

from autotuner.engine.control.gains import Gains
from autotuner.engine.experiment.relay import Status
from autotuner.engine.outcome import Code
from autotuner.engine.simulated_tuning import DesignJob
from autotuner.service import heap
from autotuner.service.channel import (Channel, Peer, PeerLost, child_start, log_levels, log_record, start_child,
                                       tree_cpu_seconds)
from autotuner.service.config import LoopConfig
from autotuner.service.daemon.analyses import AnalysisWorkers, worker_count
from autotuner.service.daemon.capacity import Cost
from autotuner.service.daemon.field import FieldSink, Lease, LocalField, nominal_rate
from autotuner.service.daemon.refused import Refused
from autotuner.service.daemon.restore import Pending, Restored
from autotuner.service.daemon.timing import TimingBatch
from autotuner.service.daemon.watch import Reading
from autotuner.service.design_pool import Outcome
from autotuner.service.link_session import SessionPlan
from autotuner.service.session_runner import SessionOutcome

MODULE = "autotuner.service.daemon.sampler"
# What each side serves of the other's messages.
SAMPLER_CALLS = frozenset({"start", "check", "run", "write_gains", "read_gains", "restore", "halt_watches", "stop"})
SAMPLER_NOTES = frozenset({"watch", "serve", "grant", "unserve", "abort", "cap"})
FRONT_CALLS = frozenset({"durable", "design", "edges"})
FRONT_NOTES = frozenset({"status", "handed_back", "timings", "reading", "link_failed", "link_back", "superseded"})
# How long a sampler whose daemon is gone may take to hand its loops back, wall seconds.
LOST_HANDBACK = 20.0
# How long the daemon waits for a sampler to start (imports, plants) and to stop, wall seconds.
START_WAIT, STOP_WAIT = 60.0, 30.0
# Pause before a sampler that died is started again, wall seconds.
RESTART_PAUSE = 1.0
# A sampler asks the kernel for real-time round-robin scheduling at this priority (1–99): it then runs as soon as it
# wakes for a sample, before any ordinary process, however busy the machine (and whatever its sessions' groups:
# nice values only count within one). Its analysis workers run as ordinary processes: their work may wait, the
# samples may not. Without the privilege (CAP_SYS_NICE), nice PRIORITY_NICE, else nothing. (The kernel caps
# real-time tasks at 95 % of a core each second by default, so a runaway sampler cannot freeze the machine.)
RT_PRIORITY, PRIORITY_NICE = 20, -5
# The GIL's switch interval in a sampler, seconds: the event loop waits at most this for another thread's GIL.
SWITCH_INTERVAL = 0.001
# The loggers whose levels a sampler takes from the daemon's.
LEVELS = ("", "autotuner", "pymodbus", "can")
log = logging.getLogger("autotuner.service.daemon")


@dataclass(frozen=True)
class SamplerInit:
    """What a sampler needs to start: its number, its loops and the daemon's log levels."""

    shard: int
    loops: list[LoopConfig]
    levels: dict[str, int]


# -- the sampler process ----------------------------------------------------------------------------------------


class _ToDaemon(FieldSink):
    """The field's sink inside a sampler: every report and question goes to the daemon over ``peer``."""

    def __init__(self, peer: Peer) -> None:
        self.peer = peer

    def status(self, loop_id: str, status: Status, pv: float, mv: float) -> None:
        self.peer.note("status", loop_id, status, pv, mv)

    def handed_back(self, loop_id: str, error: str) -> None:
        self.peer.note("handed_back", loop_id, error)

    def timings(self, batch: TimingBatch) -> None:
        self.peer.note("timings", batch)

    def reading(self, loop_id: str, reading: Reading) -> None:
        self.peer.note("reading", loop_id, reading)

    def link_failed(self, loop_id: str, error: str) -> None:
        self.peer.note("link_failed", loop_id, error)

    def link_back(self, loop_id: str) -> None:
        self.peer.note("link_back", loop_id)

    def superseded(self, loop_id: str) -> None:
        self.peer.note("superseded", loop_id)

    async def durable(self, loop_id: str, name: str, *args: object) -> str:
        try:
            return await self.peer.call("durable", loop_id, name, *args)
        except PeerLost as exc:  # the daemon is gone: nothing can be recorded, so nothing is written that needs it
            return f"the daemon's history is out of reach ({exc})"

    async def design(self, job: DesignJob) -> Outcome:
        try:
            return await self.peer.call("design", job)
        except PeerLost:  # the daemon is gone: designed here, so the session still ends as it should
            return await asyncio.to_thread(job.run)

    async def edges(self, loop_id: str, last: TuneFlags, flags: TuneFlags) -> TuneFlags | None:
        return await self.peer.call("edges", loop_id, last, flags)


class _Sampler:
    """What the daemon may call in a sampler: its :class:`LocalField`'s methods, and ``stop``."""

    def __init__(self, field: LocalField) -> None:
        self.field = field
        self.stopped = asyncio.Event()

    def __getattr__(self, name: str) -> Any:
        return getattr(self.field, name)

    async def stop(self) -> None:
        await self.field.stop()
        self.stopped.set()


async def serve(fd: int) -> None:
    """The sampler's work: the daemon's init over the socket ``fd``, then its calls until told to stop or the
    daemon is gone (then every loop is handed back first)."""
    started = await child_start(fd)
    if started is None:
        return
    channel, init = started
    realtime = _raise_priority(init.shard)
    sys.setswitchinterval(SWITCH_INTERVAL)
    workers = worker_count()
    analyses = AnalysisWorkers(workers, RT_PRIORITY - 1 if realtime else None) if workers else None
    field = LocalField(init.loops, analyses)
    sampler = _Sampler(field)
    peer = Peer(channel, sampler, SAMPLER_CALLS, SAMPLER_NOTES)
    field.bind(_ToDaemon(peer))
    log.info("sampler %d: %d objects of its start out of the garbage collector's walks", init.shard, heap.settle())
    channel.send("ready")
    await peer.serve()
    if not sampler.stopped.is_set():  # the daemon is gone: its sessions' loops are handed back before the end
        for loop_id, sid in field.running().items():
            field.abort(loop_id, sid)
        field.cap(LOST_HANDBACK)
        await peer.drain(LOST_HANDBACK + 5.0)
        await field.stop()
    await channel.close()
    if analyses is not None:
        analyses.close()


def _raise_priority(shard: int) -> bool:
    """Real-time scheduling for this (the event loop's) thread, else a higher nice value, else nothing (said once);
    True with real time."""
    try:
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(RT_PRIORITY))
        log.info("sampler %d runs with real-time priority (SCHED_RR %d)", shard, RT_PRIORITY)
        return True
    except (PermissionError, OSError):
        pass
    try:
        os.setpriority(os.PRIO_PROCESS, 0, PRIORITY_NICE)
        log.info("sampler %d runs at nice %d (no real-time priority: it needs CAP_SYS_NICE and, where the kernel "
                 "schedules real time by groups, a real-time budget for its cgroup: docs/daemon.md)", shard,
                 PRIORITY_NICE)
    except PermissionError:
        log.info("sampler %d runs at the same priority as the API (a higher one needs CAP_SYS_NICE): a machine "
                 "busy with other programs can delay its samples", shard)
    return False


def main(argv: list[str]) -> int:
    """``python -m autotuner.service.daemon.sampler FD``: a sampler over the socket ``FD``."""
    # Ctrl-C in a terminal signals the whole process group: the daemon stops its samplers itself, after the
    # hand-back; a SIGTERM to the sampler alone is taken as the daemon's end.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    asyncio.run(serve(int(argv[1])))
    return 0


# -- the daemon's side ------------------------------------------------------------------------------------------


class _Shard:
    """One sampler process and its loops, as the daemon sees it; started again when it dies."""

    def __init__(self, number: int, loops: list[LoopConfig]) -> None:
        self.number, self.loops = number, loops
        self.cost = Cost()  # the sampler's own estimate, from its timings
        self.served: dict[str, Lease] = {}  # a fleet's loops served here and their leases
        self.process: subprocess.Popen[bytes] | None = None
        self.peer: Peer | None = None
        self.watching = False
        self.stopping = False
        self._serving: asyncio.Task[None] | None = None

    async def start(self, sink: FieldSink) -> None:
        """Start the process and its field (plants); back once it is ready."""
        self.process, ours = start_child(MODULE)
        channel = await Channel.open(ours)
        channel.send("init", SamplerInit(self.number, self.loops, log_levels(LEVELS)))
        try:
            await asyncio.wait_for(self._ready(channel), START_WAIT)
        except BaseException:
            await channel.close()
            self._kill()
            raise
        self.peer = Peer(channel, _FromSampler(self, sink), FRONT_CALLS, FRONT_NOTES)
        self._serving = asyncio.create_task(self._serve(sink))
        await self.peer.call("start")
        if self.watching:  # (a sampler started again: what the one before did)
            self.peer.note("watch")
        for loop_id, lease in self.served.items():
            self.peer.note("serve", loop_id, lease)

    async def _ready(self, channel: Channel) -> None:
        while (message := await channel.receive()) is not None:
            if message[0] == "ready":
                return
            if message[0] == "log":
                log_record(*message[1:])
        raise RuntimeError(f"sampler {self.number} ended (exit code {self._exit_code()}) before it was ready")

    async def _serve(self, sink: FieldSink) -> None:
        assert self.peer is not None
        await self.peer.serve(close=False)
        if self.stopping:
            self.peer.close(f"sampler {self.number} stopped")
            return
        try:
            code: int | str | None = await asyncio.to_thread(self._wait, STOP_WAIT)
        except subprocess.TimeoutExpired:
            code = "none yet (it closed its channel)"
        why = f"sampler {self.number} (process {self.process.pid if self.process else '?'}) ended, exit code {code}"
        self.peer.close(why)
        log.error("%s: its sessions end as interrupted and its loops are restored; starting it again", why)
        while not self.stopping:
            await asyncio.sleep(RESTART_PAUSE)
            try:
                await self.start(sink)
                return
            except Exception as exc:
                log.error("sampler %d did not start again (%s); retrying", self.number, exc)

    def call(self, op: str, *args: Any) -> Awaitable[Any]:
        """``op(*args)`` in the sampler (PeerLost while it is not running)."""
        if self.peer is None:
            raise PeerLost(f"sampler {self.number} is not running")
        return self.peer.call(op, *args)

    def note(self, op: str, *args: Any) -> None:
        if self.peer is not None:
            self.peer.note(op, *args)

    async def stop(self) -> None:
        """Stop the sampler (its field: watches, plants) and wait for its process to end."""
        self.stopping = True
        try:
            if self.peer is not None and self.peer.lost is None:
                await asyncio.wait_for(self.call("stop"), STOP_WAIT)
        except (PeerLost, asyncio.TimeoutError) as exc:
            log.warning("sampler %d did not stop cleanly: %s", self.number, exc)
        if self.peer is not None:
            await self.peer.channel.close()
        if self._serving is not None:
            await asyncio.gather(self._serving, return_exceptions=True)
        try:
            await asyncio.to_thread(self._wait, STOP_WAIT)
        except subprocess.TimeoutExpired:
            log.warning("sampler %d did not end within %g s: killed", self.number, STOP_WAIT)
            self._kill()

    def _wait(self, timeout: float | None = None) -> int | None:
        return None if self.process is None else self.process.wait(timeout)

    def _exit_code(self) -> int | None:
        return None if self.process is None else self.process.poll()

    def _kill(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()


class _FromSampler:
    """What a sampler tells the daemon goes to its sink; its timings also update the shard's cost estimate."""

    def __init__(self, shard: _Shard, sink: FieldSink) -> None:
        self.shard, self.sink = shard, sink

    def timings(self, batch: TimingBatch) -> None:
        if batch.cost is not None:
            self.shard.cost = batch.cost
        self.sink.timings(batch)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.sink, name)


def shards_of(loops: list[LoopConfig], count: int) -> list[list[LoopConfig]]:
    """``loops`` in ``count`` shards (fewer if there are fewer devices): a device's loops together, the shards as
    even in loops as whole devices allow (the largest device first into the emptiest shard)."""
    devices: dict[str, list[LoopConfig]] = {}
    for loop in loops:
        devices.setdefault(device_of(loop), []).append(loop)
    shards: list[list[LoopConfig]] = [[] for _ in range(min(count, len(devices)))]
    for group in sorted(devices.values(), key=len, reverse=True):
        min(shards, key=len).extend(group)
    return [shard for shard in shards if shard]


def device_of(loop: LoopConfig) -> str:
    """The device a loop is on: its link's endpoint (scheme and host:port, or serial device, or CAN channel); a
    simulated loop is a device of its own."""
    if loop.link is None:
        return f"sim:{loop.id}"
    scheme, _, rest = loop.link.partition("://")
    endpoint = rest.split("?")[0]
    if scheme.startswith("modbus") and scheme != "modbus+rtu":
        endpoint = endpoint.split("/")[0]  # the unit id is a loop of the device
    return f"{scheme}://{endpoint}"


class SamplerField:
    """The :class:`~autotuner.service.daemon.field.Field` of ``loops`` in ``count`` sampler processes."""

    reaches: dict[str, Any] = {}  # no loop's device is reached from this process

    def __init__(self, loops: list[LoopConfig], count: int) -> None:
        if count < 1:
            raise ValueError(f"at least one sampler process, got {count}")
        self._shards = [_Shard(i + 1, shard) for i, shard in enumerate(shards_of(loops, count))]
        self._of = {loop.id: shard for shard in self._shards for loop in shard.loops}
        self._sink: FieldSink | None = None

    @property
    def pids(self) -> list[int]:
        """The sampler processes running now."""
        return [s.process.pid for s in self._shards if s.process is not None and s.process.poll() is None]

    def cpu_seconds(self) -> dict[int, float]:
        """CPU seconds (user + system) each running sampler process and its analysis workers have used, by its
        number."""
        running = {s.number: tree_cpu_seconds(s.process.pid) for s in self._shards if s.process is not None}
        return {number: seconds for number, seconds in running.items() if seconds is not None}

    def bind(self, sink: FieldSink) -> None:
        self._sink = sink

    async def start(self) -> None:
        assert self._sink is not None, "bind the field to its loop manager first"
        await asyncio.gather(*(shard.start(self._sink) for shard in self._shards))
        log.info("%d sampler process(es) for %d loop(s): %s", len(self._shards), len(self._of),
                 ", ".join(str(pid) for pid in self.pids))

    def watch(self) -> None:
        for shard in self._shards:
            shard.watching = True
            shard.note("watch")

    def serve(self, loop_id: str, lease: Lease) -> None:
        shard = self._of[loop_id]
        shard.served[loop_id] = lease
        shard.note("serve", loop_id, lease)

    def grant(self, loop_id: str, lease: Lease) -> None:
        shard = self._of[loop_id]
        shard.served[loop_id] = lease
        shard.note("grant", loop_id, lease)

    def unserve(self, loop_id: str) -> None:
        shard = self._of[loop_id]
        shard.served.pop(loop_id, None)
        shard.note("unserve", loop_id)

    async def check(self, loop_id: str) -> None:
        try:
            await self._of[loop_id].call("check", loop_id)
        except PeerLost as exc:
            raise Refused("link_unhealthy", f"loop {loop_id!r} not tuned: {exc}", Code.REFUSED_LINK) from None

    async def run(self, loop_id: str, sid: str, user: str, plan: SessionPlan) -> SessionOutcome:
        return await self._of[loop_id].call("run", loop_id, sid, user, plan)

    def load(self, loop_id: str, sessions: dict[str, SessionPlan]) -> float:
        shard = self._of[loop_id]
        return shard.cost.load(nominal_rate(shard.loops, sessions))

    def abort(self, loop_id: str, sid: str) -> None:
        self._of[loop_id].note("abort", loop_id, sid)

    def cap(self, seconds: float) -> None:
        for shard in self._shards:
            shard.note("cap", seconds)

    async def write_gains(self, loop_id: str, gains: Gains) -> Gains:
        try:
            return await self._of[loop_id].call("write_gains", loop_id, gains)
        except PeerLost as exc:
            raise LinkError(str(exc)) from None

    async def read_gains(self, loop_id: str) -> Gains | None:
        try:
            return await self._of[loop_id].call("read_gains", loop_id)
        except PeerLost:
            return None

    async def restore(self, loop_id: str, pending: Pending, track_timeout: float) -> Restored:
        try:
            return await self._of[loop_id].call("restore", loop_id, pending, track_timeout)
        except PeerLost as exc:
            raise LinkError(str(exc)) from None

    async def halt_watches(self) -> None:
        for shard in self._shards:
            shard.watching = False
        await asyncio.gather(*(self._quiet(shard.call("halt_watches")) for shard in self._shards
                               if shard.peer is not None))

    async def stop(self) -> None:
        await asyncio.gather(*(shard.stop() for shard in self._shards))

    @staticmethod
    async def _quiet(call: Awaitable[Any]) -> None:
        try:
            await call
        except PeerLost:
            pass


if __name__ == "__main__":
    sys.exit(main(sys.argv))
