"""Robust PI/PID gains from one frequency-response point and the static gain.

The static gain ``K0`` and the point ``F(jω*) = r·e^{−jφ}`` fix a
three-parameter model exactly: first order plus dead time
``K0·e^{−Ls}/(Ts + 1)`` with ``T = sqrt((K0/r)² − 1)/ω*`` and
``L = (φ − atan(ω*T))/ω*``, or, when the static gain is too large to tell from
an integrator, ``Kv·e^{−Ls}/s`` with ``Kv = r·ω*`` and ``L = (φ − π/2)/ω*``.
That model puts all the lag beyond the first-order one into dead time. The
same data are explained just as well by the other extreme, two lags and no
dead time (``K0/((T1 s + 1)(T2 s + 1))`` or ``Kv/(s(Ts + 1))``), and a real
process lies in between; designing for the first model alone overshoots the
Ms of lag-dominant higher-order processes by up to 10 %. So the gains are
those with the largest integral gain ``ki = k/ti`` for which the loop keeps
``Ms`` on the first model and ``1.05·Ms`` on the second (MIGO on both, see
:mod:`autotuner.engine.design.robustness`). PID fixes ``td`` as a fraction of ``ti``
(at most ¼, so a series form always exists) and takes the fraction with the
largest ``ki``; PI is the fraction 0, so PID never has less integral gain on
the model. The set-point weight ``b`` is the largest in [0, 1] whose
set-point response has no resonance peak on the model.

Beyond that batch (docs/design-notes.md):

* a gain at ω* clearly above the static gain (``|F(jω*)| > 1.1·K0``) is a
  resonance no lag explains; the family then also holds the underdamped second-order
  models through the point with no dead time and with the dead time that
  leaves 90° to the resonance (the lightly damped end and the other end);
* a negative static gain is an unstable process: the design of
  :mod:`autotuner.engine.design.unstable_design` (raised Ms target, or a
  refusal with its code);
* with measured noise, a PID whose high-frequency gain ``k(1 + N)`` would
  put more than :data:`MV_NOISE_BUDGET` × amp of noise (standard deviation)
  on the MV gets a lower ``N`` (down to :data:`ND_MIN`), and below that no
  derivative action.

Whatever the design had to give up is in ``Design.notes`` and its
``warning`` code (``ROBUSTNESS_MISSED``, ``DERIVATIVE_DROPPED``,
``DERIVATIVE_LIMITED``); a design with no notes met everything it was asked.

The derivation and its check on the benchmark batch are in docs/design-rule.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from autotuner.engine.described import described
from autotuner.engine.control.gains import Gains
from autotuner.engine.outcome import Code
from autotuner.engine.plant.process import Process
# A static gain INTEGRATING_RATIO times |F(jω*)| or more is designed as an integrator.
from autotuner.engine.experiment.identification import INTEGRATING_RATIO
from autotuner.engine.experiment.point import Point
from autotuner.engine.design import unstable_design
from autotuner.engine.design.robustness import (MigoResult, Plant, check_loop, log_grid, max_sensitivity, migo,
                                                pid_frequency_response)
from autotuner.engine.design.unstable_design import Refusal

# Ms allowance on the no-dead-time bound relative to the best-guess model:
# 1.0 holds every batch process under Ms·1.02 but costs up to 35 % of the
# integral gain on delay-dominant ones; 1.05 keeps Ms within 1.36–1.47.
BOUND_MARGIN = 1.05
TD_RATIOS = (0.0, 0.1, 0.15, 0.2, 0.25)
DEFAULT_ND = 10.0
# MV noise budget: the standard deviation of the MV noise the controller may make of the measured
# PV noise, as a fraction of the relay amplitude (the MV excursion the operator accepted for the test).
MV_NOISE_BUDGET = 0.1
# Lowest derivative filter factor N used to keep within that budget; below it the derivative goes.
ND_MIN = 2.0
# A gain at ω* this many times the static gain or more is a resonance; below, a gain at ω* near
# the static gain is a dead-time dominant process seen with a small error (the dead-time model).
RESONANCE_RATIO = 1.1
# Relative 2σ spread of the static gain from which its uncertainty enters the model family, and the
# largest spread considered (beyond, the estimate is no better than a guess within ±50 %).
STATIC_SPREAD_MIN = 0.05
STATIC_SPREAD_MAX = 0.5
# A static gain within this factor of |F(jω*)| cannot be told from a pure dead time (the experiment
# resolves |F|/K0 to about static_tol = 0.02): the first-order model's lag, sqrt((K0/r)² − 1)/ω*,
# is then hostage to the last digits of the estimate, and the dead-time model (no lag, so no
# high-frequency roll-off for a derivative to rely on) joins the family.
DEAD_TIME_RATIO = 1.03
# Relative slack on the Ms checks (the grid and the optimiser's tolerance).
_MS_SLACK = 1e-3


@dataclass(frozen=True)
class Design:
    """Gains with the model they were designed on, what they achieve there, and what was given up."""

    gains: Gains = described("the designed gains (standard form, times in seconds)")
    model: Process = described("the model the gains were designed on (plant seconds)")
    model_ms: float = described("maximum sensitivity Ms of the gains on model")
    bound: Process | None = described("the second extreme model of the family (None if none)")
    ms_target: float = described("the Ms the gains were designed for: the requested one, or raised for an "
                                 "unstable process", 1.4)
    family: tuple[Process, ...] = described("every model the design held to its target (model first)", ())
    noise_gain: float = described("MV noise per PV noise: the controller's high-frequency gain k (PI) or k(1 + N) "
                                  "(PID), MV units per PV unit", 0.0)
    notes: tuple[str, ...] = described("one sentence per target missed or action given up, empty when the design "
                                       "met everything asked", ())
    warning: Code = described("the outcome code for the notes (Code.OK when there are none)", Code.OK)


def fit_model(point: Point, static_gain: float) -> Process:
    """Three-parameter model through ``point`` with the given static gain (``inf``: integrating).

    Raises ValueError if the point does not lag by 90°–180° or the data are not finite.

    ``static_gain``: F(0), PV per MV unit.
    """
    w, r = point.omega, point.gain
    lag = -math.radians(point.phase_deg)
    if not (math.isfinite(w) and w > 0.0 and math.isfinite(r) and r > 0.0):
        raise ValueError(f"the point must have a positive finite frequency and gain, got ω={w}, |F|={r}")
    if not math.pi / 2 <= lag <= math.pi:
        raise ValueError(f"the point must lag by 90° to 180° for a PI(D) design, it lags by {math.degrees(lag):.1f}°")
    if math.isnan(static_gain) or static_gain <= 0.0:
        raise ValueError(
            f"the static gain must be positive (or inf for integrating), got {static_gain:.4g}: "
            "an unstable process, or a load change during the experiment"
        )
    if static_gain >= INTEGRATING_RATIO * r:
        kv = r * w
        return Process.from_tf((kv,), (1.0, 0.0), (lag - math.pi / 2) / w, text="IPDT model")
    if static_gain <= r:
        # No lag can explain a gain at ω* as large as the static gain: dead time only.
        return Process.from_tf((r,), (1.0,), lag / w, text="dead-time model")
    t = math.sqrt((static_gain / r) ** 2 - 1.0) / w
    return Process.from_tf((static_gain,), (t, 1.0), (lag - math.atan(w * t)) / w, text="FOPDT model")


def fit_lag_bound(point: Point, static_gain: float) -> Process | None:
    """The other extreme through the same data: two lags and no dead time (None if no lag can fit).

    With ``x = K0/r`` and the lag ``φ``, the lags ``a = ωT1``, ``b = ωT2`` satisfy
    ``a + b = x·sin φ`` and ``a·b = 1 + x·|cos φ|``; when they are not real the
    equal-lag model with the dead time that completes the phase is the bound.
    For an integrating process it is ``Kv/(s(Ts + 1))`` with ``atan(ωT) = φ − 90°``.

    ``point``: the identified point; ``static_gain``: F(0), PV per MV unit.
    """
    w, r = point.omega, point.gain
    lag = -math.radians(point.phase_deg)
    if static_gain >= INTEGRATING_RATIO * r:
        t = math.tan(lag - math.pi / 2) / w
        return Process.from_tf((r * w * math.hypot(1.0, w * t),), (t, 1.0, 0.0), 0.0, text="integrator + lag bound")
    x = static_gain / r
    if x <= 1.0:
        return None
    total, product = x * math.sin(lag), 1.0 + x * abs(math.cos(lag))
    disc = total * total - 4.0 * product
    if disc >= 0.0:
        return Process.from_tf((static_gain,), (product / w**2, total / w, 1.0), 0.0, text="two-lag bound")
    a = math.sqrt(x - 1.0)
    return Process.from_tf(
        (static_gain,), (a * a / w**2, 2.0 * a / w, 1.0), (lag - 2.0 * math.atan(a)) / w, text="equal-lag bound"
    )


def fit_resonant(point: Point, static_gain: float, delay: float) -> Process | None:
    """Underdamped ``K0·e^{−Ls}/(s²/ωn² + 2ζs/ωn + 1)`` through the point with dead time ``delay`` (s).

    With ``x = K0/r`` and the phase left to the rational part ``ψ = φ − ω*L``,
    ``K0/F = x·e^{jψ} = 1 − u² + j2ζu`` (``u = ω*/ωn``) gives ``u² = 1 − x·cos ψ``
    and ``ζ = x·sin ψ/(2u)``; None when no such model exists (``u² ≤ 0`` or ``ψ``
    outside (0, π)).

    ``point``: the identified point; ``static_gain``: F(0), PV per MV unit.
    """
    w, r = point.omega, point.gain
    psi = -math.radians(point.phase_deg) - w * delay
    x = static_gain / r
    u2 = 1.0 - x * math.cos(psi)
    if not (0.0 < psi < math.pi and u2 > 0.0):
        return None
    u = math.sqrt(u2)
    zeta = x * math.sin(psi) / (2.0 * u)
    wn = w / u
    return Process.from_tf((static_gain,), (1.0 / wn**2, 2.0 * zeta / wn, 1.0), delay,
                           text=f"resonant model (ζ = {zeta:.3g})")


def model_family(point: Point, static_gain: float, static_gain_std: float = math.inf) -> list[tuple[Process, float]]:
    """The models the stable design holds to its target, each with its Ms margin (best guess first).

    With a finite standard error of the static gain above :data:`STATIC_SPREAD_MIN` of it (a
    disturbed or noisy experiment), the first-order models through the point with the static gain
    ``2σ`` lower and higher join the family, so a static gain the experiment got wrong within its
    own error cannot cost the robustness. A static gain within :data:`DEAD_TIME_RATIO` of
    ``|F(jω*)|`` adds the dead-time model.

    ``point``: the identified point; ``static_gain``: F(0), PV per MV unit; ``static_gain_std``: its standard error.
    """
    model = fit_model(point, static_gain)
    bound = fit_lag_bound(point, static_gain)
    family = [(model, 1.0)] + ([] if bound is None else [(bound, BOUND_MARGIN)])
    if point.gain < static_gain < DEAD_TIME_RATIO * point.gain:
        family.append((fit_model(point, point.gain), 1.0))
    if math.isfinite(static_gain) and math.isfinite(static_gain_std):
        spread = min(2.0 * static_gain_std / static_gain, STATIC_SPREAD_MAX)
        if spread > STATIC_SPREAD_MIN:
            for gain in (max(static_gain * (1.0 - spread), 1.01 * point.gain), static_gain * (1.0 + spread)):
                if gain > point.gain:
                    family.append((fit_model(point, gain), 1.0))
    if math.isfinite(static_gain) and RESONANCE_RATIO * static_gain < point.gain:
        # A resonance: the lightly damped end (no dead time, the best guess: it reports the model)
        # and the dead time leaving 90° to it, then the dead-time model as the third extreme.
        lag = -math.radians(point.phase_deg)
        resonant = [fit_resonant(point, static_gain, delay)
                    for delay in (0.0, max(lag - math.pi / 2, 0.0) / point.omega)]
        family = [(m, 1.0) for m in resonant if m is not None] + family
    return family


def _plant(model: Process, margin: float = 1.0) -> Plant:
    return Plant(model.freqresp, integrators=model.integrator_count, rhp_poles=model.rhp_pole_count, margin=margin)


def noise_gain(gains: Gains) -> float:
    """MV noise per PV noise (MV units per PV unit): the high-frequency gain ``k`` or ``k(1 + N)`` with derivative.

    ``gains``: the controller.
    """
    return abs(gains.k) * (1.0 + gains.nd if gains.td > 0.0 else 1.0)


def setpoint_weight(model: Process, k: float, ti: float, td: float, nd: float, w: np.ndarray) -> float:
    """Largest ``b`` in [0, 1] with ``|G_yr(jω)| ≤ 1`` on the model (no set-point overshoot peak).

    When even ``b = 0`` peaks above 1 (high integral gain on a lag-dominant
    process: the integral path alone overshoots), 0 is returned, which gives
    the lowest peak available from ``b``.

    ``model``: the process model; ``k``, ``ti``, ``td``, ``nd``: the standard-form gains (``ti``, ``td`` in s);
    ``w``: the frequency grid (rad/s).
    """
    f = model.freqresp(w)
    loop = pid_frequency_response(w, k, ti, td, nd) * f
    s = 1j * w
    prop = k * f / (1.0 + loop)
    rest = (k / (ti * s)) * f / (1.0 + loop)
    lo, hi = 0.0, 1.0
    if np.max(np.abs(hi * prop + rest)) <= 1.0 + 1e-9:
        return 1.0
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        if np.max(np.abs(mid * prop + rest)) <= 1.0 + 1e-9:
            lo = mid
        else:
            hi = mid
    return math.floor(lo * 1000.0) / 1000.0  # rounding up could cross the limit


def _ms_on(model: Process, best: MigoResult, nd: float, w: np.ndarray) -> float:
    """Ms of the designed loop on ``model`` (inf if unstable)."""
    controller = lambda x: pid_frequency_response(x, best.k, best.ti, best.td, nd)  # noqa: E731
    integrators = model.integrator_count + (1 if math.isfinite(best.ti) else 0)
    return check_loop(model.freqresp, controller, w, integrators, model.rhp_pole_count).ms


def _stable_gains(family: list[tuple[Process, float]], omega: float, controller: str, ms: float, nd: float,
                  w: np.ndarray) -> MigoResult:
    plants = [_plant(m, margin) for m, margin in family]
    ratios = TD_RATIOS if controller == "PID" else (0.0,)
    return max((migo(plants, omega, ms, ratio, nd, w) for ratio in ratios), key=lambda m: m.ki)


def design(point: Point, static_gain: float, controller: str = "PI", ms: float = 1.4, nd: float = DEFAULT_ND,
           noise_std: float = 0.0, amp: float | None = None, static_gain_std: float = math.inf) -> Design:
    """Robust ``controller`` gains (``"PI"`` or ``"PID"``, standard form, derivative filter ``nd``) from the
    identified ``point`` and ``static_gain`` (F(0), PV per MV unit; inf: integrating; negative: unstable).

    ``ms`` is the required maximum sensitivity (1.2–2.0 is the usual range). ``noise_std`` (PV units) is the
    measured noise and ``amp`` (MV units) the relay amplitude: with both, a PID keeps its MV noise within
    ``MV_NOISE_BUDGET·amp``. ``static_gain_std`` (same unit as the static gain; inf: unknown) widens the model
    family (:func:`model_family`). Raises :class:`Refusal` (with an outcome code) for an unstable process no
    PI/PID of this kind stabilises robustly, ValueError for data no design applies to.
    """
    if controller not in ("PI", "PID"):
        raise ValueError(f"controller must be PI or PID, got {controller!r}")
    if not 1.05 <= ms <= 4.0:
        raise ValueError(f"Ms must be between 1.05 and 4, got {ms}")
    w = log_grid(point.omega)
    notes: list[tuple[Code, str]] = []
    if static_gain < 0.0 and -static_gain >= INTEGRATING_RATIO * point.gain:
        # An unstable pole this slow is an integrator at the experiment's frequencies (as in the relay).
        static_gain = math.inf
    if math.isfinite(static_gain) and static_gain < 0.0:
        fit_model(point, math.inf)  # the same checks of the point as the stable path
        lag = -math.radians(point.phase_deg)
        model = unstable_design.fit_unstable(point.omega, point.gain, lag, static_gain)
        ratio = unstable_design.check_dead_time(model, controller)
        family = [(model, 1.0)]
        best, target = unstable_design.design_gains(model, point.omega, controller, ms, nd)
        if target > ms * (1.0 + _MS_SLACK):
            notes.append((Code.ROBUSTNESS_MISSED, (
                f"Ms {ms:g} is out of reach of a {controller} on this unstable process (dead time {ratio:.2f} × the "
                f"unstable time constant): designed for Ms {target:.2f} on the model")))
    else:
        family = model_family(point, static_gain, static_gain_std)
        target = ms
        best = _stable_gains(family, point.omega, controller, ms, nd, w)
    model = family[0][0]
    if controller == "PID" and best.td > 0.0 and noise_std > 0.0 and amp is not None:
        best, nd, note = _within_noise_budget(best, family, point.omega, target, nd, noise_std, amp, w)
        if note is not None:
            notes.append(note)
    if controller == "PID" and best.td == 0.0 and not any(code is Code.DERIVATIVE_DROPPED for code, _ in notes):
        notes.append((Code.DERIVATIVE_DROPPED, (
            "PID was asked for, but derivative action adds no integral gain on the model "
            f"({model.text}: dead time dominates); the gains are PI")))
    for member, margin in family:
        member_ms = _ms_on(member, best, nd, w)
        if member_ms > target * margin * (1.0 + _MS_SLACK):
            notes.append((Code.ROBUSTNESS_MISSED, (
                f"Ms {member_ms:.3g} on the {member.text} exceeds the target {target * margin:.3g}")))
    b = setpoint_weight(model, best.k, best.ti, best.td, nd, w)
    gains = Gains(k=best.k, ti=best.ti, td=best.td, nd=nd, b=b, c=0.0)
    loop = pid_frequency_response(w, best.k, best.ti, best.td, nd) * model.freqresp(w)
    codes = [code for code, _ in notes]
    warning = max(codes, default=Code.OK)  # 19 robustness before 18 derivative before 15 filter
    bound = family[1][0] if len(family) > 1 else None
    return Design(gains=gains, model=model, model_ms=max_sensitivity(loop), bound=bound, ms_target=target,
                  family=tuple(m for m, _ in family), noise_gain=noise_gain(gains),
                  notes=tuple(text for _, text in notes), warning=warning)


def _within_noise_budget(best: MigoResult, family: list[tuple[Process, float]], omega: float, ms: float, nd: float,
                         noise_std: float, amp: float, w: np.ndarray) -> tuple[MigoResult, float, tuple[Code, str] | None]:
    """Lower ``N`` (and at last drop the derivative) until ``k(1 + N)·σ ≤ MV_NOISE_BUDGET·amp``.

    ``k`` changes with ``N``, so the design is redone for the lowered ``N``
    (twice: the second pass corrects for the new ``k``).
    """
    budget = MV_NOISE_BUDGET * amp
    if best.k * (1.0 + nd) * noise_std <= budget:
        return best, nd, None
    start = nd
    for _ in range(2):
        nd = min(nd, budget / (best.k * noise_std) - 1.0)
        if nd < ND_MIN:
            break
        best = max((migo([_plant(m, margin) for m, margin in family], omega, ms, r, nd, w) for r in TD_RATIOS[1:]),
                   key=lambda m: m.ki)
        if best.k <= 0.0:  # no PID with this slower filter meets the target on the family: the derivative goes
            nd = -math.inf
            break
    if nd >= ND_MIN and best.k * (1.0 + nd) * noise_std <= budget * (1.0 + 1e-6):
        return best, nd, (Code.DERIVATIVE_LIMITED, (
            f"derivative filter N lowered from {start:g} to {nd:.3g}: with the measured noise σ = {noise_std:.3g} "
            f"the MV noise stays within {MV_NOISE_BUDGET:g} × amp = {budget:.3g}"))
    pi = migo([_plant(m, margin) for m, margin in family], omega, ms, 0.0, start, w)
    if pi.k <= 0.0:
        raise ValueError(f"with the measured noise σ = {noise_std:.3g} no PID keeps the MV noise within "
                         f"{MV_NOISE_BUDGET:g} × amp = {budget:.3g}, and no PI meets Ms {ms:g} on the model family")
    return pi, start, (Code.DERIVATIVE_DROPPED, (
        f"PID was asked for, but with the measured noise σ = {noise_std:.3g} even N = {ND_MIN:g} would put "
        f"more than {MV_NOISE_BUDGET:g} × amp = {budget:.3g} of noise on the MV: derivative action dropped, "
        f"the gains are PI (MV noise {pi.k * noise_std:.3g})"))
