"""Golden traces of the relay experiment: fixed simulated runs whose every MV and whose identification must not move.

Each case runs the engine alone (``run_experiment`` on a :class:`PlantSim`: deterministic, no clock) over one
process of the benchmark batch's families, with and without noise, load steps and drift, unstable and
integrating processes, PI and PID; its MV sequence (every sample, as float64 bytes, hashed), its outcome and
its identification (every field, exactly) and designed gains are compared with tests/golden/references.json.
A change that moves any of them — a constant, an order of operations — fails here: a restructure of the
experiment must leave every reference as it is, and a change of behaviour must say so by writing new ones:

    python tests/test_golden.py --update      # after checking that the change is meant (benches, tests)
"""

from __future__ import annotations

import os

# As tests/conftest.py sets them for pytest, for `python tests/test_golden.py --update` (before numpy's import).
os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import hashlib  # noqa: E402
import json
import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from autotuner.engine.design.process_data import exact_point
from autotuner.engine.experiment.relay import RelayConfig
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import default_sample_time, default_time_limit, ramp_loads, result_of, \
    run_experiment

REFERENCES = Path(__file__).parent / "golden" / "references.json"


@dataclass(frozen=True)
class Case:
    """One run: ``plant``; noise σ as a share of the PV's oscillation amplitude (|F|·amp at 135°); load steps
    (periods after the start, MV units); a drift (MV units per period); the controller designed; the field's
    tolerances or the simulation's."""

    name: str
    plant: str
    noise: float = 0.0
    seed: int = 1
    loads: tuple[tuple[float, float], ...] = ()
    drift: float = 0.0
    controller: str = "PI"
    field: bool = False


BATCH = {  # one or two processes of each family of the benchmark batch (shared/bench/amigo-batch.csv)
    "P1-T0.1": "exp(-s)/(0.1*s+1)", "P1-T2": "exp(-s)/(2*s+1)", "P1-T20": "exp(-s)/(20*s+1)",
    "P2-T1": "exp(-s)/(s+1)^2", "P2-T10": "exp(-s)/(10*s+1)^2",
    "P3-T0.5": "exp(-s)/((s+1)*(0.5*s+1)^2)", "P4-n3": "1/(s+1)^3", "P4-n8": "1/(s+1)^8",
    "P5-a0.2": "1/((s+1)*(0.2*s+1)*(0.04*s+1)*(0.008*s+1))", "P6-a1": "(1-s)/(s+1)^3",
    "P7-T1": "exp(-s)/(s+1)/(0.1*s+1)", "P8-T3": "exp(-0.5*s)/(3*s+1)/(s+1)",
    "P9-T0.1": "1/((s+1)*(0.1*s+1)^2)", "demo": "1.5*exp(-0.7*s)/(4*s+1)^2",
}
CASES: tuple[Case, ...] = (
    *(Case(name, plant) for name, plant in BATCH.items()),
    *(Case(f"{name} PID", BATCH[name], controller="PID") for name in ("P1-T2", "P2-T1", "P4-n3", "P6-a1")),
    *(Case(f"{name} noise 1 %", BATCH[name], noise=0.01, seed=seed)
      for seed, name in enumerate(("P1-T0.1", "P2-T10", "P4-n8", "P7-T1", "demo"), 1)),
    Case("demo noise 5 % PID", BATCH["demo"], noise=0.05, seed=3, controller="PID", field=True),
    *(Case(f"{name} load {size:+g} at {when:g}", BATCH[name], loads=((when, size),), field=True)
      for name, when, size in (("P1-T2", 1.5, 0.2), ("P2-T1", 3.5, -0.3), ("demo", 1.5, -0.2),
                               ("P8-T3", 3.5, 0.3), ("P1-T20", 2.5, 0.15))),
    Case("P2-T1 noise 2 % load +0.15", BATCH["P2-T1"], noise=0.02, loads=((3.5, 0.15),), field=True),
    *(Case(f"{name} drift {rate:+g}", BATCH[name], drift=rate, field=True)
      for name, rate in (("P1-T2", 0.03), ("demo", -0.03), ("P4-n3", 0.03))),
    Case("unstable D/T 0.1", "exp(-0.2*s)/(2*s-1)"),
    Case("unstable D/T 0.2 PID", "exp(-0.4*s)/(2*s-1)", controller="PID"),
    Case("unstable with lag PID", "exp(-0.3*s)/((s-1)*(0.1*s+1))", controller="PID"),
    Case("unstable D/T 0.275 noise", "exp(-0.55*s)/(2*s-1)", noise=0.01, controller="PID"),
    Case("integrating", "exp(-0.5*s)/(s*(3*s+1))"),
    Case("integrating PID", "exp(-0.5*s)/(s*(3*s+1))", controller="PID"),
    Case("integrating dead time", "exp(-s)/s"),
    Case("integrating noise load", "exp(-0.5*s)/(s*(3*s+1))", noise=0.01, loads=((3.5, 0.1),), field=True),
)


