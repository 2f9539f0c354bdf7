"""Benchmark: the experiment and the design on every process of the batch, against the usual relay tuners.

For each process of the Åström–Hägglund batch (``amigo-batch.csv``) it runs,
in simulation with 100 samples per period of the 135° point:

* the relay + adaptive phase filter experiment, noise-free and with white
  measurement noise of 1 % of the PV oscillation amplitude, and the robust
  PI and PID designs from the identified point;
* (a) an ideal relay with the describing function and Ziegler–Nichols PI/PID;
* (b) the same relay data with the Åström–Hägglund rule (methods.md §4.4,
  ``r_b = 0.5``, ``φ_b = 45°``; its PI is the same ``K, Ti`` without ``Td``);
* (c) MIGO with full knowledge of the process: the largest integral gain at
  the same Ms, the limit any tuning is compared with.

Every controller is judged on the exact process: Ms (``inf`` when the loop is
unstable) and ``ki`` relative to MIGO.
"""

from __future__ import annotations

import csv
import math
import os
import statistics
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import TypeVar

import numpy as np

from autotuner.benchmarks.cpu import CpuCost, cpu_table, cpu_times
from autotuner.engine.design.closed_loop import check_gains
from autotuner.engine.design.point_design import DEFAULT_ND, TD_RATIOS, design, fit_model
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.control.gains import Gains
from autotuner.engine.design.process_data import exact_point
from autotuner.engine.plant.process import Process
from autotuner.engine.experiment.relay import RelayConfig
from autotuner.engine.design.robustness import Plant, log_grid, migo
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import EXPERIMENT_SAMPLES_PER_PERIOD, phase_frequency, tune

T = TypeVar("T")

NOISE_FRACTION = 0.01
AH_RADIUS = 0.5
AH_PHASE = math.radians(45.0)


def default_batch() -> Path:
    """The batch shipped with the package (a copy of shared/bench/amigo-batch.csv)."""
    return Path(str(resources.files("autotuner.benchmarks") / "data" / "amigo-batch.csv"))


def load_batch(path: Path) -> list[dict[str, str]]:
    """Rows of the batch file (columns: id, family, params, expr, ...)."""
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@dataclass(frozen=True)
class Row:
    """One process of the benchmark; Ms is inf for an unstable loop, ratios are ki/ki_MIGO."""

    id: str
    omega: float
    point_error: float
    phase_error: float
    periods: float
    pi_ms: float
    pi_ratio: float
    pid_ms: float
    pid_ratio: float
    noisy_error: float
    noisy_periods: float
    noisy_pi_ms: float
    noisy_pi_ratio: float
    zn_pi_ms: float
    zn_pid_ms: float
    ah_pi_ms: float
    ah_pid_ms: float
    migo_pid_over_pi: float
    cpu: CpuCost | None = field(default=None, repr=False, compare=False)  # the clean PI run's calls
    noisy_cpu: CpuCost | None = field(default=None, repr=False, compare=False)


def ideal_relay(process: Process, ts: float, amp: float, periods: int = 8) -> tuple[float, float]:
    """Ideal (no hysteresis) symmetric relay: (period Tu in s, PV amplitude) of the last period."""
    sim = PlantSim(process, ts)
    relay, rising, t, y = 1.0, [], [], []
    limit = 10000 * EXPERIMENT_SAMPLES_PER_PERIOD
    while len(rising) < periods + 1 and len(t) < limit:
        pv = sim.measure()
        t.append(sim.t)
        y.append(pv)
        new = 1.0 if pv < 0.0 else -1.0
        if new > relay:
            rising.append(len(t) - 1)
        relay = new
        sim.advance(amp * relay)
    if len(rising) < 2:
        return math.nan, math.nan
    a, b = rising[-2], rising[-1]
    last = np.asarray(y[a:b])
    return t[b] - t[a], 0.5 * float(last.max() - last.min())


def _judge(process: Process, gains: Gains, w: np.ndarray) -> float:
    return check_gains(process, gains, w).ms


