"""Discrete-time plant simulator, exact at the sample instants under zero-order hold.

The rational part is realised in state space (x' = A x + B v, y = C x + D v,
with v(t) = u(t - L)) and discretised exactly for the sample time Ts. A dead
time L = d*Ts + θ with 0 <= θ < Ts need not be a multiple of Ts: within each
sample interval the delayed input switches from u[k-d-1] to u[k-d] at
t_k + θ, so

    x[k+1] = Φ x[k] + Γ1 u[k-d-1] + Γ0 u[k-d]
    Γ0 = ∫_0^{Ts-θ} e^{Aσ} dσ B,   Γ1 = e^{A(Ts-θ)} ∫_0^θ e^{Aσ} dσ B.

Output convention: the PV at sample k is the output at t_k = k*Ts *just
before* the new MV u[k] is applied, y[k] = C x[k] + D u[k-d-1]; for a
biproper process (D != 0) it therefore reflects the MV held over the
previous interval, as a real sampled measurement would.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from collections.abc import Sequence

import numpy as np
import scipy.linalg
import scipy.signal

from autotuner.engine.plant.process import Process

# A dead time within this fraction of a sample of a whole number of samples is
# taken as exactly that number (L/Ts carries rounding error, e.g. 0.3/0.1).
_GRID_TOL = 1e-9


def _realise(process: Process) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Balanced controllable-canonical realisation (A, B, C, D) of the rational part."""
    if process.order == 0:
        empty = np.zeros(0)
        return np.zeros((0, 0)), empty, empty, process.num[0]
    a, b, c, d = scipy.signal.tf2ss(process.num, process.den)
    # The companion matrix of a stiff process spans many decades; an exact
    # (power-of-two) diagonal similarity evens out its rows and columns, which
    # reduces rounding in expm.
    a, (scale, _) = scipy.linalg.matrix_balance(a, permute=False, separate=True)
    return a, b[:, 0] / scale, c[0] * scale, float(d[0, 0])


