"""This daemon's place in a fleet sharing one PostgreSQL: the loops whose leases it holds, renewed in rounds.

Every ``renew`` seconds (in a thread: the database is never waited on by the
event loop) a round heartbeats this daemon, renews the leases it holds (those
it lost are given up at once), and evens the loops out: a daemon that holds
fewer than its share — the loops over the daemons alive and not draining,
rounded up — takes free leases (never held, released, or expired: their
owner died); one that holds more than its share releases idle loops (so
each settles at its share or one below; a draining daemon's share is none). Each lease
held is valid on this machine until the round's start plus the lease time
less :data:`MARGIN`: a daemon frozen past it (SIGSTOP, a stalled machine)
writes nothing more to the loop before it has renewed, and by then the lease
may be another's.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from autotuner.service.leases import Leases, Member, Owner

# A lease is held on this machine until this long before it expires in the database, seconds (the round trip of
# the renewal and the clocks' drift over a lease time stay well below it).
MARGIN = 1.0
log = logging.getLogger("autotuner.service.daemon")


@dataclass(frozen=True)
class Round:
    """What a round changed: the loops gained (loop → epoch), lost (taken over by another daemon) and released
    (given to the others to even the loops out, or drained), and until when (monotonic) the leases held are valid
    here."""

    gained: dict[str, int]
    lost: set[str]
    released: set[str]
    valid_until: float


class Fleet:
    """The leases of ``loops`` (ids) through ``leases``, renewed every ``renew`` seconds (``draining``: serving
    none). ``idle(loop)`` tells which loops may be released (the loop manager sets it: no session, no pending
    restore)."""

    def __init__(self, leases: Leases, loops: list[str], renew: float, draining: bool = False) -> None:
        self.leases, self.loops, self.renew, self.draining = leases, loops, renew, draining
        self.idle: Callable[[str], bool] = lambda loop_id: True
        self.held: dict[str, int] = {}
        self.valid_until = -math.inf
        self.members: list[Member] = []
        self.owners: dict[str, Owner] = {}

    @property
    def name(self) -> str:
        """This daemon's name in the fleet."""
        return self.leases.name

    def valid(self, loop_id: str) -> bool:
        """This daemon holds the loop's lease and it is valid now (on this machine's monotonic clock)."""
        return loop_id in self.held and time.monotonic() < self.valid_until

    def share(self) -> int:
        """The loops this daemon should hold: an even share among the daemons alive and not draining."""
        serving = sum(not m.draining for m in self.members)
        return 0 if self.draining or serving == 0 else math.ceil(len(self.loops) / serving)

    async def round(self) -> Round:
        """One round (see the module); what changed."""
        start = time.monotonic()
        self.members = await asyncio.to_thread(self.leases.heartbeat, self.draining)
        kept = await asyncio.to_thread(self.leases.renew, self.held)
        lost = set(self.held) - set(kept)
        for loop_id in lost:
            log.error("loop %s: its lease (epoch %d) was taken over by another daemon: this daemon no longer "
                      "writes to it", loop_id, self.held[loop_id])
        self.held = kept
        share = self.share()
        gained: dict[str, int] = {}
        if len(kept) < share:
            free = [loop for loop in self.loops if loop not in kept]
            gained = await asyncio.to_thread(self.leases.acquire, free, share - len(kept))
            self.held.update(gained)
        surplus = len(self.held) - share
        release: dict[str, int] = {}
        if surplus > 0:
            idle = {loop: epoch for loop, epoch in self.held.items() if self.idle(loop)}
            release = dict(list(idle.items())[:surplus])
            await asyncio.to_thread(self.leases.release, release)
            for loop_id in release:
                del self.held[loop_id]
        self.valid_until = start + self.leases.ttl - MARGIN
        self.owners = await asyncio.to_thread(self.leases.owners)
        return Round(gained, lost, set(release), self.valid_until)

    def drop(self, loop_id: str) -> None:
        """The loop's lease is lost (its device holds a newer epoch): not held from now on, not renewed."""
        self.held.pop(loop_id, None)

    async def leave(self) -> None:
        """Release every lease held (a daemon that stops after handing its loops back)."""
        held, self.held = self.held, {}
        if held:
            await asyncio.to_thread(self.leases.release, held)
