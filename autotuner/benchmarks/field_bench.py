"""Field benchmark: the experiment and the PI design on every process of the batch under field conditions.

``autotuner bench --field`` runs, for each process of the batch (in
simulation, 100 samples per period of the 135° point, relay amplitude 1,
PI at Ms 1.4), one clean experiment and then one per scenario of
:data:`SCENARIOS`: load steps at the process input of both signs and
0.1–0.3 × amp early (1.5 periods in), mid-experiment (3.5 periods in) and in
the last estimation period of the clean run (one period before its end), a
load drift, white measurement noise of 1–5 % of ``|F(jω135)|·amp``, a
quantised PV, a start while the PV is still settling from a load step, and
noise together with a load step. Time references are the period ``T135`` of
the exact 135° point and the clean run's length.

Every result is judged on the true process: tuned (``te`` false), Ms on the
true plant (Nyquist-checked), the integral gain over the MIGO limit at
Ms 1.4 (with full knowledge of the process), the experiment's periods and
the outcome code of the runs that did not tune. The peers of the plain bench
(ideal relay + describing function with Ziegler–Nichols and Åström–Hägglund
PI/PID) are run on the same processes in the same run (undisturbed: they have
no disturbance handling to compare).
"""

from __future__ import annotations

import math
import statistics
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from autotuner.benchmarks.cpu import CpuCost, cpu_table, cpu_times
from autotuner.benchmarks.design_bench import AH_PHASE, AH_RADIUS, ideal_relay, pool_map
from autotuner.engine.control.gains import Gains
from autotuner.engine.design.closed_loop import check_gains
from autotuner.engine.design.process_data import exact_point
from autotuner.engine.design.robustness import Plant, log_grid, migo
from autotuner.engine.experiment.relay import RelayConfig
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.process import Process
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.result import TuneResult
from autotuner.engine.simulated_tuning import EXPERIMENT_SAMPLES_PER_PERIOD, ramp_loads, result_of, run_experiment

MS_LIMIT = 1.6
TIME_LIMIT_PERIODS = 200


@dataclass(frozen=True)
class Scenario:
    """One field condition; times in periods of the 135° point (``late``: periods before the clean run's end).

    loads: (when, size × amp) load steps; ``when`` is a number of periods from
    the start, or "late" for one period before the end of the clean run.
    drift: load ramp, × amp per period. noise: σ as a fraction of
    ``|F(jω135)|·amp``. quantum: PV resolution, same unit. settling: the load
    step (× amp) that hit the plant half a period before the experiment starts.
    """

    name: str
    loads: tuple[tuple[float | str, float], ...] = ()
    drift: float = 0.0
    noise: float = 0.0
    quantum: float = 0.0
    settling: float = 0.0


SCENARIOS: tuple[Scenario, ...] = (
    Scenario("load +0.2 early", loads=((1.5, 0.2),)),
    Scenario("load −0.3 early", loads=((1.5, -0.3),)),
    Scenario("load +0.3 mid", loads=((3.5, 0.3),)),
    Scenario("load −0.1 mid", loads=((3.5, -0.1),)),
    Scenario("load +0.1 last period", loads=(("late", 0.1),)),
    Scenario("load −0.2 last period", loads=(("late", -0.2),)),
    Scenario("drift +0.3 per 10 periods", drift=0.03),
    Scenario("drift −0.3 per 10 periods", drift=-0.03),
    Scenario("noise 1 %", noise=0.01),
    Scenario("noise 3 %", noise=0.03),
    Scenario("noise 5 %", noise=0.05),
    Scenario("noise 2 % + load +0.15 mid", noise=0.02, loads=((3.5, 0.15),)),
    Scenario("quantised PV (2 %)", quantum=0.02),
    Scenario("non-steady start (load 0.2)", settling=0.2),
)


@dataclass(frozen=True)
class Run:
    """One run: ``ms`` inf when not tuned or unstable on the true plant; ``code`` the outcome code."""

    code: int
    tuned: bool
    ms: float
    ratio: float
    periods: float
    cpu: CpuCost | None = field(default=None, repr=False, compare=False)


