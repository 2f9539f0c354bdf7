"""Direct synthesis for unstable processes with dead time, two-controller structure (methods.md §4.10).

Process model ``M(s) = K·e^{−θs}/∏(s/h_i − 1)`` with p real unstable poles
``h_i > 0`` (1/s). ``C1`` closes the set-point loop around the model, ``C2``
closes the loop around the process against load disturbances, and the set
point passes a filter. With the exact controllers

* set point: ``Q_r = (Σ a_m s^m + 1)e^{−θs}/(λ s + 1)^{p+1}``, the ``a_m``
  solving ``Q_r(h_i) = 1`` (internal stability), ``C1 = Q_r/(M(1 − Q_r))``;
* load: the response ``y/d = M/(1 + M C2)`` is ``Q_d = s e^{−θs}/(Ki2(λ s + 1)^q)``
  with ``q = p + 1``, i.e. ``C2 = 1/Q_d − 1/M``;
* filter: ``(λ s + 1)^{p+1}/(Σ a_m s^m + 1)``.

Each controller is approximated by a parallel PID ``Kp + Ki/s + Kd s`` that
matches its frequency response at the two low frequencies
``ω0 = W0/(λ + θ)``, ``ω1 = W1/(λ + θ)``: for ``C1`` ``Kp`` is the mean of
the real parts and ``Ki, Kd`` solve the 2×2 system of the imaginary parts;
for ``C2`` the integral gain of the PID is the ``Ki2`` of ``Q_d``, so
``Kp + Ki2(1/(jω) − (λjω + 1)^q e^{jωθ}/(jω)) + Kd jω = −1/M(jω)`` is linear in
``(Kp, Ki2, Kd)``; its real and imaginary parts at ``ω0`` and imaginary part
at ``ω1`` give the 3×3 system. Both loops are checked with the Nyquist
criterion. ``λ`` (the same for both) is the smallest value on the falling side
of ``Ms(λ)`` (after its peak) with ``Ms`` of the process loop at most the
target (typically 2–5 for unstable processes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autotuner.engine.plant.process import Process
from autotuner.engine.design.robustness import closed_loop_stable, log_grid, max_sensitivity

W0, W1 = 0.01, 0.1
LAMBDA_GRID = np.logspace(math.log10(0.2), math.log10(20.0), 60)


class SynthesisError(ValueError):
    """The process is not of the form the method handles, or no λ meets the target."""


@dataclass(frozen=True)
class ParallelPid:
    """``kp + ki/s + kd·s``: kp (MV/PV), ki (MV/(PV·s)), kd (MV·s/PV)."""

    kp: float
    ki: float
    kd: float

    def freqresp(self, w: np.ndarray) -> np.ndarray:
        """``C(jw)`` of the controller at the frequencies ``w`` (rad/s)."""
        s = 1j * w
        return self.kp + self.ki / s + self.kd * s

    def as_json(self) -> dict[str, float]:
        return {"kp": self.kp, "ki": self.ki, "kd": self.kd}


@dataclass(frozen=True)
class TwoController:
    """The design: set-point controller, load controller, set-point filter (coefficients, highest power first).

    setpoint, load: the two PIDs; filter_num, filter_den: the set-point filter; lam: the closed-loop time constant λ
    (s); q: the order of its filter; ms: the process loop's Ms (inf if unstable); omegas: the frequencies (rad/s)
    the design was checked between.
    """

    setpoint: ParallelPid
    load: ParallelPid
    filter_num: tuple[float, ...]
    filter_den: tuple[float, ...]
    lam: float
    q: int
    ms: float
    omegas: tuple[float, float]


def unstable_poles(process: Process) -> np.ndarray:
    """The poles ``h_i`` (1/s) of a model ``K·e^{−θs}/∏(s/h_i − 1)``; raises SynthesisError otherwise.

    ``process``: the model.
    """
    poles = process.poles
    if len(process.num) != 1:
        raise SynthesisError("direct synthesis needs a model K·e^(−θs)/∏(s/h − 1) without zeros")
    if process.order == 0 or np.any(np.abs(poles.imag) > 1e-9 * np.abs(poles)) or np.any(poles.real <= 0):
        raise SynthesisError("direct synthesis needs a model K·e^(−θs)/∏(s/h − 1) whose poles are all "
                             "real and unstable (no stable or complex poles)")
    return np.sort(poles.real)


def _numerator(h: np.ndarray, lam: float, theta: float) -> np.ndarray:
    """``1 + Σ a_m s^m`` (highest power first) with ``Q_r(h_i) = 1``."""
    p = len(h)
    vander = np.array([[hi**m for m in range(1, p + 1)] for hi in h])
    rhs = (lam * h + 1.0) ** (p + 1) * np.exp(theta * h) - 1.0
    a = np.linalg.solve(vander, rhs)
    return np.concatenate([a[::-1], [1.0]])


def _setpoint_pid(model: Process, num: np.ndarray, lam: float, omegas: tuple[float, float]) -> ParallelPid:
    p1 = len(num)  # p + 1
    w = np.array(omegas)
    s = 1j * w
    q_r = np.polyval(num, s) * np.exp(-s * model.delay) / (lam * s + 1.0) ** p1
    c1 = q_r / (model.freqresp(w) * (1.0 - q_r))
    ki, kd = np.linalg.solve(np.array([[-1.0 / w[0], w[0]], [-1.0 / w[1], w[1]]]), c1.imag)
    return ParallelPid(float(np.mean(c1.real)), float(ki), float(kd))


def _load_pid(model: Process, lam: float, q: int, omegas: tuple[float, float]) -> ParallelPid:
    rows, rhs = [], []
    for i, w in enumerate(omegas):
        s = 1j * w
        coef_ki = 1.0 / s - (lam * s + 1.0) ** q * np.exp(s * model.delay) / s
        target = -1.0 / complex(model.freqresp(w))
        for part in (np.real, np.imag) if i == 0 else (np.imag,):
            rows.append([part(1.0 + 0j), part(coef_ki), part(s)])
            rhs.append(part(target))
    kp, ki, kd = np.linalg.solve(np.array(rows, dtype=float), np.array(rhs, dtype=float))
    return ParallelPid(float(kp), float(ki), float(kd))


def _loop_ms(model: Process, pid: ParallelPid, p: int, w: np.ndarray) -> float:
    """Ms of ``pid·model``, inf if the loop is unstable."""
    loop = pid.freqresp(w) * model.freqresp(w)
    return max_sensitivity(loop) if closed_loop_stable(loop, w, 1, p) else math.inf


def synthesise(model: Process, lam: float) -> TwoController:
    """Both PIDs and the filter for one ``λ`` (s); ``ms`` is that of the process loop (inf if unstable).

    ``model``: the unstable process; ``lam``: the closed-loop time constant λ (s).
    """
    h = unstable_poles(model)
    p = len(h)
    omegas = (W0 / (lam + model.delay), W1 / (lam + model.delay))
    num = _numerator(h, lam, model.delay)
    c1 = _setpoint_pid(model, num, lam, omegas)
    c2 = _load_pid(model, lam, p + 1, omegas)
    w = log_grid(1.0 / (lam + model.delay), 1e-4, 1e3, 4000)
    ms = _loop_ms(model, c2, p, w)
    if math.isfinite(ms) and not math.isfinite(_loop_ms(model, c1, p, w)):
        ms = math.inf  # the model loop of C1 must be stable too
    lag = np.poly(np.full(p + 1, -1.0 / lam)) * lam ** (p + 1)  # (λs + 1)^(p+1)
    return TwoController(c1, c2, tuple(float(c) for c in lag), tuple(float(c) for c in num), float(lam), p + 1, ms,
                         (float(omegas[0]), float(omegas[1])))


def design_unstable(model: Process, ms_target: float = 3.0) -> TwoController:
    """The design with the smallest ``λ`` after the peak of ``Ms(λ)`` whose Ms is at most ``ms_target``.

    ``λ`` runs over ``LAMBDA_GRID`` times θ (or the fastest unstable time
    constant ``1/h`` without dead time). Raises SynthesisError if no ``λ`` gives a
    stable loop within the target.

    ``model``: the unstable process (:func:`unstable_poles`).
    """
    h = unstable_poles(model)
    scale = model.delay if model.delay > 0 else 1.0 / float(np.max(h))
    designs = [synthesise(model, scale * x) for x in LAMBDA_GRID]
    ms = np.array([d.ms for d in designs])
    stable = np.isfinite(ms)
    if not np.any(stable):
        raise SynthesisError("no λ gives a stable loop: the dead time is too long for this method")
    peak = int(np.argmax(np.where(stable, ms, -np.inf)))
    for d in designs[peak:]:
        if d.ms <= ms_target:
            return d
    raise SynthesisError(f"no λ gives Ms ≤ {ms_target:g} (best {np.min(ms):.3g}); raise --ms")
