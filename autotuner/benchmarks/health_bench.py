"""Loop-health benchmark (``autotuner bench --health``): a labelled set of simulated loops, each assessed, and
per flag the detection rate and the false-alarm rate.

Every loop is a :class:`drivers.simplc.SimulatedPlc` (the process under its PID unit, with faults) run in
closed loop faster than real time for 3600 samples of Tu/20 (180 ultimate periods), then assessed over the
whole record with its true model (as the last tuning would have identified it), its MV limits 0–100 and PV
range 0–100. Three processes: a stable lag with dead time, an integrating one and a lag-dominant one. Healthy
loops are PI designed at Ms 1.4 (what the tuner would give) under measurement noise (σ 0.05 % of the PV span)
and, in turn, random set-point steps, a stochastic load, random load steps and a heavier stochastic load. Each
fault comes in three severities (mild, moderate, severe) with the disturbances it needs to show. Seeds vary the
noise and the random events; one seed per (scenario, severity, process, repetition).
"""

from __future__ import annotations

import math
import os
from collections import defaultdict
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.optimize

from autotuner.engine.control.gains import Gains
from autotuner.engine.design.point_design import design
from autotuner.engine.design.process_data import exact_point
from autotuner.engine.health.assessment import assess
from autotuner.engine.health.record import LoopRecord
from autotuner.engine.health.scales import LoopLimits, ultimate_period
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.faults import Faults
from autotuner.engine.plant.process import Process
from drivers.link import Mode
from drivers.sim_record import record_plc
from drivers.simplc import SimulatedPlc

PROCESSES = (
    ("stable", "1.5*exp(-0.7*s)/(4*s+1)^2"),
    ("integrating", "0.2*exp(-1*s)/(s*(2*s+1))"),
    ("lag-dominant", "2*exp(-0.5*s)/((20*s+1)*(2*s+1))"),
)
SAMPLES = 3600
SAMPLES_PER_TU = 20
NOISE = 0.05  # PV units: 0.05 % of the PV span
SEVERITIES = ("mild", "moderate", "severe")
LIMITS = LoopLimits(mv=(0.0, 100.0), pv=(0.0, 100.0))
EVENT_SPACING = 30.0  # ultimate periods between random set-point or load steps, on average


@dataclass(frozen=True)
class Loop:
    """What to simulate on a process of ultimate period ``tu``: gain factors on the healthy PI (``k``, ``ti``)
    and its set-point weight (``b``, None: the designed one), or a PI at a gain margin (``gain_margin``), faults, PV noise, random set-point and load steps (sizes, PV
    and MV units), a constant load (MV units), and the share of the record in manual at its end."""

    k: float = 1.0
    ti: float = 1.0
    b: float | None = None
    gain_margin: float | None = None
    faults: Faults = Faults()
    noise: float = NOISE
    sp_steps: float = 0.0
    load_steps: float = 0.0
    offset: float = 0.0
    manual: float = 0.0


@dataclass(frozen=True)
class Scenario:
    """A labelled condition: ``expected`` the flags it should raise (empty: healthy), ``levels`` one
    :class:`Loop` maker per severity (a healthy scenario has one level, its name ``""``)."""

    name: str
    expected: frozenset[str]
    levels: tuple[tuple[str, Callable[[float], Loop]], ...]


def _stochastic(sigma: float) -> Callable[[float], Faults]:
    return lambda tu: Faults(load_std=sigma, load_tau=3.0 * tu)


HEALTHY = (
    Scenario("healthy: noise and set-point steps", frozenset(), (("", lambda tu: Loop(sp_steps=5.0)),)),
    Scenario("healthy: stochastic load", frozenset(), (("", lambda tu: Loop(faults=_stochastic(1.0)(tu))),)),
    Scenario("healthy: load steps", frozenset(), (("", lambda tu: Loop(load_steps=5.0)),)),
    Scenario("healthy: heavy load and set-point steps", frozenset(),
             (("", lambda tu: Loop(faults=_stochastic(2.0)(tu), sp_steps=5.0)),)),
)


def _levels(make: Callable[[float, float], Loop], values: tuple[float, float, float]) -> tuple[
        tuple[str, Callable[[float], Loop]], ...]:
    return tuple((name, (lambda tu, v=v: make(tu, v))) for name, v in zip(SEVERITIES, values))


