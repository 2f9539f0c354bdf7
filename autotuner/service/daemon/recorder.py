"""The history's own thread: every write of the daemon in order, off the event loop; bounded waits for them.

Two kinds of durable record. A record that must be in the history *before* a
write it guards — a session's saved state before the loop is touched, a gains
intent before the gains — is a :meth:`Recorder.guard`: it carries its caller's
deadline into the history's thread, and past it the history drops it rather
than write it late (:class:`~autotuner.service.history.Late`), so a record
its caller was told is not in never appears afterwards. Every other record
(a session's begin and end, an applied write, a restore) is retried until it
is written: :meth:`Recorder.durable` waits for it within a bound and lets it
go on.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

from autotuner.service.history import History, Late
from autotuner.service.session_record import waited

log = logging.getLogger("autotuner.service.daemon")

# What a session (in a sampler process, possibly) may ask the history to record before a write, by name.
SESSION_RECORDS = frozenset({"saved", "intend"})
# The longest an API call (apply; a read of the history) waits behind the history's thread, wall seconds, before
# it answers 503 history_unavailable: its guard's deadline, plus LATE_GRACE for a commit under way at the deadline.
HISTORY_WAIT = 3.0
# How long a guard's caller waits past the deadline for a try already under way then (SQLite's busy timeout is 1 s;
# a full disk fails at once), wall seconds. A try still under way after it and committed later is undone, logged.
LATE_GRACE = 2.0


@dataclass
class HistoryHealth:
    """Whether the history takes writes now: ``error`` is why not (its path, since when, the database's reason),
    None while they go through. Shared by the loops' status records."""

    error: str | None = None


class Recorder:
    """Runs ``history``'s methods in one thread of their own, in the order asked (a failing write is retried
    there); the event loop never waits on the database unless it chooses to, and then within a bound: ``wait``
    wall seconds for a session's record (the config's ``record_wait``).

    ``health`` follows :attr:`History.error`; ``on_health`` (set by the loop
    manager) is called on the event loop when it changes.
    """

    def __init__(self, history: History, wait: float) -> None:
        self.history = history
        self.wait = wait  # how long a session's record is waited for, wall seconds (the config's record_wait)
        self.health = HistoryHealth()
        self.on_health: Callable[[], None] | None = None
        self._thread = ThreadPoolExecutor(1, thread_name_prefix="history")
        self._writes: set[asyncio.Future[Any]] = set()
        self._events: asyncio.AbstractEventLoop | None = None
        history.on_error = self._error

    def _error(self, error: str | None) -> None:
        """The history's outage began (``error``) or ended (None); called in its thread."""
        if self._events is not None:
            self._events.call_soon_threadsafe(self._health, error)

    def _health(self, error: str | None) -> None:
        self.health.error = error
        if self.on_health is not None:
            self.on_health()

    def record(self, method: Callable[..., Any], *args: Any, **kwargs: Any) -> asyncio.Future[Any]:
        """Run ``method(*args, **kwargs)`` in the history's thread, after the writes before it; its future.

        A write that fails after the history's own retries is logged here; the
        caller may await the future (bounded: :meth:`durable`) or not.
        """
        self._events = asyncio.get_running_loop()
        future = self._events.run_in_executor(self._thread, functools.partial(method, *args, **kwargs))
        self._writes.add(future)
        future.add_done_callback(self._done)
        return future

    def _done(self, future: asyncio.Future[Any]) -> None:
        self._writes.discard(future)
        if not future.cancelled() and future.exception() is not None and not isinstance(future.exception(), Late):
            log.error("history: a write failed for good (%s: %s)", type(future.exception()).__name__,
                      future.exception())

    async def durable(self, method: Callable[..., Any], *args: Any, wait: float | None = None) -> str:
        """Record ``method(*args)`` and wait up to ``wait`` s (None: :attr:`wait`); '' once recorded, else why not
        (it goes on)."""
        return await waited(self.record(method, *args), self.wait if wait is None else wait)

    async def read(self, method: Callable[..., Any], *args: Any, wait: float) -> Any:
        """``method(*args)`` read in the history's thread, after the writes before it; TimeoutError after ``wait``
        s (a write ahead of it is being retried: the history is down, :attr:`health` says why)."""
        return await asyncio.wait_for(asyncio.shield(self.record(method, *args)), max(wait, 0.0))

    async def guard(self, method: Callable[..., Any], *args: Any, wait: float,
                    undo: Callable[[], Any] | None = None) -> str:
        """Record ``method(*args, deadline=...)`` before a write it guards; '' once recorded, else why not — and
        then it is never recorded: the history drops it once ``wait`` s have passed.

        Waits for the history's answer up to :data:`LATE_GRACE` s past the
        deadline. A try still under way then that commits after all is logged
        and ``undo`` (a history method, run in its thread) takes it back.
        """
        deadline = time.monotonic() + wait
        future = self.record(method, *args, deadline=deadline)
        try:
            await asyncio.wait_for(asyncio.shield(future), wait + LATE_GRACE)
        except TimeoutError:
            future.add_done_callback(functools.partial(self._too_late, undo))
            return f"the history did not record it within {wait:g} s: {self.health.error or 'its thread is busy'}"
        except Late:
            return (f"the history could not record it within {wait:g} s ({self.health.error or 'writes ahead of it'}"
                    "); it never will")
        except Exception as exc:  # the history's error after its retries
            return f"the history could not record it ({type(exc).__name__}: {exc})"
        return ""

    def _too_late(self, undo: Callable[[], Any] | None, future: asyncio.Future[Any]) -> None:
        """A guard's record whose caller gave up: if it was committed after all, take it back."""
        if future.cancelled() or future.exception() is not None:
            return
        log.error("history: a record was committed after its caller had given up on it%s",
                  "; taking it back" if undo is not None else "")
        if undo is not None:
            self.record(undo)

    async def session_record(self, name: str, *args: Any) -> str:
        """:meth:`guard` of ``History.<name>`` for a session's records (:data:`SESSION_RECORDS` only), within
        :attr:`wait` s."""
        if name not in SESSION_RECORDS:
            raise ValueError(f"a session may not record {name!r}")
        method = getattr(self.history, name)
        undo = functools.partial(self.history.withdraw, args[0], args[2]) if name == "intend" else None
        return await self.guard(method, *args, wait=self.wait, undo=undo)

    @property
    def pending(self) -> int:
        """Writes asked for and not done yet (the history's queue)."""
        return len(self._writes)

    async def drain(self, timeout: float | None = None) -> None:
        """Wait until the writes asked for so far are done (at most ``timeout`` seconds)."""
        if self._writes:
            await asyncio.wait(set(self._writes), timeout=timeout)

    def close(self, wait: bool = False) -> None:
        """No more writes: the thread ends once the ones under way are done (``wait``: wait for that here); a
        write still failing then is given up at its next failure (logged), so the process can end."""
        if self._writes:
            log.warning("history: %d write(s) not done yet at the stop: %s", len(self._writes),
                        self.health.error or "under way")
        self.history.stop_retrying()
        self._thread.shutdown(wait=wait)