def _float(x: float) -> Any:
    """A float as JSON keeps it exactly (repr round-trips), infinities as text."""
    return x if math.isfinite(x) else repr(x)


def _exact(value: Any) -> Any:
    if isinstance(value, float):
        return _float(value)
    if isinstance(value, complex):
        return [_float(value.real), _float(value.imag)]
    if isinstance(value, dict):
        return {k: _exact(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_exact(v) for v in value]
    return value


def run_case(case: Case) -> dict[str, Any]:
    """The case's run: the MV sequence's hash, the outcome, the identification and the gains, exactly."""
    process = parse_process(case.plant)
    ts = default_sample_time(process)
    point = exact_point(process, 135.0)
    period = 2.0 * math.pi / point.omega if point is not None else 100.0 * ts
    scale = point.gain if point is not None else 1.0  # PV oscillation per MV unit of amp
    limit = default_time_limit(process, 135.0, ts)
    loads = [(when * period, size) for when, size in case.loads] + ramp_loads(case.drift / period, ts, limit)
    sim = PlantSim(process, ts, noise_std=case.noise * scale, seed=case.seed, loads=loads)
    config = RelayConfig(amp=1.0, time_limit=limit)
    if case.field:
        from autotuner.service.remote_tuning import field_config

        config = field_config(config)
    experiment, trace = run_experiment(sim, config)
    result = result_of(experiment, trace, case.controller, 1.4)
    ident = result.identification
    return {
        "samples": len(trace.mv),
        "mv": hashlib.sha256(np.asarray(trace.mv, dtype=np.float64).tobytes()).hexdigest(),
        "code": int(result.code),
        "message": result.message,
        "identification": None if ident is None else _exact({**asdict(ident), "point": ident.point.value,
                                                               "omega": ident.point.omega}),
        "gains": None if result.design is None else _exact(result.design.gains.as_json()),
    }


def _references() -> dict[str, Any]:
    return json.loads(REFERENCES.read_text())


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_the_run_is_its_golden_trace(case):
    reference = _references()[case.name]
    assert run_case(case) == reference


def test_the_cases_cover_what_the_experiment_does():
    names = [c.name for c in CASES]
    assert len(CASES) >= 40 and len(set(names)) == len(names)
    assert any(c.noise for c in CASES) and any(c.loads for c in CASES) and any(c.drift for c in CASES)
    assert any("unstable" in n for n in names) and any("integrating" in n for n in names)
    assert {c.controller for c in CASES} == {"PI", "PID"}
    assert set(_references()) == set(names)  # every case has a reference, and no stale one is left


def test_a_changed_constant_moves_the_traces(monkeypatch):
    # The references are no tautology: one tuning constant of the experiment changed by a hair moves them.
    from autotuner.engine.experiment import adaptation

    monkeypatch.setattr(adaptation, "RELAXATION", adaptation.RELAXATION * 1.001)
    # (The first six cases are the model rule's, model_rule.py: they stop before the secant's relaxation acts.)
    moved = [c.name for c in CASES[6:10] if run_case(c) != _references()[c.name]]
    assert moved, "no golden trace moved when a constant of the experiment did"


if __name__ == "__main__":
    if sys.argv[1:] != ["--update"]:
        sys.exit(__doc__)
    REFERENCES.parent.mkdir(exist_ok=True)
    REFERENCES.write_text(json.dumps({c.name: run_case(c) for c in CASES}, indent=1, sort_keys=True) + "\n")
    print(f"wrote {len(CASES)} references to {REFERENCES}")
