"""POST /loops/{id}/apply: a session's designed gains written to the controller, read back, recorded.

Through HTTP: the demo's simulated loops (tuned for real, 12× real time), a
simulated PLC behind Modbus TCP on localhost, and a dead Modbus address; the
status fields that follow the history (last_tuned_at, last_outcome,
pending_gains) across a restart; an old history file gaining the new columns.
"""

from __future__ import annotations

import sqlite3

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from autotuner.service.config import DaemonConfig
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.control.gains import Gains
from autotuner.engine.result import ResultRecord
from autotuner.service.history import History
from autotuner.service.remote_tuning import PLANT_TICKS_PER_SAMPLE
from drivers.link import LoopState, Mode
from drivers.simplc import SimulatedPlc

from test_api import CONFIG, OPERATOR, VIEWER, auth, modbus_plant, wait_idle

API = "/api/v1"
PLANT = "exp(-s)/(2*s+1)"
DESIGNED = Gains(k=1.25, ti=2.5, b=0.6)
BEFORE = Gains(k=0.5, ti=3.0)


def record_session(path: str, sid: str, loop: str, ok: bool = True, gains: Gains | None = DESIGNED) -> None:
    """A finished session of ``loop`` in the history file ``path``, as the daemon records one (apply false)."""
    history = History(path)
    history.begin(sid, loop, "alice", {"controller": "PI", "amp": 5.0, "hysteresis": None, "phase": 135.0,
                                       "ms": 1.4, "apply": False})
    history.saved(sid, LoopState(mode=Mode.AUTO, mv=50.0, sp=50.0, gains=BEFORE))
    result = ResultRecord.from_json({
        "tbsy": False, "te": not ok, "ite": 0 if ok else 3, "message": "ok" if ok else "no oscillation",
        "controller": "PI", "point": {"omega": 1.2, "gain": 0.6, "phase_deg": -135.0}, "static_gain": 1.0,
        "gains": None if gains is None else gains.as_json(),
        "experiment": {"duration": 60.0, "periods": 6.0, "samples": 600}})
    history.finish(sid, result, BEFORE, {"t": [0.0], "pv": [50.0], "mv": [50.0]})
    history.close()


