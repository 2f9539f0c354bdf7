"""What a session's gains will do, on the model the design was made on.

A successful session identifies one point ``F(jω*)`` and the static gain; the
design (:mod:`autotuner.engine.design.point_design`) fits a three-parameter model through them —
first order plus dead time ``K·e^{−Ls}/(Ts + 1)`` or, for an integrating
process, ``Kv·e^{−Ls}/s`` — and designs the gains on it. This module puts
gains on that model and reports, for the operator page:

* the maximum sensitivity ``Ms`` and the closed loop's stability (Nyquist,
  :func:`autotuner.engine.design.robustness.check_loop`);
* the Nyquist curve ``L(jω) = C(jω)·F(jω)`` near the point's frequency, and ``L(jω₀) = C(jω₀)·F(jω₀)`` at
  the identified point itself;
* the gains in the series and parallel forms (:func:`autotuner.engine.control.gains.forms_json`), so the page
  draws them and derives nothing;
* the unit set-point step and the unit load step (at the process input),
  simulated with the project's ZOH plant (:class:`autotuner.engine.plant.simulation.PlantSim`)
  in feedback with its PID unit (:class:`autotuner.engine.control.pid.PidUnit`), with the
  set-point weights ``b`` and ``c``.

Old gains (the controller's before the session) and new gains are put on the
same time axis, long enough for both to settle. Units: ω in rad/s, times in
plant seconds, PV per unit set point (set-point step) or per MV unit of load
(load step), MV in MV units.

Everything here is plain, synchronous computation (about 0.1 s of CPU): the
daemon runs it in a thread.
"""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import Any

import numpy as np

from autotuner.engine.design.closed_loop import check_gains, closed_loop_step, controller_response
from autotuner.engine.design.point_design import fit_model
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.control.gains import Gains, forms_json
from autotuner.engine.plant.process import Process
from autotuner.engine.result import GainsRecord, ResultRecord
from autotuner.engine.design.robustness import log_grid

# Points of a Nyquist curve and of a time response.
NYQUIST_POINTS = 300
RESPONSE_POINTS = 401
# The Nyquist curve is kept where |L| ≤ NYQUIST_RADIUS (the low frequencies of an integral action go to
# infinity) and down to |L| = NYQUIST_TAIL (the curve then only winds into the origin); it always spans
# ω*/NYQUIST_SPAN … ω*·NYQUIST_SPAN.
NYQUIST_RADIUS = 5.0
NYQUIST_TAIL = 0.02
NYQUIST_SPAN = 3.0
# Time responses: the horizon is SETTLE_MARGIN × the longest settling time of the stable responses, between
# MIN_PERIODS and MAX_PERIODS periods 2π/ω* of the identified point; the search runs SEARCH_SAMPLES samples
# per period. Settled: within SETTLE_BAND of the response's peak from its final value.
MIN_PERIODS = 4.0
MAX_PERIODS = 40.0
SEARCH_SAMPLES = 20
SETTLE_MARGIN = 1.3
SETTLE_BAND = 0.02
# An unstable loop's responses are clipped at this many times the largest |PV| (|MV|) of the stable ones.
CLIP = 10.0


def model_of(result: ResultRecord) -> Process:
    """The model the design used: the result's ``design.model`` (an expression, stored since the design key
    exists); for a result stored before that, the model fitted again through its point and static gain (null
    static gain: integrating). The result must have a point.

    ``result``: the session's result record.
    """
    if result.design is not None:
        return parse_process(result.design.model)
    static_gain = math.inf if result.static_gain is None else result.static_gain
    return fit_model(result.point.point(), static_gain)


def model_json(model: Process) -> dict[str, Any]:
    """``kind`` (FOPDT or IPDT), ``k`` (PV/MV; IPDT: PV/MV per second), ``t`` (s; 0: none), ``l`` (dead time, s)
    and ``text``, the transfer function in the expression grammar of ``autotuner sim``.

    ``model``: an FOPDT or IPDT process.
    """
    dead = f"*exp(-{model.delay:.4g}*s)" if model.delay > 0.0 else ""
    if model.is_integrating:
        k = model.num[-1]
        return {"kind": "IPDT", "k": k, "t": 0.0, "l": model.delay, "text": f"{k:.4g}{dead}/s"}
    k = model.num[-1] / model.den[-1]
    t = model.den[0] / model.den[1] if model.order == 1 else 0.0
    lag = f"/({t:.4g}*s+1)" if t > 0.0 else ""
    return {"kind": "FOPDT", "k": k, "t": t, "l": model.delay, "text": f"{k:.4g}{dead}{lag}"}