FAULTS = (
    Scenario("sticky valve (S % of span, J = S/3)", frozenset({"oscillating", "stiction"}), _levels(
        lambda tu, s: Loop(faults=replace(_stochastic(0.2)(tu), stiction_s=s, stiction_j=s / 3.0)),
        (1.5, 3.0, 6.0))),
    Scenario("aggressive tuning (PI at gain margin)", frozenset({"oscillating"}), _levels(
        lambda tu, gm: Loop(gain_margin=gm, faults=_stochastic(0.5)(tu)), (1.5, 1.3, 1.1))),
    Scenario("external sinusoid (MV units, period 8 Tu)", frozenset({"oscillating"}), _levels(
        lambda tu, a: Loop(faults=Faults(sine_amplitude=a, sine_period=8.0 * tu)), (1.0, 2.0, 4.0))),
    Scenario("sluggish tuning (K ×, Ti ÷ the factor)", frozenset({"sluggish"}), _levels(
        lambda tu, f: Loop(k=f, ti=1.0 / f, load_steps=5.0, faults=_stochastic(0.3)(tu)), (0.4, 0.2, 0.1))),
    Scenario("frozen PV sensor (share of the window)", frozenset({"frozen_pv"}), _levels(
        lambda tu, share: Loop(faults=replace(_stochastic(0.5)(tu),
                                              frozen_at=(1.0 - share) * SAMPLES * tu / SAMPLES_PER_TU)),
        (0.3, 0.5, 0.8))),
    Scenario("in manual (share of the window)", frozenset({"manual"}), _levels(
        lambda tu, share: Loop(manual=share, faults=_stochastic(0.5)(tu)), (0.2, 0.5, 1.0))),
    Scenario("noisy PV (σ, % of the PV span)", frozenset({"noisy"}), _levels(
        lambda tu, sigma: Loop(noise=sigma), (1.5, 3.0, 6.0))),
    Scenario("saturating valve (MV needed, % of span)", frozenset({"saturated"}), _levels(
        lambda tu, need: Loop(offset=need - 50.0, faults=_stochastic(2.0)(tu)), (3.0, 1.0, -1.0))),
    Scenario("over-tuned for set-point steps (K ×, b = 1)", frozenset({"poor_tracking"}), _levels(
        lambda tu, f: Loop(k=f, b=1.0, sp_steps=5.0), (1.6, 2.0, 2.4))),
)
# Reported beside the targets: a valve deadband (Choudhury's J = 0); around a self-regulating process it
# makes no limit cycle of its own.
DEADBAND = Scenario("valve deadband (% of span)", frozenset({"stiction"}), _levels(
    lambda tu, d: Loop(faults=replace(_stochastic(0.2)(tu), deadband=d)), (1.5, 3.0, 6.0)))


@dataclass(frozen=True)
class Case:
    """One simulated loop of the benchmark."""

    scenario: str
    severity: str
    process: str
    expr: str
    seed: int
    expected: frozenset[str] = field(default_factory=frozenset)


@dataclass(frozen=True)
class Outcome:
    """A case and what the assessment found."""

    case: Case
    flags: frozenset[str]
    recommendation: str
    band: float | None
    ccf_zero_lag: float | None
    shape_index: float | None


def healthy_gains(process: Process) -> Gains:
    """The PI the tuner would design: from the exact 135° point at Ms 1.4, with its set-point weight."""
    point = exact_point(process, 135.0)
    if point is None:
        raise ValueError(f"{process}: no 135° point")
    return design(point, process.static_gain(), "PI", ms=1.4).gains


def margin_gains(process: Process, tu: float, gain_margin: float) -> Gains:
    """A PI with Ti = Tu/1.2 (Ziegler–Nichols') and the gain that leaves ``gain_margin``: at the first frequency
    where the loop's phase falls through −180° its gain is 1/``gain_margin`` (the continuous loop's margin: the
    sampled loop, with its hold's half-sample lag, has less; at 20 samples per Tu about 1.3 is the limit)."""
    ti = tu / 1.2

    def shape(w: np.ndarray | float) -> np.ndarray:  # the loop at k = 1
        return (1.0 + 1.0 / (1j * np.asarray(w) * ti)) * process.freqresp(w)

    w = np.geomspace(0.05, 2.0, 2000) * 2.0 * math.pi / tu
    phase = np.unwrap(np.angle(shape(w)))
    k = int(np.flatnonzero((phase[1:] <= -math.pi) & (phase[:-1] > -math.pi))[0]) + 1
    w180 = scipy.optimize.brentq(lambda x: float(np.angle(-shape(x))), w[k - 1], w[k])  # -180°: -shape at 0°
    return Gains(k=1.0 / (gain_margin * float(abs(shape(w180)))), ti=ti, b=1.0)


