"""All applicable rules for one process in one table, judged on the process itself.

For each rule that defines the controller type and applies to the data: the
gains, then on the plant (the exact process for ``--plant``/``--fopdt``, the
model through the point for ``--point`` with static gain) the maximum
sensitivity, gain and phase margins (:func:`autotuner.engine.design.closed_loop.margins`)
and the IAE of a unit load step at the process input, simulated with the
exact ZOH plant and the engine's PID unit (:func:`autotuner.engine.design.closed_loop.integrated_error`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from autotuner.engine.design.closed_loop import HORIZON_PERIODS, STEP_SAMPLES_PER_PERIOD, integrated_error, margins, reference_period
from autotuner.engine.control.gains import json_number
from autotuner.engine.design.process_data import ProcessData
from autotuner.engine.design.rules import RULES, Options, RuleError, RuleResult, tune


@dataclass(frozen=True)
class Row:
    """One rule's result on the plant: IAE is inf for an unstable loop or a load offset (no integral)."""

    tuning: RuleResult
    stable: bool
    ms: float
    gain_margin: float
    phase_margin_deg: float
    iae: float


def compare(data: ProcessData, controller: str, options: Options) -> tuple[list[Row], dict[str, str]]:
    """Rows for every rule that applies, and the reason for each rule that does not.

    Raises RuleError when there is no plant to judge on (a point without static gain).
    """
    if data.process is None:
        raise RuleError("--compare needs a plant or a model: give --plant, --fopdt, or --static-gain with --point")
    period = reference_period(data.process)
    rows: list[Row] = []
    skipped: dict[str, str] = {}
    for name, rule in RULES.items():
        if controller not in rule.controllers:
            skipped[name] = f"defines {', '.join(rule.controllers)} only"
            continue
        try:
            tuning = tune(name, data, controller, options)
        except RuleError as exc:
            skipped[name] = str(exc)
            continue
        rows.append(_judge(data, tuning, period))
    return rows, skipped


def _judge(data: ProcessData, tuning: RuleResult, period: float) -> Row:
    m = margins(data.process, tuning.gains, 2.0 * math.pi / period)
    iae = integrated_error(data.process, tuning.gains, "load", period)[0] if m.stable else math.inf
    return Row(tuning, m.stable, m.ms, m.gain_margin, m.phase_margin_deg, iae)


METHOD_NOTE = (f"Ms, margins on a 6000-point log grid; IAE of a unit load step at the process input, "
               f"PlantSim (exact ZOH) + PidUnit at ts = T135/{STEP_SAMPLES_PER_PERIOD}, rectangle sum over "
               f"{HORIZON_PERIODS:g}·T135")


def compare_json(rows: list[Row], skipped: dict[str, str], controller: str) -> dict[str, Any]:
    """The JSON of ``autotuner design --compare``: each rule's JSON with its figures on the plant, and the
    rules that do not apply with the reason."""
    return {"controller": controller, "method": METHOD_NOTE, "skipped": skipped, "rules": [
        {**r.tuning.as_json(), "stable": r.stable, "ms": json_number(r.ms), "gain_margin": json_number(r.gain_margin),
         "phase_margin_deg": json_number(r.phase_margin_deg), "iae_load": json_number(r.iae)} for r in rows]}

