"""What a session's gains do on the identified model (autotuner/analysis.py, GET /sessions/{sid}/analysis).

The numbers are checked against computations written here from the model's
parameters alone: the model through the point, Ms on a dense grid, the
Nyquist curve at the point, and step responses from a fine Euler
integration of the continuous loop (dead time as a delay line).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, replace

import numpy as np
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from autotuner.engine.design.analysis import CLIP, analyse
from autotuner.engine.design.point_design import design
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.control.gains import Gains
from autotuner.engine.design.process_data import exact_point
from autotuner.engine.result import DesignRecord, ExperimentRecord, GainsRecord, PointRecord, ResultRecord
from drivers.simplc import safe_gains

from test_api import CONFIG, OPERATOR, VIEWER, auth, wait_idle

API = "/api/v1"
TIC = "1.5*exp(-0.7*s)/(4*s+1)^2"  # lag with dead time: FOPDT model
LIC = "0.2*exp(-1*s)/(s*(2*s+1))"  # integrating: IPDT model


def result_for(plant: str, controller: str = "PI", ms: float = 1.4) -> tuple[ResultRecord, Gains]:
    """A session's result as a row stored before the design key existed records it (exact 135° point, no model),
    and the PLC's initial gains."""
    process = parse_process(plant)
    point = exact_point(process, 135.0)
    static = process.static_gain()
    d = design(point, static, controller, ms)
    result = ResultRecord(False, False, 0, "ok", controller, PointRecord.of(point),
                          None if math.isinf(static) else static, GainsRecord.of(d.gains),
                          ExperimentRecord(60.0, 6.0, 600))
    return result, safe_gains(process)


def with_model(result: ResultRecord, model: str) -> ResultRecord:
    """The result with ``model`` stored as the design's model."""
    return replace(result, design=DesignRecord(model, 1.4, 1.4, 0.0, ()))


def model_response(model: dict, w: np.ndarray) -> np.ndarray:
    """F(jω) from the model's parameters: k·e^{−jωl}/(jωt + 1), or k·e^{−jωl}/(jω) for IPDT."""
    s = 1j * w
    lag = s if model["kind"] == "IPDT" else model["t"] * s + 1.0
    return model["k"] * np.exp(-s * model["l"]) / lag


def controller_response(g: dict, w: np.ndarray) -> np.ndarray:
    """k(1 + 1/(ti s) + td s/(td s/nd + 1)) from the JSON gains."""
    s = 1j * w
    c = 1.0 + (0.0 if g["pti"] is None else 1.0 / (g["pti"] * s))
    if g["ptd"] > 0.0:
        c = c + g["ptd"] * s / (g["ptd"] * s / g["pnd"] + 1.0)
    return g["pk"] * c


