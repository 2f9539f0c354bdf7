"""One loop's health: :func:`assess` a record over a window into an :class:`Assessment` (indices, flags,
recommendation). Pure: numpy and scipy, the times come with the record.

Which samples each index reads: utilization, MV travel and reversals, the noise levels and a frozen PV the
whole window; saturation the samples in automatic; the control-performance indices (oscillation, idle index,
stiction, variability, Harris, set-point tracking) the longest stretch in automatic, so a switch to manual
never looks like a disturbance.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from autotuner.engine.described import described
from autotuner.engine.health.indices import Indices
from autotuner.engine.health.oscillation import Oscillation, oscillation
from autotuner.engine.health.record import LoopRecord
from autotuner.engine.health.scales import (SIGNIFICANT_SHARE, LoopLimits, process_sign, pv_span,
                                            ultimate_period)
from autotuner.engine.health.sensor import frozen_share
from autotuner.engine.health.signals import noise_std
from autotuner.engine.health.sluggish import sluggishness
from autotuner.engine.health.stiction import stiction
from autotuner.engine.health.tracking import tracking
from autotuner.engine.health.usage import reversals, saturation, travel, utilization
from autotuner.engine.health.variability import delay_samples, harris_index
from autotuner.engine.health.verdict import Context, Flag, flags, recommendation
from autotuner.engine.plant.process import Process

DEFAULT_WINDOW = 3600.0  # s: one hour
MIN_SAMPLES = 20  # fewer in the window: nothing to assess
MIN_AUTO_SAMPLES = 50  # a shorter stretch in automatic: no control-performance indices
LONG_RESPONSE = 10.0  # ultimate periods: a set-point response this long that never settled counts as unsettled
REVERSAL_SHARE = 0.001  # an MV reversal counts once it moves back by this share of its span (or 3 noise σ)


@dataclass(frozen=True)
class Assessment:
    """A loop's health over a window."""

    flags: tuple[Flag, ...] = described("what is wrong, each with a severity and a reason (empty: healthy)")
    recommendation: str = described("the one thing to do first: retune, check_valve, check_sensor, put_in_auto "
                                    "or none", example="check_valve")
    indices: Indices = described("every index, with its unit (docs/health.md)")
    dead_time_source: str | None = described("the dead time the Harris index used: 'model' (the identified "
                                             "model's) or 'one sample' (no model: the index a lower bound); null: "
                                             "no index", example="model")
    start: float = described("time of the window's first sample, s (the record's clock)", example=0.0)
    end: float = described("time of the window's last sample, s", example=3599.0)
    samples: int = described("samples assessed", example=3600)
    ts: float = described("the sample time assessed at, s", example=1.0)

    def to_json(self) -> dict[str, Any]:
        """``{"flags": [names], "recommendation", "reasons": {flag: text}, "severities": {flag: level},
        "indices": {name: number or null}, "dead_time_source", "window": {start, end, samples, ts}}``."""
        return {
            "flags": [f.name for f in self.flags],
            "recommendation": self.recommendation,
            "reasons": {f.name: f.reason for f in self.flags},
            "severities": {f.name: f.severity.value for f in self.flags},
            "indices": self.indices.to_json(),
            "dead_time_source": self.dead_time_source,
            "window": {"start": self.start, "end": self.end, "samples": self.samples, "ts": self.ts},
        }


def _significant(span: float | None, limits: LoopLimits, pv: np.ndarray, mv: np.ndarray, noise: float) -> float:
    """Hägglund's a, PV units: 1 % of the PV span; without one, what 1 % of the MV span moves the PV by at the
    loop's own frequencies (σ_pv/σ_mv times it); never below 3 noise σ."""
    if span is not None:
        a = SIGNIFICANT_SHARE * span
    else:
        spread = float(np.std(mv))
        a = SIGNIFICANT_SHARE * limits.mv_span * float(np.std(pv)) / spread if spread > 0.0 else 0.0
    return max(a, 3.0 * noise, 1e-12)