def loop_check(model: Process, gains: Gains, omega: float) -> tuple[bool, float | None]:
    """(stable, Ms) of ``C·F`` on the model, Ms None when unstable; ``omega`` (rad/s) centres the grid.

    ``model``: the process model; ``gains``: the controller.
    """
    check = check_gains(model, gains, log_grid(omega))
    return check.stable, (check.ms if check.stable and math.isfinite(check.ms) else None)


def nyquist(model: Process, gains: Gains, omega: float) -> dict[str, list[float]]:
    """``L(jω) = C(jω)F(jω)`` on :data:`NYQUIST_POINTS` log-spaced frequencies (rad/s) around ``omega``, plus
    ``omega`` itself; the window keeps ``NYQUIST_TAIL ≤ |L| ≤ NYQUIST_RADIUS`` (and always ω/3 … 3ω).

    ``model``: the process model; ``gains``: the controller.
    """
    dense = log_grid(omega, 1e-3, 1e3, 4000)
    size = np.abs(controller_response(gains, dense) * model.freqresp(dense))
    big = np.nonzero(~(size <= NYQUIST_RADIUS))[0]  # NaN (ω = 0 of an integrator) counts as big
    lo = dense[min(big[-1] + 1, len(dense) - 1)] if len(big) else dense[0]
    above_tail = np.nonzero(size >= NYQUIST_TAIL)[0]
    hi = dense[above_tail[-1]] if len(above_tail) else dense[-1]
    lo, hi = min(lo, omega / NYQUIST_SPAN), max(hi, omega * NYQUIST_SPAN)
    w = np.union1d(np.logspace(math.log10(lo), math.log10(hi), NYQUIST_POINTS), [omega])
    loop = controller_response(gains, w) * model.freqresp(w)
    keep = np.abs(loop) <= NYQUIST_RADIUS
    keep[np.searchsorted(w, omega)] = True
    return {"omega": w[keep].tolist(), "re": loop.real[keep].tolist(), "im": loop.imag[keep].tolist()}


def at_point(gains: Gains, point: complex, omega: float) -> dict[str, float]:
    """``L(jω₀) = C(jω₀)·F(jω₀)``: ``gains``' controller times the identified point itself (not the model), as
    ``{"re", "im"}`` (dimensionless).

    ``gains``: the controller; ``point``: F(jω₀), PV units per MV unit; ``omega``: ω₀ (rad/s).
    """
    # (a P-only controller's response is one number, not an array)
    value = complex(np.ravel(controller_response(gains, np.array([omega])))[0]) * point
    return {"re": value.real, "im": value.imag}


