"""A loop's watch: the monitor of an idle loop and the device's handshake bits, on a link of its own.

Each loop has one watch task (the session's sampling is not involved).
While the loop is idle it monitors it: every ``monitor_period`` wall seconds
it reads the mode, SP, MV and gains and the PV and reports the reading. It
does not read the loop while the loop's session runs; the session's own
samples are the live values then.

A loop configured with ``handshake: true`` also obeys the device's own bits,
like the function block wired to an HMI: its watch also reads the flags
every ``handshake_poll`` wall seconds, idle or busy, and reports their
changes (the daemon acts on a rising edge of TUNE or TBRK). The first reading
of the bits after (re)connecting is only a reference: a bit already true then
is no edge, so a TUNE left set across a restart or a link outage never starts
an experiment by itself. Without a handshake the link is closed while the
loop's session runs.

Link errors are reported (the daemon logs them once per outage and shows
them in the status) and retried with a pause growing from the period to
:data:`LINK_RETRY_MAX`; they never reach another loop.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Protocol

from drivers.link import Link, LinkError, LoopState, TuneFlags

from autotuner.service.config import LoopConfig

# Longest pause between two tries of a watch whose link fails, wall seconds.
LINK_RETRY_MAX = 5.0
log = logging.getLogger("autotuner.service.daemon")


@dataclass(frozen=True)
class Reading:
    """One monitor reading of an idle loop: its state, its PV (PV units) and when (unix seconds)."""

    state: LoopState
    pv: float
    time: float


class WatchSink(Protocol):
    """Where a watch reports (the daemon's loop manager)."""

    def reading(self, loop_id: str, reading: Reading) -> None:
        """A monitor reading of the idle loop."""

    def link_failed(self, loop_id: str, error: str) -> None:
        """The watch's link failed (each try of an outage)."""

    def link_back(self, loop_id: str) -> None:
        """The watch's link works again after a failure."""

    def edges(self, loop_id: str, last: TuneFlags, flags: TuneFlags) -> Awaitable[TuneFlags | None]:
        """The handshake bits went from ``last`` to ``flags``: the flags to write back (a refused TUNE), or None."""


class Watch:
    """The watch of loop ``config`` through links from ``connect``, reporting to ``sink``.

    ``idle``: set while no session runs on the loop; the watch ends when
    ``halt`` is set (or it is cancelled); ``counted`` is called at each
    monitor reading (the field's capacity counts them).
    """

    def __init__(self, config: LoopConfig, connect: Callable[[], Link], sink: WatchSink, idle: asyncio.Event,
                 halt: asyncio.Event, counted: Callable[[], None] = lambda: None) -> None:
        self.config, self.connect, self.sink, self.idle, self.halt = config, connect, sink, idle, halt
        self.counted = counted
        self.failing = False

    async def run(self) -> None:
        """Watch until halted or cancelled (one link, opened on first use and after a failure)."""
        config = self.config
        period = min(config.handshake_poll, config.monitor_period) if config.handshake else config.monitor_period
        pause = period
        link: Link | None = None
        last: TuneFlags | None = None
        monitor_due = 0.0
        try:
            while not self.halt.is_set():
                try:
                    if not config.handshake and not self.idle.is_set():
                        if link is not None:
                            await link.close()
                            link = None
                        await self.idle.wait()  # nothing to read while the session runs
                        monitor_due = 0.0
                        continue
                    if link is None:
                        link = self.connect()
                        await link.open()
                    if config.handshake:
                        flags = await link.read_flags()
                        if last is not None and not self.halt.is_set():
                            answer = await self.sink.edges(config.id, last, flags)
                            if answer is not None:
                                await link.write_flags(answer)
                        last = flags
                    if self.idle.is_set() and time.monotonic() >= monitor_due:
                        monitor_due = time.monotonic() + config.monitor_period
                        await self._monitor(link)
                except (LinkError, OSError) as exc:
                    self._failed(str(exc) or type(exc).__name__)
                except Exception as exc:  # a bug must not end the watch (nor reach the event loop)
                    log.exception("loop %s: watch failed", config.id)
                    self._failed(f"{type(exc).__name__}: {exc}")
                else:
                    if self.failing:
                        self.failing = False
                        self.sink.link_back(config.id)
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

    async def _monitor(self, link: Link) -> None:
        """Read the idle loop's state and PV and report them (not if a session started meanwhile)."""
        state = await link.read_state()
        pv = await link.read_pv()
        self.counted()
        if self.idle.is_set():
            self.sink.reading(self.config.id, Reading(state, pv, time.time()))

    def _failed(self, error: str) -> None:
        self.failing = True
        self.sink.link_failed(self.config.id, error)
