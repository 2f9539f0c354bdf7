"""Benchmark: is ``ite`` (the experiment's estimate of the seconds left) honest over the batch?

Each process of the batch runs the experiment as ``autotuner bench`` does (100
samples per period of the 135° point, amp 1, the time limit 200 of those
periods; noise-free, or with white noise of ``noise`` × the clean run's PV
amplitude, seed 1) and the status is read after every sample. Once the run
has ended its true time left at each status is known: the end's time minus the
status's. Judged (:func:`judge`) over the statuses from half a period after
the relay started to half a period before the end (``T`` = 2π/ω135, the
process's own period, not the experiment's): before, nothing has been
measured; after, the stop depends on one switch's estimate, which no count
of periods can foresee.

``python -m autotuner.benchmarks.ite_bench [--noise 0.01] [--every 7] [--workers N] [--prior 0.5]`` prints the table;
``--field`` a row per field scenario (field_bench.py) instead, ``--sample 13`` every 13th process only, ``--prior``
the period the time limit implies as a share of the true one (a daemon's loop configures a time limit, not a period).
"""

from __future__ import annotations

import argparse
import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from autotuner.benchmarks.design_bench import default_batch, load_batch, pool_map
from autotuner.benchmarks.field_bench import SCENARIOS, Scenario, scenario_sim
from autotuner.engine.experiment.progress import LIMIT_SHARE
from autotuner.engine.experiment.relay import RelayConfig, Status
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.process import Process
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import EXPERIMENT_SAMPLES_PER_PERIOD, phase_frequency, run_experiment

# ite within this share of the true time left counts as honest (issue 28: ±30 %).
HONEST = 0.3
# A rise of ite between two statuses larger than this share of the earlier ite is one a user notices.
RISE_TOL = 0.02
# The statuses judged start this many periods after the relay's start and end this many before the run's end.
MARGIN_PERIODS = 0.5


@dataclass(frozen=True)
class IteRun:
    """One run's statuses: ``t`` and ``ite`` while running (s), the end's time ``end`` (s), the relay's start
    ``start`` (s), the process's period at 135° ``period`` (s), the run's ``periods`` and whether it tuned ``ok``."""

    id: str
    t: np.ndarray
    ite: np.ndarray
    end: float
    start: float
    period: float
    periods: float
    ok: bool


@dataclass(frozen=True)
class Honesty:
    """One run judged: ``ratios`` ite/true over the judged statuses, and the largest rise of ite between
    statuses as a share of the earlier ite (``rise``, 0 when it never rose; ``judged_rise``: between the
    judged statuses only)."""

    id: str
    ratios: np.ndarray
    rise: float
    judged_rise: float


def run_one(expr: str, ident: str, noise: float = 0.0, every: int = 1, prior: float = 1.0) -> IteRun:
    """Run the experiment on the process ``expr`` (named ``ident``) with noise of σ ``noise`` × |F(jω135)|·amp (the
    PV's oscillation at the point, as ``autotuner bench`` sets it), reading the status every ``every`` samples; the
    period the configuration implies is ``prior`` × the 135° period (:func:`_setting`)."""
    process = parse_process(expr)
    period, ts, config = _setting(process, prior)
    if noise <= 0.0:
        return statuses(PlantSim(process, ts), config, ident, period, every)
    std = noise * abs(complex(process.freqresp(2.0 * math.pi / period))) * config.amp  # (as autotuner bench's)
    return statuses(PlantSim(process, ts, noise_std=std, seed=1), config, ident, period, every)


def field_one(expr: str, ident: str, every: int = 1, scenarios: tuple[Scenario, ...] = SCENARIOS) -> list[IteRun | None]:
    """The field ``scenarios`` (every one of field_bench.SCENARIOS unless given) on the process ``expr`` (named
    ``ident``), statuses every ``every`` samples; None where a run did not tune."""
    process = parse_process(expr)
    period, ts, config = _setting(process)
    _, clean = run_experiment(PlantSim(process, ts), config, status_every=10**9)
    scale = abs(complex(process.freqresp(2.0 * math.pi / period)))  # |F(jω135)|·amp
    runs: list[IteRun | None] = []
    for scenario in scenarios:
        sim = scenario_sim(process, ts, period, scenario, scale, float(clean.t[-1]))
        run = statuses(sim, config, ident, period, every)
        runs.append(run if run.ok and len(run.t) > 2 else None)
    return runs