@dataclass(frozen=True)
class FieldRow:
    """One process: the clean run, one run per scenario, and the peers' Ms on the true plant."""

    id: str
    clean: Run
    runs: tuple[Run, ...]
    peers: dict[str, float] = field(default_factory=dict)


def scenario_sim(process: Process, ts: float, period: float, scenario: Scenario, scale: float,
                 clean_end: float) -> PlantSim:
    """The simulated plant of ``scenario`` at TUNE: ``process`` sampled every ``ts`` s, its 135° period
    ``period`` (s), noise and quantum as shares of ``scale`` (PV units), a "late" load a period before
    ``clean_end`` (s, the clean run's end).

    Plant time 0 is TUNE, except with a settling start: the load step hits at 0
    and TUNE comes half a period later, the PV still moving (the plant is
    advanced to it here).
    """
    settle = 0.5 * period if scenario.settling else 0.0
    loads = [(0.0, scenario.settling)] if scenario.settling else []
    for when, size in scenario.loads:
        loads.append((settle + (clean_end - period if when == "late" else float(when) * period), size))
    loads += ramp_loads(scenario.drift / period, ts, TIME_LIMIT_PERIODS * period)
    sim = PlantSim(process, ts, noise_std=scenario.noise * scale, seed=1, quantum=scenario.quantum * scale,
                   loads=loads)
    for _ in range(int(round(settle / ts))):
        sim.advance(sim.mv0)
    return sim


def _run(process, ts: float, period: float, scenario: Scenario, scale: float, clean_end: float,
         migo_ki: float, w: np.ndarray) -> tuple[Run, TuneResult]:
    sim = scenario_sim(process, ts, period, scenario, scale, clean_end)
    config = RelayConfig(amp=1.0, time_limit=TIME_LIMIT_PERIODS * period)
    times = cpu_times()
    experiment, trace = run_experiment(sim, config, times=times)
    result = result_of(experiment, trace, "PI", 1.4)
    if not result.ok:
        return Run(int(result.code), False, math.inf, 0.0, math.inf, CpuCost.of(times)), result
    gains = result.design.gains
    return Run(int(result.code), True, check_gains(process, gains, w).ms, gains.ki / migo_ki,
               result.identification.periods, CpuCost.of(times)), result


def field_one(row: dict[str, str]) -> FieldRow:
    """All scenarios on one process of the batch."""
    process = parse_process(row["expr"])
    point = exact_point(process, 135.0)
    assert point is not None
    period = 2.0 * math.pi / point.omega
    ts = period / EXPERIMENT_SAMPLES_PER_PERIOD
    w = log_grid(point.omega)
    limit = migo([Plant(process.freqresp, integrators=process.integrator_count)], point.omega, 1.4)
    scale = point.gain * 1.0  # |F(jω135)|·amp
    clean, clean_result = _run(process, ts, period, Scenario("clean"), scale, 0.0, limit.ki, w)
    clean_end = clean_result.trace.t[-1] if len(clean_result.trace.t) else 10.0 * period
    runs = tuple(_run(process, ts, period, s, scale, clean_end, limit.ki, w)[0] for s in SCENARIOS)

    tu, a = ideal_relay(process, ts, 1.0)
    ku = 4.0 / (math.pi * a)
    ah_k = ku * AH_RADIUS * math.cos(AH_PHASE)
    ah_ti = tu / math.pi * (1.0 + math.sin(AH_PHASE)) / math.cos(AH_PHASE)
    peers = {
        "ZN PI": Gains(k=0.45 * ku, ti=tu / 1.2),
        "ZN PID": Gains(k=0.6 * ku, ti=tu / 2.0, td=tu / 8.0),
        "AH PI": Gains(k=ah_k, ti=ah_ti),
        "AH PID": Gains(k=ah_k, ti=ah_ti, td=ah_ti / 4.0),
    }
    return FieldRow(row["id"], clean, runs, {name: check_gains(process, g, w).ms for name, g in peers.items()})


