"""The scales an assessment measures a loop against: its limits, its time scale and the size of a significant
deviation."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

from autotuner.engine.design.process_data import exact_point
from autotuner.engine.plant.process import Process

# The significant deviation a: Hägglund suggests 1 % of the PV span; half of it here, so a regular oscillation
# of a few noise σ on a quiet loop counts (the regularity test, not the size, keeps load disturbances out).
SIGNIFICANT_SHARE = 0.005


@dataclass(frozen=True)
class LoopLimits:
    """The loop's ranges: ``mv`` its MV limits (low, high, MV units); ``pv`` its PV range (low, high, PV units;
    None: unknown)."""

    mv: tuple[float, float] = (0.0, 100.0)
    pv: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        for name, pair in (("mv", self.mv), ("pv", self.pv)):
            if pair is None:
                continue
            lo, hi = pair
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"{name} limits must be finite with low < high, got {lo:g}:{hi:g}")

    @property
    def mv_span(self) -> float:
        """High minus low MV limit, MV units."""
        return self.mv[1] - self.mv[0]


@functools.lru_cache(maxsize=4096)  # a loop's model changes only when it is tuned; the search costs ms
def ultimate_period(model: Process | None) -> float | None:
    """The period (s) where the model lags 180°, the loop's natural time scale (Hägglund's Tu = 2π/ωu); None
    without a model or for one that never lags 180°."""
    if model is None:
        return None
    point = exact_point(model, 180.0)
    return None if point is None else 2.0 * math.pi / point.omega


def pv_span(limits: LoopLimits, model: Process | None) -> tuple[float | None, str]:
    """The PV span (PV units) and where it came from: the PV range; else the MV span times the model's static
    gain; else None (unknown).

    ``limits``: the loop's limits; ``model``: the process model, or None.
    """
    if limits.pv is not None:
        return limits.pv[1] - limits.pv[0], "the PV range"
    if model is not None and math.isfinite(model.static_gain()) and model.static_gain() != 0.0:
        return limits.mv_span * abs(model.static_gain()), "the MV span times the model's static gain"
    return None, "unknown"


def process_sign(model: Process | None) -> int:
    """+1 when more MV makes more PV (the model's sign; +1 without a model), −1 otherwise.

    ``model``: the process model, or None.
    """
    return -1 if model is not None and model.static_gain() < 0.0 else 1  # ±inf for an integrating model
