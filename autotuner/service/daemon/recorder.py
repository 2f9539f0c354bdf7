"""The history's own thread: every write of the daemon in order, off the event loop; bounded waits for them."""

from __future__ import annotations

import asyncio
import functools
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from autotuner.service.history import History
from autotuner.service.session_record import waited

log = logging.getLogger("autotuner.service.daemon")

# What a session (in a sampler process, possibly) may ask the history to record durably, by name.
SESSION_RECORDS = frozenset({"saved", "intend"})


class Recorder:
    """Runs ``history``'s methods in one thread of their own, in the order asked (a busy database is retried
    there); the event loop never waits on the database unless it chooses to (bounded: :meth:`durable`)."""

    def __init__(self, history: History) -> None:
        self.history = history
        self._thread = ThreadPoolExecutor(1, thread_name_prefix="history")
        self._writes: set[asyncio.Future[Any]] = set()

    def record(self, method: Callable[..., Any], *args: Any) -> asyncio.Future[Any]:
        """Run ``method(*args)`` in the history's thread, after the writes before it; its future.

        A write that fails after the history's own retries is logged here; the
        caller may await the future (bounded: :meth:`durable`) or not.
        """
        future = asyncio.get_running_loop().run_in_executor(self._thread, functools.partial(method, *args))
        self._writes.add(future)
        future.add_done_callback(self._done)
        return future

    def _done(self, future: asyncio.Future[Any]) -> None:
        self._writes.discard(future)
        if not future.cancelled() and future.exception() is not None:
            log.error("history: a write failed for good (%s: %s)", type(future.exception()).__name__,
                      future.exception())

    async def durable(self, method: Callable[..., Any], *args: Any) -> str:
        """Record ``method(*args)`` and wait up to ``RECORD_WAIT`` s; '' once recorded, else why not."""
        return await waited(self.record(method, *args))

    async def session_record(self, name: str, *args: Any) -> str:
        """:meth:`durable` of ``History.<name>`` for a session's records (:data:`SESSION_RECORDS` only)."""
        if name not in SESSION_RECORDS:
            raise ValueError(f"a session may not record {name!r}")
        return await self.durable(getattr(self.history, name), *args)

    @property
    def pending(self) -> int:
        """Writes asked for and not done yet (the history's queue)."""
        return len(self._writes)

    async def drain(self, timeout: float | None = None) -> None:
        """Wait until the writes asked for so far are done (at most ``timeout`` seconds)."""
        if self._writes:
            await asyncio.wait(set(self._writes), timeout=timeout)

    def close(self) -> None:
        """No more writes: the thread ends once the ones under way are done."""
        self._thread.shutdown(wait=False)
