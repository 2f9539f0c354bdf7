"""Loop robustness: maximum sensitivity, Nyquist stability, and the MIGO limit.

All functions work on frequency responses sampled on a logarithmic grid, so
they apply equally to a fitted model, the exact process, or any callable that
returns ``F(jω)`` for an array of angular frequencies in rad/s.

The MIGO problem (Åström, Panagopoulos, Hägglund 1998): find the controller
with the largest integral gain ``ki = k/ti`` such that the closed loop is
stable and ``|1 + L(jω)| ≥ 1/Ms`` at every frequency. For a fixed integral
time ``ti`` (and ``td = ratio·ti``) the open loop is ``L = k·z(ω)`` with
``z = C0·F`` known, so each frequency forbids an interval of ``k`` (where the
ray ``k·z`` crosses the Ms circle) and the largest admissible ``k`` follows
from a sorted union of intervals. The outer search over ``ti`` is a
one-dimensional maximisation.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

FreqResp = Callable[[np.ndarray], np.ndarray]


def log_grid(w_ref: float, below: float = 1e-4, above: float = 1e2, n: int = 3000) -> np.ndarray:
    """Logarithmic grid of angular frequencies (rad/s) from ``below·w_ref`` to ``above·w_ref``.

    ``n``: how many frequencies.
    """
    return np.logspace(math.log10(below * w_ref), math.log10(above * w_ref), n)


def pid_frequency_response(w: np.ndarray, k: float, ti: float, td: float = 0.0, nd: float = 10.0) -> np.ndarray:
    """Feedback part ``C(jω)`` of the standard-form PID ``k(1 + 1/(ti s) + td s/(td s/nd + 1))``.

    ``w`` in rad/s, ``ti`` and ``td`` in seconds; ``ti = inf`` means no integral action.
    """
    s = 1j * w
    c = 1.0 + (0.0 if math.isinf(ti) else 1.0 / (ti * s))
    if td > 0.0:
        c = c + td * s / (td * s / nd + 1.0)
    return k * c


def max_sensitivity(loop: np.ndarray) -> float:
    """``Ms = max |1/(1 + L)|`` over the sampled open loop ``L`` (inf if it passes through −1).

    ``loop``: L(jω) on a frequency grid.
    """
    d = np.min(np.abs(1.0 + loop))
    return math.inf if d == 0.0 else float(1.0 / d)


def closed_loop_stable(loop: np.ndarray, w: np.ndarray, integrators: int = 0, rhp_poles: int = 0) -> bool:
    """Nyquist criterion for the loop ``L`` sampled on the increasing grid ``w`` (rad/s).

    ``integrators`` is the number of open-loop poles at the origin (the
    process's plus the controller's) and
    ``rhp_poles`` the number in the open right half plane. The grid must start
    low enough for the integrators to dominate and end where ``|L|`` is small;
    the contour is indented to the right of the origin, which contributes
    ``−integrators·π`` of phase, and the negative frequencies mirror the
    positive ones.

    ``loop``: L(jω) on ``w``.
    """
    if not np.all(np.isfinite(loop)):
        return False
    phase = np.unwrap(np.angle(1.0 + loop))
    turn = phase[-1] - phase[0]
    clockwise = (integrators * math.pi - 2.0 * turn) / (2.0 * math.pi)
    return round(clockwise) + rhp_poles == 0


@dataclass(frozen=True)
class LoopCheck:
    """Robustness of one loop: ``ms`` (inf if unstable) and whether it is ``stable``."""

    ms: float
    stable: bool


def check_loop(
    freqresp: FreqResp,
    controller: Callable[[np.ndarray], np.ndarray],
    w: np.ndarray,
    integrators: int = 0,
    rhp_poles: int = 0,
) -> LoopCheck:
    """Maximum sensitivity and stability of ``C·F`` on the grid ``w`` (rad/s).

    ``freqresp``: F(jω) as a function of ω (rad/s); ``controller``: C(jω) likewise; ``integrators``, ``rhp_poles``:
    the open loop's poles at 0 and in the right half plane.
    """
    loop = controller(w) * freqresp(w)
    stable = closed_loop_stable(loop, w, integrators, rhp_poles)
    return LoopCheck(ms=max_sensitivity(loop) if stable else math.inf, stable=stable)


@dataclass(frozen=True)
class MigoResult:
    """Largest-integral-gain controller found: ``k`` (MV per PV unit), ``ti``, ``td`` in seconds."""

    k: float
    ti: float
    td: float

    @property
    def ki(self) -> float:
        """Integral gain ``k/ti`` (MV per PV unit per second)."""
        return self.k / self.ti


@dataclass(frozen=True)
class Plant:
    """A frequency response with what the Nyquist criterion needs to know about its poles.

    ``margin`` multiplies the required Ms for this plant: a plant that only
    bounds the uncertainty (not the best guess) may be held to a looser limit.

    ``freqresp``: F(jω) as a function of ω (rad/s); ``integrators``: its poles at 0; ``rhp_poles``: its poles in the
    right half plane.
    """

    freqresp: FreqResp
    integrators: int = 0
    rhp_poles: int = 0
    margin: float = 1.0


def _largest_gain(z_list: Sequence[np.ndarray], w: np.ndarray, plants: Sequence[Plant], ms: float) -> float:
    """Largest ``k`` keeping every loop ``k·z`` stable and outside the Ms circle (0 if none)."""
    lows, highs = [], []
    for z, plant in zip(z_list, plants):
        r2 = 1.0 / (ms * plant.margin) ** 2
        a = np.abs(z) ** 2
        b = z.real
        disc = b * b - a * (1.0 - r2)
        hit = (disc > 0.0) & (b < 0.0)
        root = np.sqrt(disc[hit])
        lows.append((-b[hit] - root) / a[hit])
        highs.append((-b[hit] + root) / a[hit])
    lo = np.concatenate(lows)
    hi = np.concatenate(highs)
    order = np.argsort(lo)
    lo, hi = lo[order], hi[order]
    # Admissible gains are the gaps between merged forbidden intervals; the
    # loop's stability is constant inside a gap, so one probe per gap decides.
    gaps: list[tuple[float, float]] = []
    reach = 0.0
    for a_, b_ in zip(lo, hi):
        if a_ > reach:
            gaps.append((reach, a_))
        reach = max(reach, b_)
    gaps.append((reach, math.inf))
    best = 0.0
    for g_lo, g_hi in reversed(gaps):
        if g_hi <= g_lo:
            continue
        probe = 0.5 * (g_lo + g_hi) if math.isfinite(g_hi) else 2.0 * g_lo + 1.0
        if all(
            closed_loop_stable(probe * z, w, p.integrators + 1, p.rhp_poles) for z, p in zip(z_list, plants)
        ):
            best = g_hi
            break
    return best


def migo(
    plants: Sequence[Plant],
    w_ref: float,
    ms: float = 1.4,
    td_ratio: float = 0.0,
    nd: float = 10.0,
    w: np.ndarray | None = None,
) -> MigoResult:
    """Controller with the largest integral gain such that every plant's loop has ``Ms ≤ ms``.

    ``w_ref`` (rad/s) is a frequency near the expected crossover (e.g. the
    identified point); it sets the search ranges. ``td_ratio`` fixes
    ``td = td_ratio·ti`` (0 gives PI), the usual way to keep the PID problem
    from degenerating into a needle-like derivative gain. Designing for
    several plants at once makes the controller robust to the spread between
    them.

    ``plants``: the plants the controller must hold; ``nd``: the derivative filter's N; ``w``: the frequency grid
    (rad/s; None: :func:`log_grid` around ``w_ref``).
    """
    if w is None:
        w = log_grid(w_ref)
    responses = [p.freqresp(w) for p in plants]
    s = 1j * w

    def ki_of(log_ti: float) -> float:
        ti = math.exp(log_ti)
        c0 = 1.0 + 1.0 / (ti * s)
        if td_ratio > 0.0:
            td = td_ratio * ti
            c0 = c0 + td * s / (td * s / nd + 1.0)
        k = _largest_gain([c0 * f for f in responses], w, plants, ms)
        return k / ti

    grid = np.linspace(math.log(0.02 / w_ref), math.log(200.0 / w_ref), 60)
    values = np.array([ki_of(x) for x in grid])
    i = int(np.argmax(values))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    best_x, best_v = grid[i], values[i]
    res = minimize_scalar(lambda x: -ki_of(x), bounds=(lo, hi), method="bounded", options={"xatol": 1e-4})
    if -res.fun > best_v:
        best_x = res.x
    ti = math.exp(best_x)
    return MigoResult(k=ki_of(best_x) * ti, ti=ti, td=td_ratio * ti)