def run_one(row: dict[str, str]) -> Row:
    """Benchmark one process of the batch."""
    process = parse_process(row["expr"])
    w135 = phase_frequency(process, 135.0)
    assert w135 is not None
    ts = 2.0 * math.pi / w135 / EXPERIMENT_SAMPLES_PER_PERIOD
    w = log_grid(w135)
    plant = Plant(process.freqresp, integrators=process.integrator_count)
    migo_pi = migo([plant], w135, 1.4)
    migo_pid = max((migo([plant], w135, 1.4, r, DEFAULT_ND) for r in TD_RATIOS), key=lambda m: m.ki)
    config = RelayConfig(amp=1.0, time_limit=200 * 2.0 * math.pi / w135)

    times = cpu_times()
    clean = {c: tune(PlantSim(process, ts), config, c, times=times if c == "PI" else None) for c in ("PI", "PID")}
    pi, pid = clean["PI"], clean["PID"]
    assert pi.ok and pid.ok, (row["id"], pi.message, pid.message)
    ident = pi.identification
    true = complex(process.freqresp(ident.point.omega))
    # The noise level: a share of the PV's oscillation at the 135° point, |F(jω135)|·amp (the field bench's). (It was
    # half the PV's range over the clean run's second half, 0.80–1.19 times this, median 1.02, while the clean runs
    # were long: a clean run that ends in its second period would set it from its start's transient.)
    amplitude = abs(complex(process.freqresp(w135))) * config.amp
    noisy_times = cpu_times()
    noisy = tune(PlantSim(process, ts, noise_std=NOISE_FRACTION * amplitude, seed=1), config, "PI",
                 times=noisy_times)
    if noisy.ok:
        n_ident = noisy.identification
        n_true = complex(process.freqresp(n_ident.point.omega))
        noisy_error = abs(n_ident.point.value - n_true) / abs(n_true)
        noisy_ms, noisy_ratio = _judge(process, noisy.design.gains, w), noisy.design.gains.ki / migo_pi.ki
        noisy_periods = n_ident.periods
    else:
        noisy_error = noisy_ms = noisy_periods = math.inf
        noisy_ratio = 0.0

    tu, a = ideal_relay(process, ts, 1.0)
    ku = 4.0 / (math.pi * a)
    zn_pi = Gains(k=0.45 * ku, ti=tu / 1.2)
    zn_pid = Gains(k=0.6 * ku, ti=tu / 2.0, td=tu / 8.0)
    ah_k = ku * AH_RADIUS * math.cos(AH_PHASE)
    ah_ti = tu / math.pi * (1.0 + math.sin(AH_PHASE)) / math.cos(AH_PHASE)
    ah_pi, ah_pid = Gains(k=ah_k, ti=ah_ti), Gains(k=ah_k, ti=ah_ti, td=ah_ti / 4.0)

    return Row(
        id=row["id"],
        omega=ident.point.omega,
        point_error=abs(ident.point.value - true) / abs(true),
        phase_error=ident.point.phase_deg + 135.0,
        periods=ident.periods,
        pi_ms=_judge(process, pi.design.gains, w),
        pi_ratio=pi.design.gains.ki / migo_pi.ki,
        pid_ms=_judge(process, pid.design.gains, w),
        pid_ratio=pid.design.gains.ki / migo_pi.ki,
        noisy_error=noisy_error,
        noisy_periods=noisy_periods,
        noisy_pi_ms=noisy_ms,
        noisy_pi_ratio=noisy_ratio,
        zn_pi_ms=_judge(process, zn_pi, w),
        zn_pid_ms=_judge(process, zn_pid, w),
        ah_pi_ms=_judge(process, ah_pi, w),
        ah_pid_ms=_judge(process, ah_pid, w),
        migo_pid_over_pi=migo_pid.ki / migo_pi.ki,
        cpu=CpuCost.of(times),
        noisy_cpu=CpuCost.of(noisy_times),
    )


@dataclass(frozen=True)
class DesignRow:
    """The design rule alone, from the exact point and static gain of one process."""

    id: str
    fopdt_ms: float
    fopdt_ratio: float
    pi_ms: float
    pi_ratio: float
    pid_ms: float
    pid_over_pi: float


def design_one(row: dict[str, str]) -> DesignRow:
    """Design from the exact 135° point: FOPDT-only MIGO (the starting derivation) against the project's rule."""
    process = parse_process(row["expr"])
    point = exact_point(process, 135.0)
    assert point is not None
    static = process.static_gain()
    w = log_grid(point.omega)
    limit = migo([Plant(process.freqresp, integrators=process.integrator_count)], point.omega, 1.4)
    model = fit_model(point, static)
    start = migo([Plant(model.freqresp, integrators=model.integrator_count)], point.omega, 1.4)
    pi = design(point, static, "PI").gains
    pid = design(point, static, "PID").gains
    return DesignRow(
        id=row["id"],
        fopdt_ms=_judge(process, Gains(k=start.k, ti=start.ti), w),
        fopdt_ratio=start.ki / limit.ki,
        pi_ms=_judge(process, pi, w),
        pi_ratio=pi.ki / limit.ki,
        pid_ms=_judge(process, pid, w),
        pid_over_pi=pid.ki / pi.ki,
    )


