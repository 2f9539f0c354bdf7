"""The design's worker processes: a session's robust design off the process that samples.

The design takes 0.1 s (PI) to 0.4 s (PID) of CPU. In a thread it would hold
the GIL most of that time, and many sessions ending together would stall
every other loop's sampling; so it runs in a :class:`WorkerPool` of cores − 1
spawned worker processes (one core left for the sampling), started on first
use. A worker gets a :class:`~autotuner.engine.simulated_tuning.DesignJob` —
the identification and the settings, under 1 KB — never the experiment or
its trace. The loops' health assessments run in the same workers
(:func:`pooled`): a few ms each, at most a few at a time, so a design waits
behind them for milliseconds at most.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any, TypeVar

from autotuner.engine.design.point_design import Design
from autotuner.engine.outcome import Code
from autotuner.engine.simulated_tuning import DesignJob
from autotuner.service.worker_pool import PARENT_CHECK, WorkerPool

__all__ = ["PARENT_CHECK", "Outcome", "close_design_pool", "design_cpu", "designed", "pooled", "worker_pids"]

T = TypeVar("T")

_pool = WorkerPool(max(1, (os.cpu_count() or 2) - 1))

#: A design's outcome: the code, the message and the design (None: none).
Outcome = tuple[Code, str, Design | None]


async def designed(job: DesignJob) -> Outcome:
    """``job`` run in a worker process (in a thread if no design is needed, or if a worker was killed)."""
    if job.identification is None:  # nothing identified, nothing to design: no worker needed
        return job.run()
    return await _pool.run(DesignJob.run, job)


async def pooled(fn: Callable[..., T], *args: Any) -> tuple[T, float]:
    """``fn(*args)`` in the design's workers, and its CPU seconds (not counted as the design's): the daemon's
    other work that must stay off the process that samples and off the API's event loop (a loop's health
    assessment, a few ms). ``fn`` is a module-level function; it and ``args`` are pickled."""
    return await _pool.timed(fn, *args)


def close_design_pool() -> None:
    """Stop the design's worker processes (a daemon that stops; the next design starts them again)."""
    _pool.close()


def design_cpu() -> float:
    """CPU seconds the design's worker processes have spent in this process's sessions so far."""
    return _pool.cpu


def worker_pids() -> list[int]:
    """The design workers running now (for tests that check they end with the daemon)."""
    return _pool.pids()