def _control(stretch: LoopRecord, model: Process | None, a: float, tu: float | None, noise: float) -> tuple[
        dict[str, Any], Oscillation]:
    """The control-performance indices of the longest stretch in automatic, and its oscillation."""
    ts = stretch.ts
    e = stretch.sp - stretch.pv
    hysteresis = max(3.0 * noise, 1e-12)
    osc = oscillation(e - e.mean(), ts, a, tu, hysteresis)
    slow = sluggishness(stretch.mv, stretch.pv, stretch.sp, osc.cycles, osc.detected, a,
                        process_sign(model), ts)
    found: dict[str, Any] = {
        "oscillation_rate": osc.rate, "regularity": osc.regularity, "oscillation_period": osc.period,
        "oscillation_amplitude": osc.amplitude,
        "idle_index": slow.idle, "load_recovery": slow.recovery,
        "error_mean": float(np.mean(e)), "error_std": float(np.std(e)),
        "harris": harris_index(e, delay_samples(None if model is None else model.delay, ts)),
        "dead_time": ts if model is None else model.delay,
    }
    if osc.oscillating:  # on PV − SP: the PV without the set point's steps
        st = stiction(stretch.mv, -e, ts, osc.period, hysteresis)
        found.update(ccf_zero_lag=st.ccf_zero_lag, shape_index=st.shape, stiction_band=st.band)
    tr = tracking(stretch.sp, stretch.pv, ts, noise, a, LONG_RESPONSE * (tu or 0.0))
    found.update(setpoint_steps=tr.steps, overshoot=tr.overshoot, settling_time=tr.settling_time)
    return found, osc


@dataclass(frozen=True)
class Detail:
    """An ``assessment`` with what it read: ``record`` the window as assessed (on its even grid), ``crossings`` the
    times of the control error's zero crossings Hägglund's detector counted (the half-cycles' bounds, s, the
    record's clock; empty without control-performance indices), ``period`` and ``amplitude`` the oscillation's
    (s, PV units; None: none found) — the evidence a page draws."""

    assessment: Assessment
    record: LoopRecord
    crossings: np.ndarray
    period: float | None
    amplitude: float | None


def assess(record: LoopRecord, limits: LoopLimits = LoopLimits(), model: Process | None = None,
           window: float = DEFAULT_WINDOW, ts: float | None = None, pv_unit: str = "") -> Assessment:
    """The health of the loop of ``record`` over its last ``window`` seconds.

    ``limits``: the loop's MV limits and, if known, its PV range. ``model``: the process model of the last
    tuning (None: none) — its dead time for the Harris index, its ultimate period for Hägglund's detector, its
    gain's sign and whether it integrates for the stiction tests. ``ts``: the sample time to assess at, s
    (None: the record's median spacing; an uneven record is resampled). ``pv_unit``: the PV's unit, for the
    reasons. ValueError when fewer than 20 samples remain.
    """
    return assess_detail(record, limits, model, window, ts, pv_unit).assessment


def assess_detail(record: LoopRecord, limits: LoopLimits = LoopLimits(), model: Process | None = None,
                  window: float = DEFAULT_WINDOW, ts: float | None = None, pv_unit: str = "") -> Detail:
    """:func:`assess` (the same parameters: ``record``, ``limits``, ``model``, ``window`` s, ``ts`` s,
    ``pv_unit``) with the window as assessed and the oscillation's crossings (:class:`Detail`)."""
    rec = record.last(window).uniform(ts)
    if len(rec) < MIN_SAMPLES:
        raise ValueError(f"{len(rec)} samples in the window: an assessment needs at least {MIN_SAMPLES}")
    hours = rec.duration / 3600.0
    pv_noise, mv_noise = noise_std(rec.pv), noise_std(rec.mv)
    span, _ = pv_span(limits, model)
    tu = ultimate_period(model)
    found: dict[str, Any] = {
        "utilization": utilization(rec.auto),
        "saturation": saturation(rec.mv, rec.auto, limits.mv) if np.any(rec.auto) else None,
        "mv_travel": travel(rec.mv, hours),
        "mv_reversals": reversals(rec.mv, max(REVERSAL_SHARE * limits.mv_span, 3.0 * mv_noise), hours),
        "pv_noise": pv_noise, "mv_noise": mv_noise, "frozen_share": frozen_share(rec.pv),
    }
    stretch = rec.longest_auto()
    a = _significant(span, limits, rec.pv, rec.mv, pv_noise)
    osc = None
    crossings = np.zeros(0)
    if stretch is not None and len(stretch) >= MIN_AUTO_SAMPLES:
        control, osc = _control(stretch, model, a, tu, pv_noise)
        found.update(control)
        if len(osc.cycles):
            crossings = stretch.t[np.append(osc.cycles.start, osc.cycles.end[-1])]
    ind = Indices(**found)
    ctx = Context(a, span, limits.mv_span, tu, None if model is None else model.is_integrating, rec.duration,
                  pv_unit)
    found_flags = flags(ind, osc, ctx)
    source = None if ind.harris is None else ("model" if model is not None else "one sample")
    result = Assessment(tuple(found_flags), recommendation(found_flags, ind.utilization), ind, source,
                        float(rec.t[0]), float(rec.t[-1]), len(rec), rec.ts)
    return Detail(result, rec, crossings, None if osc is None else osc.period, None if osc is None else osc.amplitude)


__all__ = ["Assessment", "Detail", "LoopLimits", "LoopRecord", "assess", "assess_detail"]
