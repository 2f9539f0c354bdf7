"""What a session on a live loop records in the history before it writes, shared by the daemon and
``autotuner tune --config`` (docs/handback.md).

Before the session touches the loop: its saved state, the relay's MV levels and the range of every MV it may
write, durably (a session that cannot record them ends without touching the loop). Before an MV outside that
range: the widened range. Before a gains write: its *intent*. After the session: the gains the device holds,
read back, so that the history says whether the gains were applied. Each record is awaited for at most
the config's ``record_wait`` seconds; a record not in by then counts as not recorded (the write it guards does not
happen), and the history drops it (it carries that deadline): it is never recorded afterwards.

:class:`Tap` is the link the session writes through: it calls those records before the writes they guard.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Awaitable, Callable
from typing import Any

from drivers.link import Link, LinkError, LoopState, Sample

from autotuner.engine.control.gains import Gains
from autotuner.engine.result import TuneResult

# Largest number of points of a stored trace: a whole experiment at full resolution (the demo's take 300–1500
# samples; a 2-hour experiment at 1 s is 7200), thinned evenly past that.
TRACE_POINTS = 8000

#: Records ``History.<name>(*args)`` and waits for it (bounded): '' once recorded, else why not. Called with the
#: method's name, so that a session running in another process than the history can ask for it.
Durable = Callable[..., Awaitable[str]]

log = logging.getLogger("autotuner.service.session_record")


async def waited(record: asyncio.Future[Any], wait: float) -> str:
    """Wait up to ``wait`` s for a history write under way (it goes on after); '' once recorded, else why not."""
    try:
        await asyncio.wait_for(asyncio.shield(record), max(wait, 0.0))
    except asyncio.TimeoutError:
        return f"the history did not record it within {wait:g} s (still retried)"
    except Exception as exc:  # the history's error after its retries
        return f"the history could not record it ({type(exc).__name__}: {exc})"
    return ""


def mv_hull(*mvs: float) -> tuple[float, float]:
    """The smallest range (low, high), MV units, holding every one of ``mvs``."""
    return min(mvs), max(mvs)


class Tap:
    """A link that remembers the last PV read (``read_sample``: the session's) and MV written (for the live samples) and forwards everything.

    A gains write first awaits ``before_gains`` (the history's intent; a
    LinkError there means the gains are not written) and remembers the gains
    in ``intended``. Once ``mv_range`` is set (the session's MV range on
    record, MV units), an MV outside it first awaits ``before_mv(mv)``, which
    records the widened range durably (a LinkError there: not written): a
    restart after a crash then knows every MV the session may have left.
    """

    def __init__(self, link: Link, before_gains: Callable[[Gains], Awaitable[None]] | None = None,
                 before_mv: Callable[[float], Awaitable[None]] | None = None) -> None:
        self._link = link
        self.pv = math.nan
        self.mv = math.nan
        self.before_gains = before_gains
        self.intended: Gains | None = None
        self.before_mv = before_mv
        self.mv_range: tuple[float, float] | None = None

    @property
    def pv_age(self) -> float | None:
        return self._link.pv_age

    async def read_sample(self) -> Sample:
        sample = await self._link.read_sample()
        self.pv = sample.pv
        return sample

    async def write_mv(self, mv: float) -> None:
        r = self.mv_range
        if r is not None and self.before_mv is not None and not r[0] <= mv <= r[1]:
            await self.before_mv(mv)
        await self._link.write_mv(mv)
        self.mv = mv

    async def write_gains(self, gains: Gains) -> None:
        if self.before_gains is not None:
            await self.before_gains(gains)
        self.intended = gains
        await self._link.write_gains(gains)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._link, name)


def same_gains(a: Gains, b: Gains) -> bool:
    """``a`` and ``b`` equal within the resolution of the links (float32 on the wire)."""
    ja, jb = a.as_json(), b.as_json()
    return all((ja[k] is None) == (jb[k] is None) and (ja[k] is None or math.isclose(ja[k], jb[k], rel_tol=1e-6,
                                                                                        abs_tol=1e-12))
               for k in ja)


async def read_gains(link: Link) -> Gains | None:
    """The controller's gains read back, None if the read fails."""
    try:
        return (await link.read_state()).gains
    except LinkError:
        return None


class SessionRecord:
    """The durable records of session ``sid`` of loop ``loop_id``, asked by ``user``, through ``durable``.

    ``saved``, ``levels`` and ``mv_range``: what :meth:`on_saved` recorded (None / () / None before);
    ``tap``: the link of :meth:`link`.
    """

    def __init__(self, durable: Durable, sid: str, loop_id: str, user: str) -> None:
        self.durable, self.sid, self.loop_id, self.user = durable, sid, loop_id, user
        self.saved: LoopState | None = None
        self.levels: tuple[float, ...] = ()
        self.mv_range: tuple[float, float] | None = None
        self.tap: Tap | None = None

    def link(self, link: Link) -> Tap:
        """``link`` as the session writes through it: MVs outside the range and gains recorded first."""
        self.tap = Tap(link, self.intend, self.widen)
        return self.tap

    async def on_saved(self, saved: LoopState, relay_levels: tuple[float, ...]) -> str:
        """``tune_link``'s ``on_saved``: the saved state, the levels and their hull with the saved MV, durably;
        '' once recorded, else why not (the session then ends without touching the loop)."""
        hull = mv_hull(saved.mv, *relay_levels)  # a switch sample lies between the levels
        why = await self.durable("saved", self.sid, saved, relay_levels, hull)
        if why:
            log.error("loop %s: session %s ends without touching the loop: its saved state is not recorded (%s)",
                      self.loop_id, self.sid, why)
            return why
        self.saved, self.levels, self.mv_range = saved, relay_levels, hull
        if self.tap is not None:
            self.tap.mv_range = hull
        return ""

    async def widen(self, mv: float) -> None:
        """Before an MV outside the range on record: the widened range, durably; LinkError (not written) if not."""
        assert self.saved is not None and self.mv_range is not None
        hull = mv_hull(*self.mv_range, mv)
        why = await self.durable("saved", self.sid, self.saved, self.levels, hull)
        if why:
            raise LinkError(f"MV {mv:g} not written: the session's MV range must be recorded first; {why}")
        self.mv_range = hull
        if self.tap is not None:
            self.tap.mv_range = hull

    async def intend(self, gains: Gains) -> None:
        """Before the gains write: its intent, durably; LinkError (the gains are not written) if not."""
        why = await self.durable("intend", self.sid, self.user, gains)
        if why:
            raise LinkError(f"the intent to write them must be recorded first; {why}")

    @property
    def intended(self) -> Gains | None:
        """The gains a write was attempted with (None: none was)."""
        return None if self.tap is None else self.tap.intended

    async def gains_after(self, link: Link, result: TuneResult, apply: bool) -> Gains | None:
        """The controller's gains after the session, on the still open ``link``: read back; if that fails, what the
        session should have left — but None (unknown, the intent stays open) after a gains write."""
        if self.intended is not None:
            return await read_gains(link)
        if self.saved is None:
            return None
        try:
            return (await link.read_state()).gains
        except LinkError:
            return result.design.gains if result.ok and apply else self.saved.gains

    def applied_by(self, gains_after: Gains | None) -> str | None:
        """Who applied gains in the session: its user if the device holds the gains written, else None."""
        intended = self.intended
        applied = intended is not None and gains_after is not None and same_gains(gains_after, intended)
        return self.user if applied else None
