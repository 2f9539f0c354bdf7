"""A sampler's analysis workers: where its sessions' periods are analysed, so that no session waits for one.

The workers (:class:`~autotuner.service.worker_pool.WorkerPool`) start in the
background when the sampler's first session starts — a sampler that never
tunes never starts them, and a daemon starts as fast as without them. Until
they are ready a period is analysed in a thread of the sampler, awaited (as
with ``samplers: 0``). They start at an ordinary priority (their start-up is
the interpreter, numpy and scipy, which must not compete with the samples),
then a sampler with real-time scheduling gives them real-time priority one
below its own: an analysis is part of the experiment's timing (a relay switch
waits for it), so an ordinary process must not delay it, and the sampler's
reads must still come first.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os

from autotuner.service import heap
from autotuner.service.link_session import Analyse, analysed
from autotuner.service.worker_pool import WorkerPool

log = logging.getLogger(__name__)

# Analysis worker processes per sampler, unless the environment says otherwise (docs/daemon.md, "A plant").
DEFAULT_WORKERS = 2
# The environment variable that sets them (0: none; every period then in a thread, awaited).
WORKERS_ENV = "AUTOTUNER_ANALYSIS_WORKERS"


def worker_count() -> int:
    """The analysis workers per sampler: :data:`WORKERS_ENV` when it is a count, else :data:`DEFAULT_WORKERS`."""
    value = os.environ.get(WORKERS_ENV, "")
    return int(value) if value.isdigit() else DEFAULT_WORKERS


class AnalysisWorkers:
    """``size`` worker processes, started by :meth:`want`; ``priority``: the real-time priority (SCHED_RR, 1–99)
    they run at once started, None: an ordinary one."""

    def __init__(self, size: int, priority: int | None) -> None:
        self.pool = WorkerPool(size, functools.partial(_worker_setup, priority))
        self._ready = False
        self._starting: asyncio.Task[None] | None = None

    def want(self) -> None:
        """Start the workers in the background, if not yet started."""
        if self._starting is None:
            self._starting = asyncio.create_task(self._start())

    def analyse(self) -> Analyse | None:
        """How a period is analysed now: in the workers, or None (in a thread, awaited) until they are ready."""
        return functools.partial(self.pool.run, analysed) if self._ready else None

    def close(self) -> None:
        """Stop the workers."""
        if self._starting is not None:
            self._starting.cancel()
        self.pool.close()

    async def _start(self) -> None:
        try:
            await self.pool.start()
        except Exception as exc:  # noqa: BLE001 - the sessions then analyse in threads, as without workers
            log.error("the analysis workers did not start (%s): periods are analysed in threads", exc)
            return
        self._ready = True


def _worker_setup(priority: int | None) -> None:
    """In a worker, once started (the engine imported with this module): its start's objects out of the garbage
    collector's full walks (:func:`~autotuner.service.heap.settle`: an analysis is part of the experiment's
    timing), then real-time ``priority`` (SCHED_RR), or an ordinary priority when None or not permitted."""
    heap.settle()
    if priority is not None:
        with contextlib.suppress(PermissionError, OSError):
            os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(priority))
            return
    with contextlib.suppress(PermissionError, OSError):
        os.setpriority(os.PRIO_PROCESS, 0, 0)