def _events(rng: np.random.Generator, duration: float, spacing: float, size: float) -> list[tuple[float, float]]:
    """Random steps: Poisson times ``spacing`` s apart on average, sizes ±(0.5–1)·``size``."""
    times = np.cumsum(rng.exponential(spacing, size=int(3 * duration / spacing) + 3))
    times = times[times < duration]
    return [(float(t), float(rng.choice((-1.0, 1.0)) * rng.uniform(0.5, 1.0) * size)) for t in times]


def _concat(a: LoopRecord, b: LoopRecord) -> LoopRecord:
    return LoopRecord.of(*(np.concatenate((getattr(a, n), getattr(b, n))) for n in ("t", "sp", "pv", "mv", "auto")))


def simulate(loop: Loop, process: Process, seed: int) -> LoopRecord:
    """The record of ``loop`` around ``process`` (3600 samples of Tu/20)."""
    tu = ultimate_period(process)
    assert tu is not None
    ts = tu / SAMPLES_PER_TU
    duration = SAMPLES * ts
    plc = SimulatedPlc(process, ts=ts, noise_std=loop.noise, seed=seed, faults=loop.faults)
    base = healthy_gains(process)
    plc.set_gains(margin_gains(process, tu, loop.gain_margin) if loop.gain_margin is not None
                  else Gains(k=base.k * loop.k, ti=base.ti * loop.ti, b=base.b if loop.b is None else loop.b))
    if loop.offset:
        plc.sim.step_load(-loop.offset)
    rng = np.random.default_rng([seed, 7])
    sp_steps, level = [], plc.sp
    for t, size in _events(rng, duration, EVENT_SPACING * tu, loop.sp_steps) if loop.sp_steps else []:
        level = min(max(level + size, 40.0), 60.0)
        sp_steps.append((t, level))
    load_steps = _events(rng, duration, EVENT_SPACING * tu, loop.load_steps) if loop.load_steps else []
    auto = int(round(SAMPLES * (1.0 - loop.manual)))
    if auto == SAMPLES:
        return record_plc(plc, SAMPLES, sp_steps, load_steps)
    if auto < 2:
        plc.mode = Mode.MAN
        return record_plc(plc, SAMPLES, sp_steps, load_steps)
    first = record_plc(plc, auto, sp_steps, load_steps)
    plc.mode = Mode.MAN
    later = [(t - auto * ts, v) for t, v in sp_steps if t >= auto * ts]
    return _concat(first, record_plc(plc, SAMPLES - auto, later))


def run_case(case: Case) -> Outcome:
    """Simulate and assess one case."""
    process = parse_process(case.expr)
    scenario = next(s for s in (*HEALTHY, *FAULTS, DEADBAND) if s.name == case.scenario)
    make = dict(scenario.levels)[case.severity]
    tu = ultimate_period(process)
    assert tu is not None
    result = assess(simulate(make(tu), process, case.seed), LIMITS, process, window=math.inf)
    ind = result.indices
    return Outcome(case, frozenset(f.name for f in result.flags), result.recommendation, ind.stiction_band,
                   ind.ccf_zero_lag, ind.shape_index)


def cases(repeats: int) -> list[Case]:
    """Every case: each scenario at each severity on each process, ``repeats`` times (healthy ones 3× as often,
    so the false-alarm rates rest on as many loops as a fault's detection rate)."""
    out = []
    for index, scenario in enumerate((*HEALTHY, *FAULTS, DEADBAND)):
        times = repeats * (3 if not scenario.expected else 1)
        for level, (severity, _) in enumerate(scenario.levels):
            for p, (name, expr) in enumerate(PROCESSES):
                for r in range(times):
                    seed = 100_000 * index + 10_000 * level + 1000 * p + r
                    out.append(Case(scenario.name, severity, name, expr, seed, scenario.expected))
    return out


def run(repeats: int = 5, workers: int | None = None) -> list[Outcome]:
    """Every case of :func:`cases` in a pool of ``workers`` processes (default: all cores)."""
    todo = cases(repeats)
    with ProcessPoolExecutor(max_workers=workers or os.cpu_count()) as pool:
        return list(pool.map(run_case, todo, chunksize=4))


def _pct(hits: int, total: int) -> str:
    return f"{100.0 * hits / total:.0f} % ({hits}/{total})" if total else "–"