def step_response(model: Process, gains: Gains, step: str, ts: float, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """(PV, MV) at ``samples`` samples ``ts`` seconds apart after a unit step at t = 0, from rest at 0.

    As :func:`~autotuner.engine.design.closed_loop.closed_loop_step` ("setpoint" or "load"),
    with a diverging loop's last values repeated to ``samples`` points.

    ``model``: the process model; ``gains``: the controller; ``step``: ``"setpoint"`` or ``"load"``.
    """
    pv, mv = closed_loop_step(model, gains, step, ts, samples)
    pad = samples - len(pv)
    return np.pad(pv, (0, pad), mode="edge"), np.pad(mv, (0, pad), mode="edge")


def settling_time(pv: np.ndarray, ts: float) -> float:
    """Seconds after which ``pv`` stays within :data:`SETTLE_BAND` of its peak from its last value.

    ``ts``: the sample time (s).
    """
    band = SETTLE_BAND * float(np.max(np.abs(pv)))
    out = np.nonzero(np.abs(pv - pv[-1]) > band)[0]
    return 0.0 if len(out) == 0 else float(out[-1] + 1) * ts


def responses(model: Process, gains: list[Gains], stable: list[bool], omega: float) -> list[dict[str, Any]]:
    """Set-point and load step responses of each of ``gains`` on one time axis (plant seconds).

    The horizon lets every stable loop settle (see :data:`MIN_PERIODS`);
    ``stable[i]`` False clips that loop's PV and MV (:data:`CLIP`). Each
    element: ``{"setpoint": {"t", "pv", "mv"}, "load": {"t", "pv", "mv"}}``.

    ``model``: the process model; ``stable``: whether each of ``gains`` is stable on it; ``omega``: the point's
    frequency (rad/s), which sets the time axis.
    """
    period = 2.0 * math.pi / omega
    search_ts = period / SEARCH_SAMPLES
    search_n = int(MAX_PERIODS * SEARCH_SAMPLES) + 1
    settle = [settling_time(step_response(model, g, step, search_ts, search_n)[0], search_ts)
              for g, ok in zip(gains, stable) if ok for step in ("setpoint", "load")]
    horizon = min(max(SETTLE_MARGIN * max(settle, default=0.0), MIN_PERIODS * period), MAX_PERIODS * period)
    ts = horizon / (RESPONSE_POINTS - 1)
    t = (ts * np.arange(RESPONSE_POINTS)).tolist()
    out: list[dict[str, Any]] = [{} for _ in gains]
    for step in ("setpoint", "load"):
        runs = [step_response(model, g, step, ts, RESPONSE_POINTS) for g in gains]
        pv_scale = max((float(np.max(np.abs(pv))) for (pv, _), ok in zip(runs, stable) if ok), default=1.0)
        mv_scale = max((float(np.max(np.abs(mv))) for (_, mv), ok in zip(runs, stable) if ok), default=1.0)
        for i, ((pv, mv), ok) in enumerate(zip(runs, stable)):
            if not ok:
                pv = np.clip(pv, -CLIP * pv_scale, CLIP * pv_scale)
                mv = np.clip(mv, -CLIP * mv_scale, CLIP * mv_scale)
            out[i][step] = {"t": t, "pv": pv.tolist(), "mv": mv.tolist()}
    return out


def usable_gains(data: dict[str, Any] | GainsRecord | None) -> Gains | None:
    """Gains from their JSON (``pk, pti, ...``) or record, or None if absent or not a valid controller.

    ``data``: the JSON object, the record or None.
    """
    if not data:
        return None
    try:
        return Gains.from_json(asdict(data) if isinstance(data, GainsRecord) else data)
    except (ValueError, TypeError, KeyError):
        return None


def analyse(result: ResultRecord, ms_target: float, gains_before: dict[str, Any] | None) -> dict[str, Any]:
    """The analysis of a session's result: model, point, Ms circle, and old and new gains on the model.

    ``result`` must have a ``point`` and ``gains`` (the designed ones);
    ``gains_before`` (JSON, may be None) are the controller's gains before the
    session. The body of ``GET /sessions/{sid}/analysis`` without ``session``
    and ``loop``.

    ``ms_target``: the Ms the design aimed at (the circle drawn).
    """
    point = result.point.point()
    model = model_of(result)
    new = result.gains.gains()
    old = usable_gains(gains_before)
    gains = [new] if old is None else [new, old]
    checks = [loop_check(model, g, point.omega) for g in gains]
    stable = [ok for ok, _ in checks]
    steps = responses(model, gains, stable, point.omega)
    loops = [{"gains": g.as_json(), "forms": forms_json(g), "ms": ms, "stable": ok,
              "nyquist": nyquist(model, g, point.omega), "at_point": at_point(g, point.value, point.omega), **s}
             for g, (ok, ms), s in zip(gains, checks, steps)]
    return {
        "controller": result.controller,
        "ms_target": ms_target,
        "point": {"omega": point.omega, "gain": point.gain, "phase_deg": point.phase_deg,
                  "re": point.value.real, "im": point.value.imag},
        "model": model_json(model),
        "ms_circle": {"center_re": -1.0, "radius": 1.0 / ms_target},
        "old": loops[1] if old is not None else None,
        "new": loops[0],
    }
