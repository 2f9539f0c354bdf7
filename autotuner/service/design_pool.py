"""The design's worker processes: a session's robust design off the process that samples.

The design takes 0.1 s (PI) to 0.4 s (PID) of CPU. In a thread it would hold
the GIL most of that time, and many sessions ending together would stall
every other loop's sampling; so it runs in a pool of spawned worker processes
(cores − 1 of them, one core left for the sampling), started on first use.
A worker gets a :class:`~autotuner.engine.simulated_tuning.DesignJob` — the
identification and the settings, under 1 KB — never the experiment or its
trace. A worker exits when the process that started it is gone (killed by a
signal, it never shuts its pool down).
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

from autotuner.engine.design.point_design import Design
from autotuner.engine.outcome import Code
from autotuner.engine.simulated_tuning import DesignJob

# How often a design worker checks that the process that started it still lives, seconds.
PARENT_CHECK = 0.5
# Worker processes of the design, started on first use, and the CPU seconds they spent.
_pool: ProcessPoolExecutor | None = None
_design_cpu = 0.0

#: A design's outcome: the code, the message and the design (None: none).
Outcome = tuple[Code, str, Design | None]


async def designed(job: DesignJob) -> Outcome:
    """``job`` run in a worker process (in a thread if no design is needed, or if a worker was killed)."""
    global _pool, _design_cpu
    if job.identification is None:  # nothing identified, nothing to design: no worker needed
        return job.run()
    if _pool is None:
        # spawn: a worker inherits none of the daemon's sockets or its event loop; one core left for sampling.
        _pool = ProcessPoolExecutor(max(1, (os.cpu_count() or 2) - 1), mp_context=multiprocessing.get_context("spawn"),
                                    initializer=_follow_parent, initargs=(os.getpid(),))
    try:
        outcome, cpu = await asyncio.get_running_loop().run_in_executor(_pool, _timed, job)
    except BrokenProcessPool:  # a worker was killed: the design still comes, from a thread
        _pool = None
        return await asyncio.to_thread(job.run)
    _design_cpu += cpu
    return outcome


def _timed(job: DesignJob) -> tuple[Outcome, float]:
    cpu0 = time.process_time()
    return job.run(), time.process_time() - cpu0


def _follow_parent(parent: int) -> None:
    """In a design worker: exit when the process that started it is gone."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_CHECK)
        os._exit(0)

    threading.Thread(target=watch, name="follow-parent", daemon=True).start()


def close_design_pool() -> None:
    """Stop the design's worker processes (a daemon that stops; the next design starts them again)."""
    global _pool
    if _pool is not None:
        _pool.shutdown(wait=True)
        _pool = None


def design_cpu() -> float:
    """CPU seconds the design's worker processes have spent in this process's sessions so far."""
    return _design_cpu


def worker_pids() -> list[int]:
    """The design workers running now (for tests that check they end with the daemon)."""
    return [] if _pool is None else list(_pool._processes)  # noqa: SLF001 - no public accessor