def run_field(rows: list[dict[str, str]], workers: int | None = None) -> list[FieldRow]:
    """The field benchmark on every row, in the plain bench's worker pool."""
    return pool_map(field_one, rows, workers)


# Unstable processes with dead time up to half the unstable time constant (T = 2 s), PI and PID.
UNSTABLE_CASES = tuple((f"exp(-{d:g}*s)/(2*s-1)", c) for d in (0.1, 0.2, 0.4, 0.5, 0.55, 0.8, 1.0)
                       for c in ("PI", "PID"))


@dataclass(frozen=True)
class UnstableRow:
    """One unstable process tuned end to end: outcome, the phase used, Ms on the model and the true plant."""

    plant: str
    controller: str
    code: int
    message: str
    phase_deg: float
    ms_target: float
    ms_model: float
    ms_true: float
    ki: float


def unstable_one(case: dict[str, str]) -> UnstableRow:
    """The relay experiment and the design on one unstable process (noise-free, amp 1)."""
    process = parse_process(case["expr"])
    ts = 2.0 * math.pi * process.delay / 0.5 / EXPERIMENT_SAMPLES_PER_PERIOD  # ~100 samples per period when ωD ≈ 0.5
    sim = PlantSim(process, ts)
    experiment, trace = run_experiment(sim, RelayConfig(amp=1.0, phase_deg=135.0, time_limit=4000 * ts))
    result = result_of(experiment, trace, case["controller"], 1.4)
    ident, des = result.identification, result.design
    ms_true = math.inf
    if des is not None:
        ms_true = check_gains(process, des.gains, log_grid(ident.point.omega)).ms
    return UnstableRow(case["expr"], case["controller"], int(result.code), result.message,
                       math.nan if ident is None else ident.point.phase_deg,
                       math.nan if des is None else des.ms_target, math.nan if des is None else des.model_ms,
                       ms_true, 0.0 if des is None else des.gains.ki)


def run_unstable(workers: int | None = None) -> list[UnstableRow]:
    """Every case of :data:`UNSTABLE_CASES`, in the plain bench's worker pool."""
    return pool_map(unstable_one, [{"expr": e, "controller": c} for e, c in UNSTABLE_CASES], workers)


