"""Worker processes for the CPU-bound work of a process that must keep time: the designs, the analyses.

A thread would hold the process's GIL while it computes, and the event loop
that samples would wait for it at every read and write (each takes the GIL
back after a system call: with 100 loops, thousands of times a second). So the
work runs in a :class:`WorkerPool` of spawned worker processes: a worker
inherits none of its parent's sockets or its event loop, and exits when the
process that started it is gone (killed by a signal, it never shuts its pool
down). A pool whose worker was killed runs that call in a thread instead and
starts new workers for the next. A worker never inherits the real-time
scheduling of the thread that starts it (SCHED_RESET_ON_FORK while it is
spawned): its start-up (the interpreter, numpy, scipy) must not compete with
that thread's samples; its ``setup`` sets the priority it is meant to run at.
"""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing
import os
import threading
import time
from collections.abc import Callable, Iterator
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
        fresh = self._pool is None
        await asyncio.gather(*(self._submit(_started) for _ in range(self.size)))
        if fresh:
            _threads_like_this()

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` in a worker (``fn`` and its arguments and result are pickled); in a thread if a worker
        was killed. Its CPU seconds count in :attr:`cpu`."""
        result, cpu = await self.timed(fn, *args)
        self.cpu += cpu
        return result

    async def timed(self, fn: Callable[..., T], *args: Any) -> tuple[T, float]:
        """``fn(*args)`` as :meth:`run`, and the CPU seconds it took (not counted in :attr:`cpu`)."""
        fresh = self._pool is None
        try:
            result = await self._submit(_timed, fn, *args)
        except BrokenProcessPool:
            self._pool = None
            return await asyncio.to_thread(_thread_timed, fn, *args)
        if fresh:
            _threads_like_this()
        return result

    def close(self) -> None:
        """Stop the workers (the next call starts them again)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def pids(self) -> list[int]:
        """The workers running now."""
        return [] if self._pool is None else list(self._pool._processes)  # noqa: SLF001 - no public accessor

    def _submit(self, fn: Callable[..., T], *args: Any) -> asyncio.Future[T]:
        """``fn(*args)`` submitted to the workers; a submit may start a worker (in this thread), and that worker
        starts at an ordinary priority."""
        with _children_ordinary():
            return asyncio.get_running_loop().run_in_executor(self._executor(), fn, *args)

    def _executor(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(self.size, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=_worker_start, initargs=(os.getpid(), self.setup))
        return self._pool


@contextlib.contextmanager
def _children_ordinary() -> Iterator[None]:
    """Processes and threads this thread starts in the block start at an ordinary priority, whatever this thread's
    real-time policy (the kernel's SCHED_RESET_ON_FORK, for the block only)."""
    policy = _policy()
    if policy is None:
        yield
        return
    param = os.sched_getparam(0)
    os.sched_setscheduler(0, policy | os.SCHED_RESET_ON_FORK, param)
    try:
        yield
    finally:
        os.sched_setscheduler(0, policy, param)


def _threads_like_this() -> None:
    """Every thread of this process at this thread's real-time policy, if it has one: the pool's own threads,
    started at an ordinary priority with its workers, carry the results this thread's event loop waits for."""
    policy = _policy()
    if policy is None:
        return
    param = os.sched_getparam(0)
    for tid in os.listdir("/proc/self/task"):
        with contextlib.suppress(PermissionError, OSError):
            os.sched_setscheduler(int(tid), policy, param)


def _policy() -> int | None:
    """This thread's real-time scheduling policy; None: an ordinary one (or no such scheduling here)."""
    if not hasattr(os, "SCHED_RESET_ON_FORK"):
        return None
    policy = os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK
    return policy if policy in (os.SCHED_RR, os.SCHED_FIFO) else None


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
