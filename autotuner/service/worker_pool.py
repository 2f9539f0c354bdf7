"""Worker processes for the CPU-bound work of a process that must keep time: the designs, the analyses.

A thread would hold the process's GIL while it computes, and the event loop
that samples would wait for it at every read and write (each takes the GIL
back after a system call: with 100 loops, thousands of times a second). So the
work runs in a :class:`WorkerPool` of spawned worker processes: a worker
inherits none of its parent's sockets or its event loop, and exits when the
process that started it is gone (killed by a signal, it never shuts its pool
down). A pool whose worker was killed runs that call in a thread instead and
starts new workers for the next.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

# How often a worker checks that the process that started it still lives, seconds.
PARENT_CHECK = 0.5

T = TypeVar("T")


class WorkerPool:
    """``size`` spawned worker processes, started on first use (or :meth:`start`); each runs ``setup`` (a
    module-level function: it is pickled) when it starts. ``cpu``: the CPU seconds the calls took in the workers.
    """

    def __init__(self, size: int, setup: Callable[[], None] | None = None) -> None:
        self.size = size
        self.setup = setup
        self.cpu = 0.0
        self._pool: ProcessPoolExecutor | None = None

    async def start(self) -> None:
        """Start the workers now and wait until each has started (a first call then waits for none)."""
        executor = self._executor()
        loop = asyncio.get_running_loop()
        await asyncio.gather(*(loop.run_in_executor(executor, _started) for _ in range(self.size)))

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` in a worker (``fn`` and its arguments and result are pickled); in a thread if a worker
        was killed. Its CPU seconds count in :attr:`cpu`."""
        result, cpu = await self.timed(fn, *args)
        self.cpu += cpu
        return result

    async def timed(self, fn: Callable[..., T], *args: Any) -> tuple[T, float]:
        """``fn(*args)`` as :meth:`run`, and the CPU seconds it took (not counted in :attr:`cpu`)."""
        try:
            return await asyncio.get_running_loop().run_in_executor(self._executor(), _timed, fn, *args)
        except BrokenProcessPool:
            self._pool = None
            return await asyncio.to_thread(_thread_timed, fn, *args)

    def close(self) -> None:
        """Stop the workers (the next call starts them again)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def pids(self) -> list[int]:
        """The workers running now."""
        return [] if self._pool is None else list(self._pool._processes)  # noqa: SLF001 - no public accessor

    def _executor(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(self.size, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=_worker_start, initargs=(os.getpid(), self.setup))
        return self._pool


def _started() -> bool:
    return True


def _timed(fn: Callable[..., T], *args: Any) -> tuple[T, float]:
    cpu0 = time.process_time()
    return fn(*args), time.process_time() - cpu0


def _thread_timed(fn: Callable[..., T], *args: Any) -> tuple[T, float]:
    cpu0 = time.thread_time()
    return fn(*args), time.thread_time() - cpu0


def _worker_start(parent: int, setup: Callable[[], None] | None) -> None:
    """In a worker: ``setup``, then exit once the process that started it is gone."""
    if setup is not None:
        setup()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_CHECK)
        os._exit(0)

    threading.Thread(target=watch, name="follow-parent", daemon=True).start()