def _setting(process: Process, prior: float = 1.0) -> tuple[float, float, RelayConfig]:
    """The period at 135° (s), the sample time (s) and the experiment's settings of ``autotuner bench``, with the
    time limit that makes the period the configuration implies (progress.configured_period) ``prior`` times the
    135° one: 1 as ``autotuner bench`` sets it; a daemon's loop sets a time limit of its own (tests/test_handshake:
    the period it implies is half the plant's)."""
    w135 = phase_frequency(process, 135.0)
    assert w135 is not None
    period = 2.0 * math.pi / w135
    limit = prior * LIMIT_SHARE * period
    return period, period / EXPERIMENT_SAMPLES_PER_PERIOD, RelayConfig(amp=1.0, time_limit=limit)


def statuses(sim: PlantSim, config: RelayConfig, ident: str, period: float, every: int) -> IteRun:
    """The experiment with ``config`` on ``sim`` (named ``ident``, its 135° period ``period``, s), its status read
    every ``every`` samples."""
    read: list[tuple[float, Status]] = []
    start = sim.t
    ts = sim.ts
    experiment, trace = run_experiment(sim, config, on_status=lambda s: read.append((sim.t - ts, s)),
                                       status_every=every)
    # (The status is read after the sample at sim.t − ts: its time is that sample's.)
    running = [(t, s.ite) for t, s in read if s.code is None]
    result = experiment.result
    return IteRun(ident, np.array([t for t, _ in running]), np.array([i for _, i in running]),
                  float(trace.t[-1]), start + (config.noise_samples - 1) * ts, period,
                  result.periods if result else math.nan, experiment.code is not None and experiment.code == 0)


def judge(run: IteRun) -> Honesty:
    """The ratios ite/true time left of ``run``'s judged statuses and its largest rise."""
    true = run.end - run.t
    margin = MARGIN_PERIODS * run.period
    judged = (run.t >= run.start + margin) & (true >= margin)
    return Honesty(run.id, run.ite[judged] / true[judged], largest_rise(run.ite), largest_rise(run.ite[judged]))


def largest_rise(ite: np.ndarray) -> float:
    """The largest rise between consecutive values of ``ite`` (s) as a share of the earlier one (0: none)."""
    rises = np.diff(ite) / ite[:-1] if len(ite) > 1 else np.zeros(0)
    return float(max(rises.max(initial=0.0), 0.0))


@dataclass(frozen=True)
class Summary:
    """The batch judged: the share of statuses within ``HONEST``, of runs whose ite never rose beyond
    ``RISE_TOL`` (over all statuses, and over the judged ones), the median and p90 ratio ite/true (p10 too:
    ite low is the worse lie) and the runs."""

    within: float
    never_rising: float
    never_rising_judged: float
    median: float
    p10: float
    p90: float
    runs: int
    statuses: int


def summarise(judged: list[Honesty]) -> Summary:
    """The batch's figures from its ``judged`` runs."""
    ratios = np.concatenate([h.ratios for h in judged])
    return Summary(within=float(np.mean(np.abs(ratios - 1.0) <= HONEST)),
                   never_rising=float(np.mean([h.rise <= RISE_TOL for h in judged])),
                   never_rising_judged=float(np.mean([h.judged_rise <= RISE_TOL for h in judged])),
                   median=float(np.median(ratios)), p10=float(np.percentile(ratios, 10)),
                   p90=float(np.percentile(ratios, 90)), runs=len(judged), statuses=len(ratios))


def run_batch(noise: float, every: int, workers: int | None, sample: int = 1, prior: float = 1.0) -> list[IteRun]:
    """Every ``sample``-th process of the batch with ``noise``, statuses every ``every`` samples, on ``workers``
    processes, the configuration's period ``prior`` × the 135° one."""
    return pool_map(partial(_batch_one, noise=noise, every=every, prior=prior), load_batch(default_batch())[::sample],
                    workers)