def euler_loop(model: dict, g: dict, step: str, t_end: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Continuous PI loop (no derivative) on the model by Euler steps of ``dt``: (t, pv)."""
    n = int(round(t_end / dt)) + 1
    delay = int(round(model["l"] / dt))
    u_line = np.zeros(n + delay + 1)  # u(t − l) by index
    r = 1.0 if step == "setpoint" else 0.0
    load = 1.0 if step == "load" else 0.0
    y, integral = 0.0, 0.0
    ys = np.empty(n)
    for i in range(n):
        ys[i] = y
        e = r - y
        u = g["pk"] * (g["pb"] * r - y) + integral
        integral += g["pk"] / g["pti"] * e * dt
        u_line[i + delay] = u + load
        v = u_line[i]
        if model["kind"] == "IPDT":
            y += dt * model["k"] * v
        else:
            y += dt * (model["k"] * v - y) / model["t"]
    return dt * np.arange(n), ys


@pytest.mark.parametrize("plant, kind", [(TIC, "FOPDT"), (LIC, "IPDT")])
def test_analysis_agrees_with_an_independent_computation(plant, kind):
    result, old = result_for(plant)
    a = analyse(result, 1.4, old.as_json())
    model, point = a["model"], a["point"]
    assert model["kind"] == kind
    w0 = point["omega"]
    f0 = complex(point["re"], point["im"])
    assert abs(f0) == pytest.approx(point["gain"]) and math.degrees(np.angle(f0)) == pytest.approx(point["phase_deg"])
    # The model goes through the identified point.
    assert complex(model_response(model, np.array([w0]))[0]) == pytest.approx(f0, rel=1e-9)
    if kind == "IPDT":
        assert model["t"] == 0.0 and model["k"] == pytest.approx(point["gain"] * w0)
        assert model["text"].endswith("/s")
    else:
        assert model["k"] == pytest.approx(1.5)
    assert a["ms_circle"] == {"center_re": -1.0, "radius": pytest.approx(1 / 1.4)}
    assert a["new"]["gains"] == asdict(result.gains) and a["old"]["gains"] == old.as_json()

    w = np.logspace(math.log10(w0) - 4, math.log10(w0) + 2, 200000)
    for loop in (a["new"], a["old"]):
        g = loop["gains"]
        ms = float(np.max(1.0 / np.abs(1.0 + controller_response(g, w) * model_response(model, w))))
        assert loop["stable"] is True and loop["ms"] == pytest.approx(ms, rel=2e-3)
        # The Nyquist curve at the point's frequency is C(jω)·F(jω*).
        nyq = loop["nyquist"]
        assert len(nyq["omega"]) == len(nyq["re"]) == len(nyq["im"]) >= 100
        assert np.all(np.diff(nyq["omega"]) > 0)
        i = nyq["omega"].index(w0)
        c0 = complex(controller_response(g, np.array([w0]))[0])
        assert complex(nyq["re"][i], nyq["im"][i]) == pytest.approx(c0 * f0, rel=1e-9)
    # The design's Ms on its model: at most the target, and close to it (1.05 × the target on the lag bound may
    # be the active limit instead).
    assert 0.93 * 1.4 <= a["new"]["ms"] <= 1.4 * 1.001
    assert a["old"]["ms"] == pytest.approx(1.2, rel=0.02)  # the PLC's gains: designed at Ms 1.2 on the process

    for step in ("setpoint", "load"):
        new, old_r = a["new"][step], a["old"][step]
        assert new["t"] == old_r["t"] and len(new["t"]) >= 200 and new["t"][0] == 0.0
        t = np.array(new["t"])
        horizon = t[-1]
        final = 1.0 if step == "setpoint" else 0.0
        for r in (new, old_r):  # both settle within the horizon
            pv = np.array(r["pv"])
            tail = pv[t >= 0.8 * horizon]
            assert np.max(np.abs(tail - final)) <= 0.02 * np.max(np.abs(pv)), step
        # An independent continuous-time simulation agrees with the sampled one.
        # (Measured: within 0.4–2.4 % of the peak; the sampled controller adds half a sample of lag.)
        te, ye = euler_loop(model, a["new"]["gains"], step, horizon, horizon / 40000)
        ref = np.interp(t, te, ye)
        assert np.max(np.abs(np.array(new["pv"]) - ref)) <= 0.04 * np.max(np.abs(ye)), step
        if step == "setpoint":  # MV at t = 0: the proportional kick k·b
            assert new["mv"][0] == pytest.approx(result.gains.pk * result.gains.pb)
        else:  # the controller ends up cancelling the unit load
            assert new["mv"][-1] == pytest.approx(-1.0, abs=0.03)


def series_form(g: dict) -> tuple[float, float | None, float] | None:
    """K′(1 + 1/(Ti′s))(1 + Td′s) with the same zeros as K(1 + 1/(Ti s) + Td s): Ti′ + Td′ = Ti, Ti′·Td′ = Ti·Td
    (the roots of x² − Ti·x + Ti·Td, the larger one Ti′), K′ = K·Ti′/Ti; None when the roots are complex."""
    if g["pti"] is None:
        return g["pk"], None, g["ptd"]
    roots = np.roots([1.0, -g["pti"], g["pti"] * g["ptd"]])
    if np.any(np.abs(roots.imag) > 1e-9 * g["pti"]):
        return None
    ti, td = sorted(roots.real, reverse=True)
    return g["pk"] * ti / g["pti"], ti, td


@pytest.mark.parametrize("plant, controller, ms", [(TIC, "PI", 1.4), (TIC, "PID", 1.6), (LIC, "PID", 1.4)])
def test_the_page_draws_the_open_loop_at_the_point_and_the_gain_forms_from_the_analysis(plant, controller, ms):
    """L(jω₀) = C(jω₀)·F(jω₀) on the identified point and the parallel and series forms of old and new gains
    come with the analysis (the page derives none of them), equal to their definitions computed here."""
    result, old = result_for(plant, controller, ms)
    a = analyse(result, ms, old.as_json())
    w0, f0 = a["point"]["omega"], complex(a["point"]["re"], a["point"]["im"])
    for loop in (a["new"], a["old"]):
        g = loop["gains"]
        expected = complex(controller_response(g, np.array([w0]))[0]) * f0
        assert complex(loop["at_point"]["re"], loop["at_point"]["im"]) == pytest.approx(expected, rel=1e-12)
        parallel = loop["forms"]["parallel"]
        ki = 0.0 if g["pti"] is None else g["pk"] / g["pti"]
        assert parallel == pytest.approx({"kp": g["pk"], "ki": ki, "kd": g["pk"] * g["ptd"]}, rel=1e-12)
        series = series_form(g)
        if series is None:
            assert loop["forms"]["series"] is None and "4" in loop["forms"]["series_reason"]
        else:
            got = loop["forms"]["series"]
            assert (got["k"], got["ti"], got["td"]) == pytest.approx(series, rel=1e-9, abs=1e-12)
    # The designed PID has a derivative: its series form differs from the standard one.
    if controller == "PID":
        assert a["new"]["gains"]["ptd"] > 0.0 and a["new"]["forms"]["series"]["td"] > 0.0


def test_the_stored_model_is_analysed_and_old_results_are_fitted_again():
    """A result with ``design.model`` is analysed on that model, not on one refitted through its point; a result
    stored before the design key existed gets the refitted one."""
    result, old = result_for(TIC)
    fitted = analyse(result, 1.4, old.as_json())["model"]
    # A model through the same point with another static gain (what a design of another family could use).
    other = "1.2*exp(-3.1*s)/(6.5*s+1)"
    stored = analyse(with_model(result, other), 1.4, old.as_json())["model"]
    assert (stored["kind"], stored["k"], stored["t"], stored["l"]) == ("FOPDT", pytest.approx(1.2),
                                                                       pytest.approx(6.5), pytest.approx(3.1))
    assert fitted["k"] == pytest.approx(1.5, rel=0.05) and fitted["k"] != pytest.approx(1.2, rel=0.05)
    # The model a real design stored: the same as fitting again (12 digits in the expression).
    process = parse_process(TIC)
    point = exact_point(process, 135.0)
    d = design(point, process.static_gain(), "PI", 1.4)
    same = analyse(with_model(result, str(d.model)), 1.4, old.as_json())["model"]
    assert same["kind"] == fitted["kind"] and same["text"] == fitted["text"]
    assert [same[k] for k in "ktl"] == pytest.approx([fitted[k] for k in "ktl"], rel=1e-9)


def test_unstable_or_missing_old_gains():
    result, old = result_for(TIC)
    aggressive = Gains(k=old.k * 8, ti=old.ti / 4).as_json()
    a = analyse(result, 1.4, aggressive)
    assert a["old"]["stable"] is False and a["old"]["ms"] is None and a["new"]["stable"] is True
    for step in ("setpoint", "load"):
        pv, new_pv = np.array(a["old"][step]["pv"]), np.array(a["new"][step]["pv"])
        assert np.all(np.isfinite(pv)) and np.max(np.abs(pv)) <= CLIP * np.max(np.abs(new_pv)) * (1 + 1e-12)
        assert a["old"][step]["t"] == a["new"][step]["t"]
    assert analyse(result, 1.4, None)["old"] is None
    assert analyse(result, 1.4, {"pk": 0.0, "pti": 3.0, "ptd": 0.0, "pnd": 10.0, "pb": 1.0, "pc": 0.0})["old"] is None
    # A P-only controller before: stable, with the load's offset.
    p_only = analyse(result, 1.4, Gains(k=0.5).as_json())["old"]
    assert p_only["stable"] is True
    assert p_only["load"]["pv"][-1] == pytest.approx(1.5 / (1 + 1.5 * 0.5), rel=0.02)


def test_pid_design_is_analysed_with_its_derivative():
    result, old = result_for(TIC, "PID", 1.6)
    a = analyse(result, 1.6, old.as_json())
    assert a["new"]["gains"]["ptd"] > 0.0 and a["ms_target"] == 1.6 and a["controller"] == "PID"
    assert a["new"]["ms"] <= 1.6 * 1.001 and a["new"]["stable"]
    pv = np.array(a["new"]["setpoint"]["pv"])
    assert pv[-1] == pytest.approx(1.0, abs=0.02)


def test_analysis_endpoint():
    with TestClient(create_app(CONFIG, env_token=OPERATOR)) as client:
        sid = client.post(f"{API}/loops/TIC-101/tune", headers=auth(OPERATOR)).json()["session"]
        busy = client.get(f"{API}/sessions/{sid}/analysis", headers=auth(VIEWER))
        aborted = client.post(f"{API}/loops/FIC-301/tune", headers=auth(OPERATOR)).json()["session"]
        client.post(f"{API}/loops/FIC-301/break", headers=auth(OPERATOR))
        wait_idle(client, "FIC-301")
        done = wait_idle(client, "TIC-101")
        assert done["ite"] == 0, done["message"]
        r = client.get(f"{API}/sessions/{sid}/analysis", headers=auth(VIEWER))
        again = client.get(f"{API}/sessions/{sid}/analysis", headers=auth(VIEWER))
        record = client.get(f"{API}/sessions/{sid}", headers=auth(VIEWER)).json()
        no_result = client.get(f"{API}/sessions/{aborted}/analysis", headers=auth(VIEWER))
        unknown = client.get(f"{API}/sessions/nope/analysis", headers=auth(VIEWER))
        anonymous = client.get(f"{API}/sessions/{sid}/analysis")
        spec = client.get(f"{API}/openapi.json").json()
    assert busy.status_code == 409 and busy.json()["code"] == "no_result"
    assert r.status_code == 200 and again.json() == r.json()
    body = r.json()
    assert body["session"] == sid and body["loop"] == "TIC-101" and body["controller"] == "PI"
    assert body["ms_target"] == record["request"]["ms"] == 1.4
    assert body["point"]["omega"] == record["result"]["point"]["omega"]
    assert body["model"]["kind"] == "FOPDT" and "exp(-" in body["model"]["text"]
    assert body["new"]["gains"] == record["result"]["gains"] and body["old"]["gains"] == record["gains_before"]
    assert body["new"]["ms"] <= 1.4 * 1.001 and body["new"]["setpoint"]["pv"][-1] == pytest.approx(1.0, abs=0.02)
    # What the page draws besides the curves: the open loop at the point, the gains' other forms (the result's own
    # forms for the new gains).
    assert body["new"]["forms"]["parallel"] == record["result"]["forms"]["parallel"]
    assert body["new"]["forms"]["series"] == record["result"]["forms"]["series"]
    assert set(body["old"]["at_point"]) == {"re", "im"} and body["old"]["forms"]["parallel"]["kp"] == body["old"]["gains"]["pk"]
    assert no_result.status_code == 409 and no_result.json()["code"] == "no_result"
    assert unknown.status_code == 404 and unknown.json()["code"] == "not_found"
    assert anonymous.status_code == 401
    responses = spec["paths"][f"{API}/sessions/{{sid}}/analysis"]["get"]["responses"]
    assert {"200", "404", "409"} <= responses.keys()
