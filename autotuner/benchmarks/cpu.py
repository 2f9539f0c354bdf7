"""The experiment's CPU time in the benchmarks: each period's analysis and each sample's step.

The daemon tunes many loops at once on a few cores, and a field session runs
each period's analysis (:meth:`RelayExperiment.analyse`: the estimates, the
stopping rule, the load fit) in a worker thread after its write: what a loop
costs is that analysis once per switch of the relay and :meth:`RelayExperiment.step`
once per sample. Both are timed as process CPU time (``time.process_time``)
around each call, in the benchmark's worker processes, and summarised as
median, 99th percentile and maximum in milliseconds.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from autotuner.engine.simulated_tuning import CallTimes


def cpu_times() -> CallTimes:
    """A record of call times read from this process's CPU clock."""
    return CallTimes(time.process_time)


@dataclass(frozen=True)
class CpuCost:
    """CPU milliseconds of each call of one or more runs (float32: a field bench holds a few million)."""

    analyse: np.ndarray
    step: np.ndarray

    @classmethod
    def of(cls, times: CallTimes) -> CpuCost:
        """The milliseconds of the calls ``times`` recorded."""
        return cls(np.asarray(times.analyse, dtype=np.float32) * 1e3, np.asarray(times.step, dtype=np.float32) * 1e3)

    @classmethod
    def joined(cls, costs: list[CpuCost]) -> CpuCost:
        """The calls of all ``costs`` together."""
        return cls(np.concatenate([c.analyse for c in costs] or [np.zeros(0, np.float32)]),
                   np.concatenate([c.step for c in costs] or [np.zeros(0, np.float32)]))


_HEAD = ("| | runs | analyses | analyse() CPU ms: median | p99 | max | steps | step() CPU ms: median | p99 | max |\n"
         "|---|---|---|---|---|---|---|---|---|---|")


def _figures(ms: np.ndarray) -> str:
    if not len(ms):
        return "— | — | —"
    return f"{np.median(ms):.3f} | {np.percentile(ms, 99):.2f} | {np.max(ms):.2f}"


def cpu_row(name: str, costs: list[CpuCost]) -> str:
    """One markdown row: the runs of ``costs``, their analyses' and their steps' CPU milliseconds."""
    total = CpuCost.joined(costs)
    return (f"| {name} | {len(costs)} | {len(total.analyse)} | {_figures(total.analyse)} | {len(total.step)} | "
            f"{_figures(total.step)} |")


def cpu_table(rows: dict[str, list[CpuCost]]) -> str:
    """A markdown table with one row per named group of runs."""
    return "\n".join([_HEAD] + [cpu_row(name, costs) for name, costs in rows.items()])