def test_apply_writes_the_designed_gains_and_records_who():
    with TestClient(create_app(CONFIG, env_token=OPERATOR)) as client:
        plc = client.app.state.manager.loops["TIC-101"].plc
        before = plc.gains
        nothing_yet = client.post(f"{API}/loops/TIC-101/apply", headers=auth(OPERATOR))
        sid = client.post(f"{API}/loops/TIC-101/tune", headers=auth(OPERATOR)).json()["session"]
        busy = client.post(f"{API}/loops/TIC-101/apply", headers=auth(OPERATOR))
        done = wait_idle(client, "TIC-101")
        assert done["ite"] == 0, done["message"]
        designed = done["gains"]
        pending = client.get(f"{API}/loops/TIC-101", headers=auth(VIEWER)).json()
        as_viewer = client.post(f"{API}/loops/TIC-101/apply", headers=auth(VIEWER))
        unchanged = plc.gains
        r = client.post(f"{API}/loops/TIC-101/apply", headers=auth(OPERATOR))
        after = client.get(f"{API}/loops/TIC-101", headers=auth(VIEWER)).json()
        record = client.get(f"{API}/sessions/{sid}", headers=auth(VIEWER)).json()
        again = client.post(f"{API}/loops/TIC-101/apply", headers=auth(OPERATOR), json={"session": sid})
        record_again = client.get(f"{API}/sessions/{sid}", headers=auth(VIEWER)).json()
        other_loop = client.post(f"{API}/loops/FIC-301/apply", headers=auth(OPERATOR), json={"session": sid})
        unknown = client.post(f"{API}/loops/TIC-101/apply", headers=auth(OPERATOR), json={"session": "nope"})
        unknown_loop = client.post(f"{API}/loops/nope/apply", headers=auth(OPERATOR))
        invalid = client.post(f"{API}/loops/TIC-101/apply", headers=auth(OPERATOR), json={"sesion": sid})
        failed = client.post(f"{API}/loops/FIC-301/tune", headers=auth(OPERATOR)).json()["session"]
        client.post(f"{API}/loops/FIC-301/break", headers=auth(OPERATOR))
        aborted = wait_idle(client, "FIC-301")
        failed_apply = client.post(f"{API}/loops/FIC-301/apply", headers=auth(OPERATOR))
        failed_by_id = client.post(f"{API}/loops/FIC-301/apply", headers=auth(OPERATOR), json={"session": failed})
        spec = client.get(f"{API}/openapi.json").json()

    assert nothing_yet.status_code == 409 and nothing_yet.json()["code"] == "nothing_to_apply"
    assert busy.status_code == 409 and busy.json()["code"] == "busy"
    assert pending["pending_gains"] is True and pending["last_outcome"] == "success"
    assert pending["last_tuned_at"] is not None and pending["current_gains"] == before.as_json()
    assert as_viewer.status_code == 403 and unchanged == before  # refused: nothing written
    assert r.status_code == 200 and r.json() == {"loop": "TIC-101", "session": sid, "gains": designed}
    assert plc.gains == Gains.from_json(designed) and plc.mode is Mode.AUTO
    assert after["pending_gains"] is False and after["current_gains"] == designed
    assert after["last_tuned_at"] == pending["last_tuned_at"] == record["finished_at"]
    assert record["applied_by"] == "AUTOTUNER_TOKEN" and record["applied_at"] >= record["finished_at"]
    assert record["gains_after"] == designed and record["gains_before"] == before.as_json()
    assert again.status_code == 200 and record_again["applied_at"] >= record["applied_at"]  # idempotent
    assert other_loop.status_code == 404 and other_loop.json()["code"] == "not_found"
    assert unknown.status_code == 404 and unknown_loop.status_code == 404
    assert invalid.status_code == 422 and invalid.json()["message"].startswith("sesion: ")
    assert aborted["pending_gains"] is False and aborted["last_outcome"] == "failure"
    for refused in (failed_apply, failed_by_id):
        assert refused.status_code == 409 and refused.json()["code"] == "nothing_to_apply"
        assert "did not succeed" in refused.json()["message"]
    responses = spec["paths"][f"{API}/loops/{{loop_id}}/apply"]["post"]["responses"]
    assert {"200", "403", "404", "409", "422", "502"} <= responses.keys()


def test_apply_over_modbus_and_a_dead_link_is_502_recording_nothing(tmp_path):
    path = str(tmp_path / "history.db")
    record_session(path, "s-live", "TIC-1")
    record_session(path, "s-dead", "DEAD")
    record_session(path, "s-none", "TIC-1", gains=None)
    ts = 0.1
    plc = SimulatedPlc(parse_process(PLANT), ts=ts / PLANT_TICKS_PER_SAMPLE)
    with modbus_plant(plc, 5.0) as url:
        config = DaemonConfig.model_validate({"history": path, "loops": [
            {"id": "TIC-1", "link": url, "ts": ts, "speed": 5.0, "monitor_period": 0.1},
            {"id": "DEAD", "link": "modbus://127.0.0.1:1/1", "ts": ts, "monitor_period": 0.1}]})
        with TestClient(create_app(config, env_token=OPERATOR)) as client:
            no_gains = client.post(f"{API}/loops/TIC-1/apply", headers=auth(OPERATOR), json={"session": "s-none"})
            r = client.post(f"{API}/loops/TIC-1/apply", headers=auth(OPERATOR), json={"session": "s-live"})
            live = client.get(f"{API}/loops/TIC-1", headers=auth(OPERATOR)).json()
            dead = client.post(f"{API}/loops/DEAD/apply", headers=auth(OPERATOR))
            dead_status = client.get(f"{API}/loops/DEAD", headers=auth(OPERATOR)).json()
            dead_record = client.get(f"{API}/sessions/s-dead", headers=auth(OPERATOR)).json()
    assert no_gains.status_code == 409 and no_gains.json()["code"] == "nothing_to_apply"
    assert r.status_code == 200
    gains = r.json()["gains"]  # read back over Modbus (float32 registers)
    assert gains["pk"] == pytest.approx(DESIGNED.k, rel=1e-6) and gains["pb"] == pytest.approx(DESIGNED.b, rel=1e-6)
    assert plc.gains.k == pytest.approx(DESIGNED.k, rel=1e-6) and plc.gains.ti == pytest.approx(DESIGNED.ti, rel=1e-6)
    assert live["current_gains"] == gains and live["pending_gains"] is False
    assert dead.status_code == 502 and dead.json()["code"] == "link" and "DEAD" in dead.json()["message"]
    assert dead_record["applied_at"] is None and dead_record["gains_after"] == BEFORE.as_json()
    assert dead_status["pending_gains"] is True and dead_status["monitor_error"]


