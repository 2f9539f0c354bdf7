"""Set-point tracking after set-point steps: overshoot and settling time.

A step is a change of the set point at least twice the significant deviation a, ten noise standard deviations
and four standard deviations of the error before it (a smaller one drowns in the loop's own variations); its response lasts until the next change or
the end of the record. Overshoot: how far the PV went past the new set point, in % of the step. Settling
time: from the step until the PV enters the band about the new set point, ±5 % of the step (or 3 standard
deviations of the error before the step, if the loop varies more than that), to stay in it for 20 samples or
to the end of the response; None when it never does. A response cut short by the next step before it settled
is left out unless it lasted long enough that it should have (``long_enough``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BAND = 0.05  # the settling band, share of the step
MIN_RESPONSE = 10  # samples: a shorter response is left out
HOLD = 20  # samples the PV must stay in the band to have settled
LONG_SAMPLES = 100  # a response never settled over this many samples (at least) is unsettled


@dataclass(frozen=True)
class Tracking:
    """The set-point steps of a record: how many were analysed, their mean overshoot (%) and settling time (s;
    None: one or more never settled, or no step), and how many never settled.

    steps: set-point steps analysed; overshoot: their mean, %; settling_time: their mean, s; unsettled: how many
    never settled.
    """

    steps: int
    overshoot: float | None
    settling_time: float | None
    unsettled: int


def _settled(inside: np.ndarray) -> int | None:
    """The first sample from which ``inside`` holds for ``HOLD`` samples or to its end (None: never)."""
    edges = np.diff(np.concatenate(([False], inside, [False])).astype(np.int8))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    long = (ends - starts >= HOLD) | (ends == len(inside))
    return int(starts[long][0]) if np.any(long) else None


def _spread(e: np.ndarray) -> float:
    """The error's own standard deviation, from its median absolute deviation (so the set-point responses,
    a small share of the samples, do not count)."""
    return float(1.4826 * np.median(np.abs(e - np.median(e))))


def tracking(sp: np.ndarray, pv: np.ndarray, ts: float, noise: float, a: float, long_enough: float) -> Tracking:
    """The set-point steps in ``sp`` and the ``pv``'s response to each (PV units, every ``ts`` seconds);
    ``noise``: the PV's noise standard deviation, ``a`` the significant deviation, PV units; ``long_enough``:
    seconds a response must last to count as unsettled when it never settled (at least 100 samples)."""
    changes = np.flatnonzero(np.diff(sp) != 0.0) + 1
    spread = _spread(sp - pv)
    bounds = np.concatenate((changes, [len(sp)]))
    overshoots, settling, unsettled = [], [], 0
    for k, end in zip(bounds[:-1], bounds[1:]):
        if end - k < MIN_RESPONSE:
            continue
        step = sp[k] - sp[k - 1]
        if abs(step) < max(2.0 * a, 10.0 * noise, 4.0 * spread):
            continue
        past = (pv[k:end] - sp[k]) * np.sign(step)
        overshoots.append(100.0 * max(0.0, float(past.max()) - 2.0 * spread) / abs(step))
        band = max(BAND * abs(step), 3.0 * noise, 3.0 * spread)
        settled = _settled(np.abs(pv[k:end] - sp[k]) <= band)
        if settled is None and (end - k) * ts >= max(long_enough, LONG_SAMPLES * ts):
            unsettled += 1
        elif settled is None:
            overshoots.pop()  # cut short by the next step: says nothing
        else:
            settling.append(settled * ts)
    if not overshoots:
        return Tracking(0, None, None, 0)
    return Tracking(len(overshoots), float(np.mean(overshoots)),
                    float(np.mean(settling)) if settling and not unsettled else None, unsettled)
