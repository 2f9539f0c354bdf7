"""The classical tuning rules of methods.md §4 as plain functions, and a registry of them.

Every rule takes the :class:`autotuner.engine.design.process_data.ProcessData` of one process,
the controller type and the :class:`Options`, and returns a :class:`RuleResult`
in the standard (ISA) form ``K[bW − Y + E/(Ti s) + Td s/(Td s/N + 1)(cW − Y)]``
(``c = 0``, ``N = 10`` unless the rule says otherwise), plus its native form
where it has one. A rule asked for something it does not define raises
:class:`RuleError` with the reason; it never returns numbers then.

Times are in seconds, gains in MV units per PV unit. Sources per rule are in
``RULES`` and in docs/rules.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import minimize

from autotuner.engine.design.closed_loop import integrated_error, margins, reference_period
from autotuner.engine.design.point_design import DEFAULT_ND, design
from autotuner.engine.control.gains import Gains, forms_json
from autotuner.engine.design.process_data import Fopdt, ProcessData, Tangent
from autotuner.engine.design.direct_synthesis import SynthesisError, design_unstable

# itae-optimal: simulation samples per T135 and horizon in T135; Ms penalty weight;
# accepted excess of Ms over the limit (the penalty is soft).
OPT_SAMPLES = 20
OPT_PERIODS = 12.0
PENALTY = 1e4
MS_SLACK = 1.02


class RuleError(ValueError):
    """A rule cannot tune this process or this controller type; the message says why."""


@dataclass(frozen=True)
class Options:
    """Rule parameters.

    ts: sample time, s (takahashi). ms: maximum sensitivity target (None: the
    rule's default). rb, phib_deg: the Nyquist point ``r_b·e^{j(−π+φ_b)}``
    of the Åström–Hägglund relay rule. step: "load" or "setpoint", the step
    whose ITAE itae-optimal minimises.
    """

    ts: float | None = None
    ms: float | None = None
    rb: float = 0.5
    phib_deg: float = 45.0
    step: str = "load"


@dataclass(frozen=True)
class RuleResult:
    """Result of a rule: standard-form gains and JSON-ready extras (native forms, data used).

    rule: the rule's name; controller: the controller type; gains: standard form; extra: the JSON-ready extras.
    """

    rule: str
    controller: str
    gains: Gains
    extra: dict[str, Any] = field(default_factory=dict)

    def as_json(self) -> dict[str, Any]:
        """The JSON of ``autotuner design --rule``: rule, controller, standard-form gains, series and parallel
        forms (:func:`~autotuner.engine.control.gains.forms_json`), then the rule's extras."""
        return {"rule": self.rule, "controller": self.controller, "gains": self.gains.as_json(),
                **forms_json(self.gains), **self.extra}


# -- what a rule needs ----------------------------------------------------------


def _stable(data: ProcessData, rule: str) -> None:
    if data.unstable:
        raise RuleError(f"{rule} is not defined for an unstable process (use direct-synthesis-unstable)")


def _model_needed(data: ProcessData, rule: str) -> None:
    if data.process is None:
        raise RuleError(f"{rule} needs a process model: a point alone is not enough, give --static-gain "
                        "with --point (or use --fopdt / --plant)")


def _fopdt(data: ProcessData, rule: str) -> Fopdt:
    """The FOPDT model of a self-regulating process with dead time."""
    _model_needed(data, rule)
    _stable(data, rule)
    if data.integrating:
        raise RuleError(f"{rule} is defined for self-regulating processes only; this one is integrating")
    if data.fopdt is None or data.fopdt.l <= 0.0:
        raise RuleError(f"{rule} needs a process with dead time (L > 0)")
    return data.fopdt


def _tangent(data: ProcessData, rule: str) -> Tangent:
    _model_needed(data, rule)
    _stable(data, rule)
    if data.tangent is None:
        raise RuleError(f"{rule} needs the step-response tangent, which this process does not have")
    return data.tangent


def _point(data: ProcessData, rule: str, lag_deg: float):
    _stable(data, rule)
    point = data.phase_point(lag_deg)
    if point is None:
        if data.source == "point":
            raise RuleError(f"{rule} needs the point with {lag_deg:g}° phase lag; the point given lags by "
                            f"{-data.point.phase_deg:.1f}°")
        raise RuleError(f"{rule} needs the point with {lag_deg:g}° phase lag, and this process never lags that much")
    return point


def _gains(k: float, ti: float = math.inf, td: float = 0.0, b: float = 1.0) -> Gains:
    return Gains(k=k, ti=ti, td=td, nd=DEFAULT_ND, b=b, c=0.0)


def _table(controller: str, p: tuple, pi: tuple, pid: tuple) -> Gains:
    """Pick the (k, ti, td) row of a P/PI/PID table."""
    return _gains(*{"P": p, "PI": pi, "PID": pid}[controller])


# -- the rules ------------------------------------------------------------------


def zn_step(data: ProcessData, controller: str, options: Options) -> RuleResult:
    """Ziegler–Nichols step response (methods.md §4.1): a = R·D; K = 1/a, 0.9/a, 1.2/a; Ti = 3D, 2D; Td = D/2.

    ``data``: the process data; ``controller``: the controller type; ``options``: the rules' options.
    """
    tan = _tangent(data, "zn-step")
    a, d = tan.a, tan.d
    gains = _table(controller, (1.0 / a,), (0.9 / a, 3.0 * d), (1.2 / a, 2.0 * d, 0.5 * d))
    return RuleResult("zn-step", controller, gains, {"data": {"D": d, "R": tan.r, "a": a}})


# (a0, a1, a2) of f(τ) = a0·exp(a1 τ + a2 τ²), methods.md §4.2
KAPPA_TAU = {
    "PI": {"aK": (0.29, -2.7, 3.7), "Ti/D": (8.9, -6.6, 3.0), "Ti/T": (0.79, -1.4, 2.4), "b": (0.81, 0.73, 1.9)},
    "PID": {"aK": (3.8, -8.4, 7.3), "Ti/D": (5.2, -2.5, -1.4), "Ti/T": (0.46, 2.8, -2.1),
            "Td/D": (0.89, -0.37, -4.1), "Td/T": (0.077, 5.0, -4.8), "b": (0.40, 0.18, 2.8)},
}


def _f(coeffs: tuple[float, float, float], tau: float) -> float:
    a0, a1, a2 = coeffs
    return a0 * math.exp(a1 * tau + a2 * tau * tau)


def kappa_tau(data: ProcessData, controller: str, options: Options) -> RuleResult:
    """Åström–Hägglund modified step response (methods.md §4.2) from ``a = R·D``, ``D`` and ``T = t63 − D``.

    ``τ = D/(D + T)`` (0 for an integrating process). Ti and Td use the rows
    normalised by D for τ ≤ 0.5 and by T above, where each fit is the better
    conditioned one.

    ``data``: the process data; ``controller``: the controller type; ``options``: the rules' options.
    """
    tan = _tangent(data, "kappa-tau")
    lag = None if tan.t63 is None else tan.t63 - tan.d
    tau = 0.0 if lag is None else tan.d / (tan.d + lag)
    row = KAPPA_TAU[controller]
    by_d = tau <= 0.5
    ti = _f(row["Ti/D"], tau) * tan.d if by_d else _f(row["Ti/T"], tau) * lag
    td = 0.0
    if controller == "PID":
        td = _f(row["Td/D"], tau) * tan.d if by_d else _f(row["Td/T"], tau) * lag
    gains = _gains(_f(row["aK"], tau) / tan.a, ti, td, _f(row["b"], tau))
    return RuleResult("kappa-tau", controller, gains, {"data": {"D": tan.d, "T": lag, "a": tan.a, "tau": tau}})


def _ultimate(data: ProcessData, rule: str) -> tuple[float, float]:
    """Critical gain Kc and period T180 (s)."""
    point = _point(data, rule, 180.0)
    return 1.0 / point.gain, 2.0 * math.pi / point.omega


def zn_frequency(data: ProcessData, controller: str, options: Options) -> RuleResult:
    """Ziegler–Nichols frequency response (methods.md §4.3): 0.5Kc; 0.45Kc, T180/1.2; 0.6Kc, T180/2, T180/8.

    ``data``: the process data; ``controller``: the controller type; ``options``: the rules' options.
    """
    kc, tu = _ultimate(data, "zn-frequency")
    gains = _table(controller, (0.5 * kc,), (0.45 * kc, tu / 1.2), (0.6 * kc, tu / 2.0, tu / 8.0))
    return RuleResult("zn-frequency", controller, gains, {"data": {"Kc": kc, "T180": tu}})


def astrom_hagglund(data: ProcessData, controller: str, options: Options) -> RuleResult:
    """Relay rule with a prescribed Nyquist point (methods.md §4.4); PI is the same K, Ti without Td.

    ``data``: the process data; ``controller``: the controller type; ``options``: the rules' options.
    """
    if not (0.0 < options.rb < 1.0 and 0.0 < options.phib_deg < 90.0):
        raise RuleError(f"astrom-hagglund needs 0 < r_b < 1 and 0° < φ_b < 90°, got r_b = {options.rb:g}, "
                        f"φ_b = {options.phib_deg:g}°")
    kc, tu = _ultimate(data, "astrom-hagglund")
    phi = math.radians(options.phib_deg)
    ti = tu / math.pi * (1.0 + math.sin(phi)) / math.cos(phi)
    gains = _gains(kc * options.rb * math.cos(phi), ti, ti / 4.0 if controller == "PID" else 0.0)
    return RuleResult("astrom-hagglund", controller, gains,
                  {"data": {"Kc": kc, "T180": tu, "rb": options.rb, "phib_deg": options.phib_deg}})


def chr_regulation(data: ProcessData, controller: str, options: Options) -> RuleResult:
    """Chien–Hrones–Reswick, load disturbance, 20 % overshoot (methods.md §4.5).

    ``data``: the process data; ``controller``: the controller type; ``options``: the rules' options.
    """
    m = _fopdt(data, "chr-regulation")
    g = m.t / (m.k * m.l)
    gains = _table(controller, (0.7 * g,), (0.7 * g, 2.3 * m.l), (1.2 * g, 2.0 * m.l, 0.42 * m.l))
    return RuleResult("chr-regulation", controller, gains, {"data": _fopdt_json(m)})


def chr_servo(data: ProcessData, controller: str, options: Options) -> RuleResult:
    """Chien–Hrones–Reswick, set point, 20 % overshoot (methods.md §4.5).

    ``data``: the process data; ``controller``: the controller type; ``options``: the rules' options.
    """
    m = _fopdt(data, "chr-servo")
    g = m.t / (m.k * m.l)
    gains = _table(controller, (0.7 * g,), (0.6 * g, m.t), (0.95 * g, 1.36 * m.t, 0.47 * m.l))
    return RuleResult("chr-servo", controller, gains, {"data": _fopdt_json(m)})


def cohen_coon(data: ProcessData, controller: str, options: Options) -> RuleResult:
    """Cohen–Coon, quarter decay ratio (methods.md §4.6).

    ``data``: the process data; ``controller``: the controller type; ``options``: the rules' options.
    """
    m = _fopdt(data, "cohen-coon")
    r, g = m.l / m.t, m.t / (m.k * m.l)
    gains = _table(
        controller,
        (g * (1.0 + r / 3.0),),
        (g * (0.9 + r / 12.0), m.l * (30.0 + 3.0 * r) / (9.0 + 20.0 * r)),
        (g * (4.0 / 3.0 + r / 4.0), m.l * (32.0 + 6.0 * r) / (13.0 + 8.0 * r), 4.0 * m.l / (11.0 + 2.0 * r)),
    )
    return RuleResult("cohen-coon", controller, gains, {"data": _fopdt_json(m)})


def takahashi(data: ProcessData, controller: str, options: Options) -> RuleResult:
    """Takahashi discrete PI/PID from the reaction curve (methods.md §4.7), ``τ/Km = 1/R``, ``L = D``.

    Native form: velocity form ``Δu(k) = K Δe + Ki e + Kd Δ²e`` with sample
    time ``ts``; the standard form has ``Ti = K·ts/Ki``, ``Td = Kd·ts/K``.

    ``data``: the process data; ``controller``: the controller type; ``options``: the rules' options.
    """
    if options.ts is None or not (math.isfinite(options.ts) and options.ts > 0.0):
        raise RuleError("takahashi is a discrete rule: give the sample time --ts (s, > 0)")
    tan = _tangent(data, "takahashi")
    ts, l, inv = options.ts, tan.d, 1.0 / tan.r  # inv = τ/Km
    half = (l + ts / 2.0) ** 2
    if controller == "PI":
        k = 0.9 * inv / (l + ts / 2.0) - 0.135 * inv * ts / half
        ki, kd = 0.27 * inv * ts / half, 0.0
    else:
        k = 1.2 * inv / (l + ts) - 0.3 * inv * ts / half
        ki, kd = 0.6 * inv * ts / half, 0.5 * inv / ts
    gains = _gains(k, k * ts / ki, kd * ts / k)
    return RuleResult("takahashi", controller, gains,
                  {"discrete": {"k": k, "ki": ki, "kd": kd, "ts": ts}, "data": {"D": l, "R": tan.r}})


def amigo(data: ProcessData, controller: str, options: Options) -> RuleResult:
    """AMIGO (Åström–Hägglund, Advanced PID Control 2006, §7) from K, L (tangent) and T = t63 − L.

    Integrating process ``Kv·e^{−Ls}/s``: PI ``K = 0.35/(Kv L)``, ``Ti = 13.4 L``;
    PID ``K = 0.45/(Kv L)``, ``Ti = 8 L``, ``Td = 0.5 L``. Set-point weight
    ``b = 0`` for ``τ ≤ 0.5``, 1 above.

    ``data``: the process data; ``controller``: the controller type; ``options``: the rules' options.
    """
    tan = _tangent(data, "amigo")
    l = tan.d
    if data.integrating:
        kv = tan.r
        k, ti, td = (0.35 / (kv * l), 13.4 * l, 0.0) if controller == "PI" else (0.45 / (kv * l), 8.0 * l, 0.5 * l)
        return RuleResult("amigo", controller, _gains(k, ti, td, 0.0), {"data": {"Kv": kv, "L": l, "tau": 0.0}})
    k0, t = data.static_gain, tan.t63 - l
    tau = l / (l + t)
    if controller == "PI":
        k = 0.15 / k0 + (0.35 - l * t / (l + t) ** 2) * t / (k0 * l)
        ti, td = 0.35 * l + 13.0 * l * t * t / (t * t + 12.0 * l * t + 7.0 * l * l), 0.0
    else:
        k = (0.2 + 0.45 * t / l) / k0
        ti, td = (0.4 * l + 0.8 * t) / (l + 0.1 * t) * l, 0.5 * l * t / (0.3 * l + t)
    return RuleResult("amigo", controller, _gains(k, ti, td, 0.0 if tau <= 0.5 else 1.0),
                  {"data": {"K": k0, "L": l, "T": t, "tau": tau}})


# ITAE set-point rule (Rovira, Murrill & Smith 1969, as tabulated by Seborg et al.):
# K·Km = A (θ/T)^B, T/Ti = A + B·θ/T, Td/T = A (θ/T)^B.
ITAE_SETPOINT = {"PI": {"K": (0.586, -0.916), "I": (1.03, -0.165)},
                 "PID": {"K": (0.965, -0.85), "I": (0.796, -0.1465), "D": (0.308, 0.929)}}


def itae_integral(data: ProcessData, controller: str, options: Options) -> RuleResult:
    """ITAE rule from the integral-controller experiment (methods.md §4.8).

    The critical integral gain ``ki,kr = ω90/|F(jω90)|`` and ``ω_osc = ω90``
    (an integral controller oscillates where the process lags 90°) and the
    static gain ``k`` give ``T = sqrt((ki,kr·k)² − ω²)/ω²`` and
    ``θ0 = (π/2 − atan Ω)/Ω``, ``Ω = ωT``: the FOPDT ``k·e^{−θ0 T s}/(Ts + 1)``
    through the 90° point. The gains are the ITAE-optimal set-point settings
    of ``ITAE_SETPOINT`` at ``θ/T = θ0``.

    ``data``: the process data; ``controller``: the controller type; ``options``: the rules' options.
    """
    _model_needed(data, "itae-integral")
    _stable(data, "itae-integral")
    if data.integrating:
        raise RuleError("itae-integral is defined for self-regulating processes only; this one is integrating")
    point = _point(data, "itae-integral", 90.0)
    k, w = data.static_gain, point.omega
    kikr = w / point.gain
    if abs(kikr * k) <= w:
        raise RuleError("itae-integral: the 90° point is not below the static gain; no lag fits")
    t = math.sqrt((kikr * k) ** 2 - w * w) / (w * w)
    big = w * t
    theta0 = (math.pi / 2.0 - math.atan(big)) / big
    if theta0 <= 0.0:
        raise RuleError("itae-integral needs dead time (θ0 > 0)")
    row = ITAE_SETPOINT[controller]
    kc = row["K"][0] * theta0 ** row["K"][1] / k
    ti = t / (row["I"][0] + row["I"][1] * theta0)
    td = row["D"][0] * theta0 ** row["D"][1] * t if controller == "PID" else 0.0
    return RuleResult("itae-integral", controller, _gains(kc, ti, td),
                  {"data": {"ki_kr": kikr, "omega_osc": w, "K": k, "T": t, "theta0": theta0}})


def _penalised_itae(data: ProcessData, step: str, period: float, ms_max: float,
                    w_ref: float) -> Callable[[np.ndarray], float]:
    """Cost of log-parameters (ln k, ln ti[, ln td]): simulated ITAE, times a quadratic penalty above ms_max."""

    def cost(x: np.ndarray) -> float:
        if np.any(np.abs(x) > 50.0):
            return 1e12
        gains = _gains(*np.exp(x), b=1.0)
        ms = margins(data.process, gains, w_ref).ms
        if not math.isfinite(ms):
            return 1e12
        itae = integrated_error(data.process, gains, step, period, OPT_SAMPLES, OPT_PERIODS)[1]
        return itae * (1.0 + PENALTY * max(0.0, ms - ms_max) ** 2)

    return cost


def itae_optimal(data: ProcessData, controller: str, options: Options) -> RuleResult:
    """Minimise the simulated ITAE of a unit load (or set-point) step subject to ``Ms ≤ ms`` (methods.md §4.9).

    Starts from Ziegler–Nichols step-response settings (or AMIGO's where ZN
    is unstable); parameters are optimised in logarithms; Nelder–Mead for
    PI, BFGS with numerical gradients for PID; the Ms constraint is a
    quadratic penalty (``ITAE·(1 + PENALTY·(Ms − ms)²)``, so the optimum may
    exceed the limit by about 1 %). The simulation runs at ``T135/OPT_SAMPLES``
    over ``OPT_PERIODS·T135``.

    ``data``: the process data; ``controller``: the controller type; ``options``: the rules' options.
    """
    _model_needed(data, "itae-optimal")
    _stable(data, "itae-optimal")
    ms_max = options.ms or 1.4
    period = reference_period(data.process)
    w_ref = 2.0 * math.pi / period
    cost = _penalised_itae(data, options.step, period, ms_max, w_ref)
    starts = [zn_step(data, controller, options).gains, amigo(data, controller, options).gains]
    x0s = [np.log([g.k, g.ti] + ([g.td] if controller == "PID" else [])) for g in starts]
    scale, x0 = min(((cost(x), x) for x in x0s), key=lambda pair: pair[0])  # the optimisers start at about 1

    def relative(x: np.ndarray) -> float:
        return cost(x) / scale

    if controller == "PI":
        res = minimize(relative, x0, method="Nelder-Mead", options={"xatol": 1e-3, "fatol": 1e-4, "maxfev": 300})
    else:
        res = minimize(relative, x0, method="BFGS", options={"eps": 1e-3, "gtol": 1e-2, "maxiter": 15})
    gains = _gains(*np.exp(res.x))
    ms = margins(data.process, gains, w_ref).ms
    if ms > ms_max * MS_SLACK:
        raise RuleError(f"itae-optimal found no controller with Ms ≤ {ms_max:g} (best Ms {ms:.3g})")
    method = "Nelder-Mead" if controller == "PI" else "BFGS"
    return RuleResult("itae-optimal", controller, gains, {"optimisation": {
        "method": method, "step": options.step, "iterations": int(res.nit), "evaluations": int(res.nfev),
        "itae": float(res.fun * scale), "ms": ms, "ms_max": ms_max}})


def direct_synthesis_unstable(data: ProcessData, controller: str, options: Options) -> RuleResult:
    """Two-controller direct synthesis for unstable processes with dead time (methods.md §4.10).

    ``gains`` is the load controller C2 (the one in feedback with the
    process) in standard form; ``two_controller`` holds both parallel PIDs
    and the set-point filter.

    ``data``: the process data; ``controller``: the controller type; ``options``: the rules' options.
    """
    if not data.unstable:
        raise RuleError("direct-synthesis-unstable is for unstable processes K·e^(−θs)/∏(s/h − 1); "
                        "this one is stable")
    try:
        des = design_unstable(data.process, options.ms or 3.0)
    except SynthesisError as exc:
        raise RuleError(f"direct-synthesis-unstable: {exc}") from None
    c2 = des.load
    if c2.kp <= 0.0 or c2.ki <= 0.0 or c2.kd < 0.0:
        raise RuleError("direct-synthesis-unstable: the load controller has no standard form "
                        f"(kp = {c2.kp:.4g}, ki = {c2.ki:.4g}, kd = {c2.kd:.4g})")
    gains = _gains(c2.kp, c2.kp / c2.ki, c2.kd / c2.kp)
    return RuleResult("direct-synthesis-unstable", controller, gains, {"two_controller": {
        "setpoint_controller": des.setpoint.as_json(), "load_controller": c2.as_json(),
        "setpoint_filter": {"num": list(des.filter_num), "den": list(des.filter_den)},
        "lambda": des.lam, "q": des.q, "ms": des.ms, "match_omegas": list(des.omegas)}})


def robust(data: ProcessData, controller: str, options: Options) -> RuleResult:
    """The project's robust one-point rule (docs/design-rule.md) from the 135° point and the static gain.

    ``data``: the process data; ``controller``: the controller type; ``options``: the rules' options.
    """
    _stable(data, "robust")
    if data.static_gain is None:
        raise RuleError("robust needs the static gain: give --static-gain with --point")
    point = data.point if data.source == "point" else _point(data, "robust", 135.0)
    try:
        des = design(point, data.static_gain, controller, options.ms or 1.4)
    except ValueError as exc:
        raise RuleError(f"robust: {exc}") from None
    return RuleResult("robust", controller, des.gains,
                  {"data": {"omega": point.omega, "gain": point.gain, "phase_deg": point.phase_deg,
                            "model": str(des.model), "model_ms": des.model_ms}})


def _fopdt_json(m: Fopdt) -> dict[str, float]:
    return {"K": m.k, "T": m.t, "L": m.l}


# -- registry -------------------------------------------------------------------


@dataclass(frozen=True)
class Rule:
    """A registered rule: name, the controller types it defines, one line on when to use it, its source.

    name: its name (``--rule``); controllers: the controller types it defines; when: one line on when to use it;
    source: where it comes from; func: the rule itself.
    """

    name: str
    controllers: tuple[str, ...]
    when: str
    source: str
    func: Callable[[ProcessData, str, Options], RuleResult]


_PPI = ("P", "PI", "PID")
RULES: dict[str, Rule] = {r.name: r for r in (
    Rule("zn-step", _PPI, "first guess from a step test (tangent D, R); aggressive, may destabilise",
         "Ziegler & Nichols 1942", zn_step),
    Rule("kappa-tau", ("PI", "PID"), "robust (Ms ≈ 1.4) step-response rule for stable or integrating "
         "processes, with set-point weight b", "Åström & Hägglund 1995, PID Controllers (kappa–tau)", kappa_tau),
    Rule("zn-frequency", _PPI, "first guess from the ultimate point (relay at 180°); aggressive",
         "Ziegler & Nichols 1942", zn_frequency),
    Rule("astrom-hagglund", ("PI", "PID"), "relay autotuner classic: move the ultimate point to "
         "r_b·e^{j(−π+φ_b)}", "Åström & Hägglund 1984", astrom_hagglund),
    Rule("chr-regulation", _PPI, "FOPDT, load disturbance rejection, 20 % overshoot",
         "Chien, Hrones & Reswick 1952", chr_regulation),
    Rule("chr-servo", _PPI, "FOPDT, set-point following, 20 % overshoot", "Chien, Hrones & Reswick 1952",
         chr_servo),
    Rule("cohen-coon", _PPI, "FOPDT with fairly long dead time, quarter decay (oscillatory)",
         "Cohen & Coon 1953", cohen_coon),
    Rule("takahashi", ("PI", "PID"), "digital controller with a long sample time (--ts), from a step test",
         "Takahashi 1970 (methods.md §4.7)", takahashi),
    Rule("amigo", ("PI", "PID"), "robust default for stable or integrating processes from a step test",
         "Åström & Hägglund 2004/2006 (AMIGO)", amigo),
    Rule("itae-integral", ("PI", "PID"), "stable process tested with a pure integral controller "
         "(90° point); ITAE set-point response", "methods.md §4.8; ITAE settings: Rovira et al. 1969", itae_integral),
    Rule("itae-optimal", ("PI", "PID"), "a model is known: minimise simulated ITAE with an Ms limit (slow)",
         "methods.md §4.9", itae_optimal),
    Rule("direct-synthesis-unstable", ("PID",), "unstable process with dead time: two controllers and a "
         "set-point filter", "methods.md §4.10 (Anwar & Pan 2015 structure)", direct_synthesis_unstable),
    Rule("robust", ("PI", "PID"), "this project's rule: largest integral gain at Ms from one point + "
         "static gain", "docs/design-rule.md", robust),
)}


def default_controller(rule: Rule) -> str:
    """PI where the rule defines it, else its first controller type.

    ``rule``: the rule.
    """
    return "PI" if "PI" in rule.controllers else rule.controllers[0]


def tune(name: str, data: ProcessData, controller: str | None = None, options: Options = Options()) -> RuleResult:
    """Run the rule ``name``; RuleError for an unknown rule or a controller type it does not define.

    ``data``: the process data; ``controller``: ``"P"``, ``"PI"`` or ``"PID"`` (None: :func:`default_controller`);
    ``options``: the rules' options.
    """
    rule = RULES.get(name)
    if rule is None:
        raise RuleError(f"unknown rule {name!r}; the rules are: {', '.join(RULES)}")
    controller = controller or default_controller(rule)
    if controller not in rule.controllers:
        raise RuleError(f"{name} defines {', '.join(rule.controllers)} controllers, not {controller}")
    return rule.func(data, controller, options)
