"""The numbers of a loop's health assessment (:class:`Indices`), each with its unit (docs/health.md)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

from autotuner.engine.described import described


def _i(description: str, example: float | int) -> Any:
    """An index that is always computed."""
    return described(description, example=example)


def _o(description: str, example: float | int) -> Any:
    """An index the window may not allow: null then."""
    return described(description, None, example=example)


@dataclass(frozen=True)
class Indices:
    """Every index of an assessment; None where the window does not allow it (e.g. no set-point step, never in
    automatic, no oscillation to test for stiction)."""

    utilization: float = _i("share of the window in the loop's normal (automatic) mode, 0–1", 1.0)
    mv_travel: float = _i("the MV's total travel Σ|ΔMV| per hour, MV units/h", 120.0)
    mv_reversals: float = _i("the MV's reversals of direction per hour (moves back of more than 0.1 % of its "
                             "span or 3 noise σ)", 60.0)
    pv_noise: float = _i("standard deviation of the PV's white noise (from its second differences), PV units",
                         0.05)
    mv_noise: float = _i("standard deviation of the MV's white noise (from its second differences), MV units",
                         0.02)
    frozen_share: float = _i("longest run with the PV unchanged, share of the window, 0–1", 0.0)
    saturation: float | None = _o("share of the automatic samples with the MV at a limit (within 0.5 % of its "
                                  "span), 0–1", 0.0)
    oscillation_rate: float | None = _o("Hägglund's load detections (half-cycles of the error whose IAE exceeds "
                                        "2a/ωu) per supervision time of 50 periods", 2.0)
    regularity: float | None = _o("Thornhill's regularity of the error's zero crossings, mean(Tp)/(3·std(Tp)); "
                                  "above 1: regular", 0.7)
    oscillation_period: float | None = _o("mean period between alternate zero crossings of the error, s", 42.0)
    oscillation_amplitude: float | None = _o("amplitude of the error as a sine of equal mean |e|, PV units", 0.3)
    idle_index: float | None = _o("Hägglund's idle index after load disturbances, −1…1; near 1: sluggish", -0.2)
    load_recovery: float | None = _o("median time the error stays beyond a quarter of its peak after a load disturbance, s",
                                      30.0)
    ccf_zero_lag: float | None = _o("Horch's |r_uy(0)|/max|r_uy(τ)| over half a period, 0 (odd: sticking valve) "
                                    "… 1 (even)", 0.9)
    shape_index: float | None = _o("He et al.'s shape index of the PV's half-cycles, MSE_sine/(MSE_sine + "
                                   "MSE_triangle), 0–1; above 0.5: triangular", 0.2)
    stiction_band: float | None = _o("the MV's swing per PV cycle (median), an estimate of the valve's deadband "
                                     "plus stickband S, MV units", 3.1)
    error_mean: float | None = _o("mean of the control error SP − PV in automatic, PV units", 0.01)
    error_std: float | None = _o("standard deviation of the control error SP − PV in automatic, PV units", 0.4)
    harris: float | None = _o("Harris index σ²_mv/σ²_e, 0–1; 1 at minimum variance", 0.35)
    dead_time: float | None = _o("the dead time the Harris index used, s (one sample without a model)", 0.7)
    setpoint_steps: int = described("set-point steps analysed", 0, example=1)
    overshoot: float | None = _o("mean overshoot past the new set point after a step, % of the step", 12.0)
    settling_time: float | None = _o("mean time from a step until the PV stays within ±5 % of it, s (null: a "
                                     "step never settled, or none)", 25.0)

    def to_json(self) -> dict[str, float | int | None]:
        """The indices by name (null where not computed, or not finite)."""
        return {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in asdict(self).items()}