def table(outcomes: list[Outcome]) -> str:
    """The benchmark's tables (markdown): detection per fault and severity, false alarms per flag, stiction
    against aggressive tuning, and the recommendations."""
    by: dict[tuple[str, str], list[Outcome]] = defaultdict(list)
    for o in outcomes:
        by[(o.case.scenario, o.case.severity)].append(o)
    lines = ["| fault | flag | mild | moderate | severe |", "|---|---|---|---|---|"]
    for scenario in (*FAULTS, DEADBAND):
        for flag in sorted(scenario.expected):
            cells = [_pct(sum(flag in o.flags for o in by[(scenario.name, sev)]), len(by[(scenario.name, sev)]))
                     for sev in SEVERITIES]
            lines.append(f"| {scenario.name} | `{flag}` | " + " | ".join(cells) + " |")
    healthy = [o for o in outcomes if not o.case.expected]
    lines += ["", "| flag | false alarms on healthy loops |", "|---|---|"]
    for flag in ("manual", "saturated", "oscillating", "stiction", "sluggish", "noisy", "frozen_pv", "poor_tracking"):
        lines.append(f"| `{flag}` | {_pct(sum(flag in o.flags for o in healthy), len(healthy))} |")
    lines.append(f"| any | {_pct(sum(bool(o.flags) for o in healthy), len(healthy))} |")
    lines += ["", _told_apart(outcomes), "", _band(outcomes), "", _stiction_tests(outcomes), "",
              _recommendations(outcomes)]
    return "\n".join(lines)


def _band(outcomes: list[Outcome]) -> str:
    """The band estimate against the valve's S, over the sticky loops flagged stiction."""
    sticky = FAULTS[0]
    values = dict(zip(SEVERITIES, (1.5, 3.0, 6.0)))  # S of each severity, % of a 100 span: MV units
    ratios = [o.band / values[o.case.severity] for o in outcomes
              if o.case.scenario == sticky.name and "stiction" in o.flags and o.band is not None]
    if not ratios:
        return "stiction band: no sticky loop flagged"
    return (f"stiction band estimate / S over the {len(ratios)} sticky loops flagged stiction: median "
            f"{float(np.median(ratios)):.2f}, from {min(ratios):.2f} to {max(ratios):.2f}")


def _told_apart(outcomes: list[Outcome]) -> str:
    """Among the sticky-valve and aggressive loops flagged oscillating: stiction flagged exactly for the
    sticky ones."""
    sticky, aggressive = FAULTS[0].name, FAULTS[1].name
    oscillating = [o for o in outcomes if o.case.scenario in (sticky, aggressive) and "oscillating" in o.flags]
    right = sum(("stiction" in o.flags) == (o.case.scenario == sticky) for o in oscillating)
    per = {name: [o for o in oscillating if o.case.scenario == name] for name in (sticky, aggressive)}
    return (f"stiction told apart from aggressive tuning in {_pct(right, len(oscillating))} of the oscillating "
            f"loops of both (sticky valve: {_pct(sum('stiction' in o.flags for o in per[sticky]), len(per[sticky]))}"
            f" flagged stiction; aggressive: {_pct(sum('stiction' in o.flags for o in per[aggressive]), len(per[aggressive]))}"
            " flagged stiction)")


def _span(values: list[float]) -> str:
    return f"{min(values):.2f}–{max(values):.2f}" if values else "–"


def _stiction_tests(outcomes: list[Outcome]) -> str:
    """The two stiction tests' values on the oscillating loops of the three oscillating faults, per process."""
    lines = ["| oscillating loops of | process | ρ0 (Horch) | SI (shape) |", "|---|---|---|---|"]
    for scenario in FAULTS[:3]:
        for name, _ in PROCESSES:
            group = [o for o in outcomes if o.case.scenario == scenario.name and o.case.process == name
                     and "oscillating" in o.flags]
            lines.append(f"| {scenario.name} | {name} | "
                         f"{_span([o.ccf_zero_lag for o in group if o.ccf_zero_lag is not None])} | "
                         f"{_span([o.shape_index for o in group if o.shape_index is not None])} |")
    return "\n".join(lines)


def _recommendations(outcomes: list[Outcome]) -> str:
    names = ("none", "retune", "check_valve", "check_sensor", "put_in_auto")
    lines = ["| scenario | " + " | ".join(f"`{n}`" for n in names) + " |", "|---|" + "---|" * len(names)]
    for scenario in (*HEALTHY, *FAULTS, DEADBAND):
        group = [o for o in outcomes if o.case.scenario == scenario.name]
        lines.append(f"| {scenario.name} | " + " | ".join(
            str(sum(o.recommendation == n for o in group)) for n in names) + " |")
    return "\n".join(lines)
