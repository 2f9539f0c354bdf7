"""Sluggish control: Hägglund's idle index after load disturbances.

Hägglund (1999), "Automatic detection of sluggish control loops", Control Engineering Practice 7(12):1505–1511.
After a load disturbance a well-tuned loop brings the PV back while the MV has already stopped moving the same
way (ΔMV and ΔPV of opposite signs, for a process of positive gain); a sluggish one keeps pushing the MV the same
way as the PV recovers, slowly (same signs). With t_pos the time when ΔMV·ΔPV > 0 and t_neg the time when it is
< 0, both over the periods after load disturbances only (here: the half-cycles of the error that Hägglund's
detector counted, :mod:`autotuner.engine.health.oscillation`), the idle index is

    Ii = (t_pos − t_neg) / (t_pos + t_neg),

close to 1 for a sluggish loop and negative for a well-tuned one. MV and PV are low-pass filtered first (time
constant a tenth of the disturbances' median half-cycle) so noise does not count.

Around an integrating process the MV must overshoot its new balance for the PV to come back, so the index is
negative however slow the loop (Hägglund's index is for self-regulating processes). There the sign of
sluggishness is time: the recovery time, how long the error stays beyond a quarter of its peak after a load
disturbance (median over them), against the process's ultimate period Tu (a loop tuned for it recovers within
a few Tu). It is judged for every process when the model gives Tu. And a loop so slow that its error hardly
ever crosses zero shows as an offset: the error's mean over the window beyond twice the significant deviation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.signal

from autotuner.engine.health.signals import HalfCycles

SLUGGISH = 0.4  # Ii above this: sluggish
MAX_RECOVERIES = 100  # the latest load disturbances whose recovery times are taken
RECOVERED = 0.25  # a disturbance has passed once the error is back within this share of its peak
SLOW_RECOVERY = 10.0
OFFSET = 2.0  # a mean error beyond this many significant deviations: sluggish (integral action removes it)  # load disturbances recovered over more ultimate periods than this: sluggish
MIN_DISTURBANCES = 2  # fewer detected load disturbances say nothing


def _lowpass(x: np.ndarray, samples: float) -> np.ndarray:
    """First-order low-pass of time constant ``samples`` sample times, starting at rest at x[0]."""
    a = np.exp(-1.0 / max(samples, 1e-9))
    y, _ = scipy.signal.lfilter([1.0 - a], [1.0, -a], x, zi=[a * x[0]])
    return y


@dataclass(frozen=True)
class Sluggishness:
    """``idle``: Hägglund's Ii (None: fewer than two load disturbances); ``recovery``: the median time the
    error spends beyond a quarter of its peak in their half-cycles (the latest 100), s (None: likewise)."""

    idle: float | None
    recovery: float | None


def _set_point_free(sp: np.ndarray, cycles: HalfCycles) -> np.ndarray:
    """Which half-cycles no set-point change in ``sp`` starts or crosses (those are set-point responses)."""
    changes = np.concatenate(([0], np.cumsum(np.diff(sp) != 0.0)))  # set-point changes up to each sample
    return changes[cycles.end] == changes[np.maximum(cycles.start - 1, 0)]


def sluggishness(u: np.ndarray, y: np.ndarray, sp: np.ndarray, cycles: HalfCycles, detected: np.ndarray,
                 a: float, sign: int, ts: float) -> Sluggishness:
    """Hägglund's Ii and the recovery time over the load disturbances among the error's half-cycles
    ``cycles``, from the MV ``u``, PV ``y`` and set point ``sp`` sampled every ``ts`` seconds; ``sign``: the
    process gain's sign.

    The load disturbances: the half-cycles Hägglund's detector counted (``detected``), no set-point response,
    whose filtered error reaches beyond the significant deviation ``a`` (a slow wander of noise can pile up an
    IAE too, but not a filtered peak).
    """
    candidates = np.flatnonzero(detected & _set_point_free(sp, cycles))
    if len(candidates) < MIN_DISTURBANCES:
        return Sluggishness(None, None)
    tau = 0.1 * float(np.median(cycles.end[candidates] - cycles.start[candidates]))
    deviation = np.abs(_lowpass(sp - y, tau))
    peaks = np.maximum.reduceat(deviation, cycles.start)[candidates]
    chosen = candidates[peaks > a]
    if len(chosen) < MIN_DISTURBANCES:
        return Sluggishness(None, None)
    product = sign * np.diff(_lowpass(u, tau)) * np.diff(_lowpass(y, tau))  # product[k]: from sample k to k+1
    inside = np.zeros(len(u) + 1, dtype=np.int64)  # +1 at each chosen start, -1 at its end: a running count
    np.add.at(inside, cycles.start[chosen], 1)
    np.add.at(inside, cycles.end[chosen], -1)
    mask = np.cumsum(inside)[: len(product)] > 0
    t_pos = int(np.count_nonzero(product[mask] > 0.0))
    t_neg = int(np.count_nonzero(product[mask] < 0.0))
    idle = float((t_pos - t_neg) / (t_pos + t_neg)) if t_pos + t_neg else None
    latest = chosen[-MAX_RECOVERIES:]  # as telling as all of them, for a bounded cost
    return Sluggishness(idle, ts * float(np.median([_recovery(deviation[a:b])
                                                    for a, b in zip(cycles.start[latest], cycles.end[latest])])))


def _recovery(deviation: np.ndarray) -> int:
    """Samples from the first to the last beyond a quarter of the peak of one half-cycle's |error| (filtered
    like MV and PV, so noise does not stretch it)."""
    beyond = np.flatnonzero(deviation > RECOVERED * deviation.max())
    return int(beyond[-1] - beyond[0] + 1)