def pool_map(work: Callable[[dict[str, str]], T], rows: list[dict[str, str]], workers: int | None = None) -> list[T]:
    """``work`` on every row in a pool of ``workers`` processes (default: all cores), results in row order."""
    with ProcessPoolExecutor(max_workers=workers or os.cpu_count()) as pool:
        return list(pool.map(work, rows, chunksize=1))


def run_batch(rows: list[dict[str, str]], workers: int | None = None, design_only: bool = False) -> list:
    """Benchmark every row (experiment and design, or with ``design_only`` the rule alone), on all cores."""
    return pool_map(design_one if design_only else run_one, rows, workers)


_COLUMNS = (
    ("id", "id", "{}"),
    ("ω̂ rad/s", "omega", "{:.4g}"),
    ("err %", "point_error", "pct"),
    ("Δφ °", "phase_error", "{:+.2f}"),
    ("periods", "periods", "{:.1f}"),
    ("PI Ms", "pi_ms", "ms"),
    ("PI ki/max", "pi_ratio", "{:.3f}"),
    ("PID Ms", "pid_ms", "ms"),
    ("PID ki/max", "pid_ratio", "{:.3f}"),
    ("noisy err %", "noisy_error", "pct"),
    ("noisy periods", "noisy_periods", "{:.1f}"),
    ("noisy PI Ms", "noisy_pi_ms", "ms"),
    ("noisy ki/max", "noisy_pi_ratio", "{:.3f}"),
    ("ZN PI Ms", "zn_pi_ms", "ms"),
    ("ZN PID Ms", "zn_pid_ms", "ms"),
    ("AH PI Ms", "ah_pi_ms", "ms"),
    ("AH PID Ms", "ah_pid_ms", "ms"),
    ("MIGO PID/PI", "migo_pid_over_pi", "{:.3f}"),
)


def _fmt(value: float | str, spec: str) -> str:
    if spec == "pct":
        return f"{100.0 * value:.3f}" if math.isfinite(value) else "fail"
    if spec == "ms":
        return f"{value:.3f}" if math.isfinite(value) else "unstable"
    return spec.format(value)


_DESIGN_COLUMNS = (
    ("id", "id", "{}"),
    ("FOPDT-only Ms", "fopdt_ms", "ms"),
    ("FOPDT-only ki/max", "fopdt_ratio", "{:.3f}"),
    ("PI Ms", "pi_ms", "ms"),
    ("PI ki/max", "pi_ratio", "{:.3f}"),
    ("PID Ms", "pid_ms", "ms"),
    ("PID ki / PI ki", "pid_over_pi", "{:.3f}"),
)


def cpu_summary(rows: list[Row]) -> str:
    """The experiment's CPU per period's analysis and per sample (markdown), clean and noisy (PI runs)."""
    return cpu_table({"noise-free": [r.cpu for r in rows if r.cpu is not None],
                      f"{100 * NOISE_FRACTION:g} % noise": [r.noisy_cpu for r in rows if r.noisy_cpu is not None]})


def format_table(rows: list) -> str:
    """The benchmark table (markdown) with a median and a worst line per column."""
    columns = _DESIGN_COLUMNS if rows and isinstance(rows[0], DesignRow) else _COLUMNS
    head = "| " + " | ".join(c[0] for c in columns) + " |"
    rule = "|" + "|".join("---" for _ in columns) + "|"
    lines = [head, rule]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(getattr(r, attr), spec) for _, attr, spec in columns) + " |")
    medians, worsts = ["**median**"], ["**worst**"]
    for _, attr, spec in columns[1:]:
        if attr == "omega":  # a frequency has no better or worse
            medians.append("")
            worsts.append("")
            continue
        low_is_worse = "ratio" in attr or "over" in attr
        values = [getattr(r, attr) for r in rows]
        finite = [v for v in values if math.isfinite(v)]
        med = statistics.median(finite) if finite else math.nan
        worst = min(values) if low_is_worse else max(values, key=abs)
        unstable = len(values) - len(finite)
        medians.append(_fmt(med, spec) + (f" ({unstable} unst.)" if unstable and spec == "ms" else ""))
        worsts.append(_fmt(worst, spec))
    lines.append("| " + " | ".join(medians) + " |")
    lines.append("| " + " | ".join(worsts) + " |")
    return "\n".join(lines)