def _hold_integrals(a: np.ndarray, b: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """(e^{Aτ}, ∫_0^τ e^{Aσ}dσ B) from one exponential of the augmented matrix."""
    n = len(b)
    m = np.zeros((n + 1, n + 1))
    m[:n, :n] = a * tau
    m[:n, n] = b * tau
    e = scipy.linalg.expm(m)
    return e[:n, :n], e[:n, n]


@functools.lru_cache(maxsize=64)
def _discretise(process: Process, ts: float) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """(d, Φ, Γ0, Γ1, C, D) of the module docstring for sample time ``ts`` seconds, read-only arrays.

    Remembered per (process, ts): a plant of many loops of one process (drivers.modbus_plant) would otherwise
    take the matrix exponentials once per loop (they dominate its start, ~10 ms each on a busy machine).
    """
    samples = process.delay / ts
    d = round(samples)
    if abs(samples - d) > _GRID_TOL * max(1.0, samples):
        d = math.floor(samples)
    theta = max(0.0, process.delay - d * ts)
    a, b, c, dd = _realise(process)
    phi, _ = _hold_integrals(a, b, ts)
    e_late, g0 = _hold_integrals(a, b, ts - theta)
    g1 = e_late @ _hold_integrals(a, b, theta)[1]
    for array in (phi, g0, g1, c):
        array.setflags(write=False)  # shared by every PlantSim of (process, ts)
    return d, phi, g0, g1, c, dd


class PlantSim:
    """Simulated process in deviation form around an operating point: pv = pv0 + F*(mv - mv0 + load) + noise.

    ``ts`` is the sample time in seconds. The plant starts at rest at the
    operating point (state zero, MV history mv0). ``loads`` are (time in s,
    step size in MV units) load steps at the process input; each acts from
    the first sample instant at or after its time (a step between samples is
    rounded up to the sample grid). ``measure()`` adds seeded white noise of
    standard deviation ``noise_std`` (a fresh draw on every call) and then
    rounds to a multiple of ``quantum`` if it is > 0.

    ``process``: the process F; ``pv0``, ``mv0``: the operating point; ``seed``: of the noise (None: fresh);
    ``mv_limits``: the MV's (low, high), MV units, where ``advance`` clips it; ``drift``: a load ramp at the process
    input, MV units per s.
    """

    def __init__(self, process: Process, ts: float, *, pv0: float = 0.0, mv0: float = 0.0,
                 noise_std: float = 0.0, seed: int | None = None, quantum: float = 0.0,
                 mv_limits: tuple[float, float] = (-math.inf, math.inf),
                 loads: Sequence[tuple[float, float]] = (), drift: float = 0.0) -> None:
        if not (math.isfinite(ts) and ts > 0):
            raise ValueError(f"sample time must be a positive number of seconds, got {ts}")
        if not (math.isfinite(noise_std) and noise_std >= 0):
            raise ValueError(f"noise_std must be finite and >= 0, got {noise_std}")
        if not (math.isfinite(quantum) and quantum >= 0):
            raise ValueError(f"quantum must be finite and >= 0, got {quantum}")
        lo, hi = mv_limits
        if not lo <= hi:
            raise ValueError(f"mv_limits must satisfy low <= high, got {mv_limits}")
        if not math.isfinite(drift):
            raise ValueError(f"drift must be a finite number of MV units per second, got {drift}")
        if not (math.isfinite(pv0) and math.isfinite(mv0)):
            raise ValueError("pv0 and mv0 must be finite")
        self.process = process
        self.ts = float(ts)
        self.pv0, self.mv0 = float(pv0), float(mv0)
        self.noise_std, self.quantum = float(noise_std), float(quantum)
        self.mv_limits = (float(lo), float(hi))
        self._rng = np.random.default_rng(seed)

        d, self._phi, self._g0, self._g1, self._c, self._d = _discretise(process, self.ts)
        self._x = np.zeros(len(self._g0))
        # u[k-d-1] ... u[k-1] in deviation units; advance() appends u[k].
        self._u: deque[float] = deque([0.0] * (d + 1))

        steps: dict[int, float] = {}
        for time, size in loads:
            if not (math.isfinite(time) and math.isfinite(size)):
                raise ValueError(f"load step ({time}, {size}) must be finite")
            k = max(0, math.ceil(time / ts - _GRID_TOL))
            steps[k] = steps.get(k, 0.0) + size
        self._load_steps = sorted(steps.items(), reverse=True)  # next step last
        self._load = 0.0
        self.drift = float(drift)
        self._k = 0

    @property
    def t(self) -> float:
        """Current plant time in seconds (k * ts; starts at 0)."""
        return self._k * self.ts

    def true_pv(self) -> float:
        """PV at time t without noise or quantisation."""
        return self.pv0 + float(self._c @ self._x) + self._d * self._u[0]

    def measure(self) -> float:
        """PV at time t as a sensor reads it: plus noise, then quantised."""
        pv = self.true_pv()
        if self.noise_std:
            pv += self.noise_std * self._rng.standard_normal()
        if self.quantum:
            pv = math.floor(pv / self.quantum + 0.5) * self.quantum
        return pv

    def step_load(self, size: float) -> None:
        """A load step of ``size`` MV units at the process input from now on (from the next :meth:`advance`)."""
        if not math.isfinite(size):
            raise ValueError(f"load step must be a finite number of MV units, got {size}")
        self._load += float(size)

    def advance(self, mv: float) -> float:
        """Hold mv over [t, t+ts) and advance t by ts; returns the MV applied after clipping.

        Raises ValueError for a non-finite mv.

        ``mv``: MV units.
        """
        if not math.isfinite(mv):
            raise ValueError(f"manipulated variable must be finite, got {mv}")
        applied = min(max(float(mv), self.mv_limits[0]), self.mv_limits[1])
        while self._load_steps and self._load_steps[-1][0] <= self._k:
            self._load += self._load_steps.pop()[1]
        u = self._u
        u.append(applied - self.mv0 + self._load + self.drift * self.t)
        self._x = self._phi @ self._x + self._g1 * u[0] + self._g0 * u[1]
        u.popleft()
        self._k += 1
        return applied


def simulate_open_loop(process: Process, u: np.ndarray, ts: float) -> np.ndarray:
    """Response to the MV sequence u held over successive intervals of ts seconds.

    Returns y with len(u) + 1 samples: y[k] is the output at t = k*ts just
    before u[k] is applied (y[0] = 0: the process starts at rest).

    ``process``: the process; ``u``: the MV sequence (deviations); ``ts``: s.
    """
    sim = PlantSim(process, ts)
    y = np.empty(len(u) + 1)
    for k, mv in enumerate(np.asarray(u, dtype=float)):
        y[k] = sim.true_pv()
        sim.advance(mv)
    y[-1] = sim.true_pv()
    return y