def unstable_table(rows: list[UnstableRow]) -> str:
    """Markdown: one line per unstable case."""
    lines = ["| plant | D/T | controller | ite | phase of the point | Ms target | Ms on model | Ms on true plant | "
             "ki | message |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        d = parse_process(r.plant).delay / 2.0
        tuned = math.isfinite(r.ms_model)
        lines.append(f"| `{r.plant}` | {d:.3g} | {r.controller} | {r.code} | "
                     f"{r.phase_deg:.1f}° | {r.ms_target:.2f} | {r.ms_model:.3f} | {_ms_text(r.ms_true)} | "
                     f"{r.ki:.3g} | {r.message if r.code else 'ok'} |" if tuned else
                     f"| `{r.plant}` | {d:.3g} | {r.controller} | {r.code} | "
                     + (f"{r.phase_deg:.1f}°" if math.isfinite(r.phase_deg) else "—")
                     + f" | — | — | — | — | {r.message} |")
    return "\n".join(lines)


# -- tables -------------------------------------------------------------------


def _good(run: Run) -> bool:
    return run.tuned and run.ms <= MS_LIMIT


def _median(values: list[float]) -> float:
    return statistics.median(values) if values else math.nan


def _ms_text(x: float) -> str:
    return f"{x:.3f}" if math.isfinite(x) else "unstable"


def _codes(runs: list[Run]) -> str:
    count = Counter(r.code for r in runs if not r.tuned)
    return ", ".join(f"{n}× ite {code}" for code, n in sorted(count.items())) or "—"


def _summary_row(name: str, runs: list[Run]) -> str:
    tuned = [r for r in runs if r.tuned]
    good = sum(_good(r) for r in runs)
    ms = [r.ms for r in tuned]
    ratios = [r.ratio for r in tuned]
    periods = [r.periods for r in tuned]
    ok_high = sum(1 for r in tuned if r.code == 0 and r.ms > MS_LIMIT)
    return (f"| {name} | {len(runs)} | {len(tuned)} | {good} ({100.0 * good / len(runs):.1f} %) | "
            f"{_ms_text(_median(ms))} | {_ms_text(max(ms, default=math.inf))} | {_median(ratios):.3f} | "
            f"{min(ratios, default=math.nan):.3f} | {_median(periods):.1f} | {max(periods, default=math.nan):.1f} | "
            f"{ok_high} | {_codes(runs)} |")


SUMMARY_HEAD = ("| scenario | runs | tuned | tuned, Ms ≤ 1.6 | median Ms | worst Ms | median ki/MIGO | worst ki/MIGO | "
                "median periods | worst periods | \"ok\" with Ms > 1.6 | not tuned |\n"
                "|---|---|---|---|---|---|---|---|---|---|---|---|")


def summary(rows: list[FieldRow]) -> tuple[str, str]:
    """(table with one line per scenario, the summary line) over all processes."""
    lines = [SUMMARY_HEAD, _summary_row("clean (reference)", [r.clean for r in rows])]
    for i, scenario in enumerate(SCENARIOS):
        lines.append(_summary_row(scenario.name, [r.runs[i] for r in rows]))
    field_runs = [run for r in rows for run in r.runs]
    tuned = [run for run in field_runs if run.tuned]
    good = sum(_good(run) for run in field_runs)
    ratios = [run.ratio for run in tuned]
    ok_high = sum(1 for run in tuned if run.code == 0 and run.ms > MS_LIMIT)
    line = (f"field scenarios: {good} of {len(field_runs)} runs tuned with Ms ≤ {MS_LIMIT:g} on the true plant "
            f"({100.0 * good / len(field_runs):.1f} %); {len(tuned)} tuned; median PI ki/MIGO {_median(ratios):.3f}, "
            f"worst {min(ratios, default=math.nan):.3f}; {ok_high} \"ok\" with Ms > {MS_LIMIT:g}")
    peer_lines = []
    for name in rows[0].peers if rows else ():
        values = [r.peers[name] for r in rows]
        finite = [v for v in values if math.isfinite(v)]
        peer_lines.append(f"{name}: {len(values) - len(finite)} of {len(values)} unstable, median Ms "
                          f"{_ms_text(_median(finite))} of the rest")
    lines.append("")
    lines.append("peers (ideal relay + describing function, undisturbed, same processes): " + "; ".join(peer_lines))
    return "\n".join(lines), line


def cpu_summary(rows: list[FieldRow]) -> str:
    """The experiment's CPU per period's analysis and per sample (markdown): the clean runs, the field runs."""
    return cpu_table({"clean (reference)": [r.clean.cpu for r in rows if r.clean.cpu is not None],
                      "field scenarios": [run.cpu for r in rows for run in r.runs if run.cpu is not None]})


def per_scenario_tables(rows: list[FieldRow]) -> str:
    """One table per scenario: per process tuned / Ms on the true plant / ki over MIGO / periods."""
    out = []
    for i, scenario in enumerate(SCENARIOS):
        out.append(f"### {scenario.name}\n\n| id | tuned | Ms | ki/MIGO | periods |\n|---|---|---|---|---|")
        for r in rows:
            run = r.runs[i]
            tuned = "yes" if run.tuned and run.code == 0 else (f"warning {run.code}" if run.tuned else
                                                               f"no (ite {run.code})")
            out.append(f"| {r.id} | {tuned} | {_ms_text(run.ms) if run.tuned else '—'} | "
                       f"{run.ratio:.3f} | {run.periods:.1f} |" if run.tuned else
                       f"| {r.id} | {tuned} | — | — | — |")
        out.append("")
    return "\n".join(out)