def test_the_last_session_and_its_pending_gains_survive_a_restart(tmp_path):
    path = str(tmp_path / "history.db")
    record_session(path, "s-old", "TIC-101")
    record_session(path, "s-new", "TIC-101")
    record_session(path, "s-bad", "LIC-201", ok=False)
    config = CONFIG.model_copy(update={"history": path})
    with TestClient(create_app(config, env_token=OPERATOR)) as client:
        first = client.get(f"{API}/loops", headers=auth(VIEWER)).json()
        r = client.post(f"{API}/loops/TIC-101/apply", headers=auth(OPERATOR))
    with TestClient(create_app(config, env_token=OPERATOR)) as client:
        second = client.get(f"{API}/loops/TIC-101", headers=auth(VIEWER)).json()
        newest = client.get(f"{API}/sessions/s-new", headers=auth(VIEWER)).json()
    by_id = {loop["id"]: loop for loop in first}
    tic, lic, fic = by_id["TIC-101"], by_id["LIC-201"], by_id["FIC-301"]
    assert tic["pending_gains"] is True and tic["last_outcome"] == "success" and tic["last_tuned_at"]
    assert lic["pending_gains"] is False and lic["last_outcome"] == "failure"
    assert fic["last_tuned_at"] is None and fic["last_outcome"] is None and fic["pending_gains"] is False
    assert r.status_code == 200 and r.json()["session"] == "s-new"  # the newest by default
    assert second["pending_gains"] is False and second["last_tuned_at"] == newest["finished_at"]
    assert newest["applied_by"] == "AUTOTUNER_TOKEN"


def test_an_older_history_file_gains_the_applied_columns(tmp_path):
    path = str(tmp_path / "old.db")
    db = sqlite3.connect(path)
    db.executescript("""
        CREATE TABLE sessions (id TEXT PRIMARY KEY, loop TEXT NOT NULL, user TEXT NOT NULL,
            started_at TEXT NOT NULL, finished_at TEXT, state TEXT NOT NULL, request TEXT NOT NULL,
            saved TEXT, result TEXT, gains_after TEXT, trace TEXT);
        INSERT INTO sessions (id, loop, user, started_at, state, request) VALUES
            ('s1', 'A', 'bob', '2024-01-01T00:00:00+00:00', 'running', '{}');
    """)
    db.close()
    history = History(path)
    try:
        record = history.get("s1")
        assert record["applied_at"] is None and record["applied_by"] is None
        history.applied("s1", "carol", DESIGNED)
        record = history.get("s1")
        assert record["applied_by"] == "carol" and record["gains_after"] == DESIGNED.as_json()
    finally:
        history.close()
    History(path).close()  # opening it again: nothing to add