def _batch_one(row: dict[str, str], noise: float, every: int, prior: float) -> IteRun:
    return run_one(row["expr"], row["id"], noise, every, prior)


def _field_one(row: dict[str, str], every: int) -> list[IteRun | None]:
    return field_one(row["expr"], row["id"], every)


def field_table(every: int, workers: int | None, sample: int) -> str:
    """The field scenarios on every ``sample``-th process of the batch: a markdown row per scenario."""
    rows = pool_map(partial(_field_one, every=every), load_batch(default_batch())[::sample], workers)
    lines = ["| scenario | runs | within ±30 % | never rising (judged) | ite/true p10 | median | p90 |",
             "|---|---|---|---|---|---|---|"]
    for k, scenario in enumerate(SCENARIOS):
        judged = [judge(r[k]) for r in rows if r[k] is not None]
        s = summarise([h for h in judged if len(h.ratios)])
        lines.append(f"| {scenario.name} | {s.runs} | {s.within:.0%} | {s.never_rising_judged:.0%} | {s.p10:.2f} "
                     f"| {s.median:.2f} | {s.p90:.2f} |")
    return "\n".join(lines)


def _at_least(low: float, kind: type) -> Callable[[str], Any]:
    """An argparse type: a ``kind`` number ≥ ``low`` (the option's unit), else a usage error naming it."""
    def parse(text: str) -> Any:
        value = kind(text)
        if not value >= low:
            raise argparse.ArgumentTypeError(f"must be at least {low}, got {text}")
        return value
    return parse


def main() -> None:
    """Print the table for the batch (``--noise``, ``--every``, ``--sample``, ``--workers``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--noise", type=_at_least(0.0, float), default=0.0,
                        help="σ of white measurement noise as a share of |F(jω135)|·amp (default 0)")
    parser.add_argument("--every", type=_at_least(1, int), default=7, help="a status every this many samples")
    parser.add_argument("--sample", type=_at_least(1, int), default=1, help="every this many-th process of the batch")
    parser.add_argument("--workers", type=_at_least(1, int), default=None,
                        help="worker processes (default: one per core)")
    parser.add_argument("--worst", type=int, default=0, help="also list this many least honest runs")
    parser.add_argument("--prior", type=_at_least(0.01, float), default=1.0,
                        help="the period the time limit implies as a share of the 135° one (default 1)")
    parser.add_argument("--field", action="store_true", help="the field scenarios instead (no --noise)")
    a = parser.parse_args()
    if a.field:
        print(field_table(a.every, a.workers, a.sample))
        return
    runs = run_batch(a.noise, a.every, a.workers, a.sample, a.prior)
    judged = [judge(r) for r in runs]
    s = summarise(judged)
    print("| runs | statuses | within ±30 % | never rising (≤ 2 %): all / judged | ite/true p10 | median | p90 |")
    print("|---|---|---|---|---|---|---|")
    print(f"| {s.runs} | {s.statuses} | {s.within:.0%} | {s.never_rising:.0%} / {s.never_rising_judged:.0%} "
          f"| {s.p10:.2f} | {s.median:.2f} | {s.p90:.2f} |")
    periods = [r.periods for r in runs if math.isfinite(r.periods)]
    print(f"\nperiods: median {statistics.median(periods):.2f}, max {max(periods):.2f}; "
          f"{sum(not r.ok for r in runs)} runs not ok")
    by_share = sorted(judged, key=lambda h: float(np.mean(np.abs(h.ratios - 1.0) <= HONEST)) if len(h.ratios) else 1)
    for h in by_share[:a.worst]:
        share = float(np.mean(np.abs(h.ratios - 1.0) <= HONEST)) if len(h.ratios) else math.nan
        lo, hi = (float(h.ratios.min()), float(h.ratios.max())) if len(h.ratios) else (math.nan, math.nan)
        print(f"{h.id}: within {share:.0%}, ratio {lo:.2f}–{hi:.2f}, largest rise {h.rise:.0%}")


if __name__ == "__main__":
    main()
