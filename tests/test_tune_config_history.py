"""``autotuner tune --config … --apply`` records its session in the config's history as the daemon does: the saved
state before the loop is touched, the gains intent before the write, the outcome after. A command killed between the
gains write and its record leaves an open intent, which the next start of ``autotuner serve`` with the same config
reconciles with the gains read back from the device (a real Modbus server; the CLI and the daemon as processes)."""

from __future__ import annotations

import json
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from autotuner.service.configured_loop import cli_user
from autotuner.service.history import History
from test_handback import wait_for
from test_history_faults import SLOW, TS, ThreadedPlc, locked, reconciled_at_start

# How long the history's writes are held past the first failed one, wall seconds: beyond the old fixed wait (10 s),
# well within the config's record_wait (60 s).
HELD = 15.0


def config_for(tmp: Path, plant: ThreadedPlc) -> Path:
    config = tmp / "daemon.yaml"
    config.write_text(yaml.safe_dump({"history": str(tmp / "h.db"), "loops": [
        {"id": "TIC", "link": f"modbus://127.0.0.1:{plant.server.port}/1?timeout=2", "ts": TS, "speed": SLOW,
         "tuning": {"amp": 5.0, "time_limit": 1000.0}}]}))
    return config


def tune(config: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "autotuner.cli", "tune", "--config", str(config), "--loop", "TIC",
                             "--apply", "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_tune_config_with_apply_records_the_session_and_the_gains_the_device_holds(tmp_path: Path):
    plant = ThreadedPlc(SLOW)
    try:
        config = config_for(tmp_path, plant)
        before = plant.plc.gains
        proc = tune(config)
        out, err = proc.communicate(timeout=300)
        result = json.loads(out.strip().splitlines()[-1])
        assert proc.returncode == 0, (result["message"], err)
        history = History(str(tmp_path / "h.db"))
        [record] = history.of_loop("TIC")
        history.close()
        assert record["state"] == "finished" and record["outcome"] == "success" and record["user"] == cli_user()
        assert record["saved"]["mode"] == "AUTO" and record["saved"]["mv_range"]  # on record before the loop's touched
        assert record["gains_before"]["pk"] == pytest.approx(before.k)
        # The outcome: written, read back, recorded as applied by the command's user; history and device agree.
        assert record["gains_intent"] is None and record["applied_by"] == cli_user()
        assert plant.plc.gains != before
        assert record["gains_after"]["pk"] == pytest.approx(plant.plc.gains.k, rel=1e-6)
        assert record["gains_after"]["pti"] == pytest.approx(plant.plc.gains.ti, rel=1e-6)
        assert record["gains_after"]["pk"] == pytest.approx(result["gains"]["pk"], rel=1e-6)
    finally:
        plant.close()


def test_tune_config_killed_after_the_gains_write_is_reconciled_by_the_next_daemon_start(tmp_path: Path):
    plant = ThreadedPlc(SLOW)
    try:
        config = config_for(tmp_path, plant)
        db = tmp_path / "h.db"
        before = plant.plc.gains
        plant.freeze_after_gains = True  # the command's read-back and record cannot happen before it is killed
        proc = tune(config)
        try:
            wait_for(lambda: plant.gains_written.is_set() or proc.poll() is not None, 240, "the gains written")
            assert plant.gains_written.is_set(), proc.communicate()
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.communicate(timeout=30)
        written = plant.plc.gains
        assert written != before
        row = sqlite3.connect(db).execute("SELECT id, state, gains_intent, applied_by FROM sessions").fetchall()
        assert len(row) == 1
        sid, state, intent, applied_by = row[0]
        assert state == "running" and applied_by is None  # written, its outcome not recorded ...
        assert json.loads(intent)["gains"]["pk"] == pytest.approx(written.k, rel=1e-6)  # ... but its intent is
        record = reconciled_at_start(plant, config, sid)  # the next start of the daemon on the same config
        assert record["applied_by"] == cli_user() and plant.plc.gains == written
        assert record["gains_after"]["pk"] == pytest.approx(written.k, rel=1e-6)
        assert record["gains_after"]["pti"] == pytest.approx(written.ti, rel=1e-6)
    finally:
        plant.close()


def test_tune_config_waits_for_its_records_as_long_as_the_configs_record_wait(tmp_path: Path):
    """The config's ``record_wait`` bounds the command's wait for its records as it bounds the daemon's (the
    command waited its own 10 s whatever the config said): with record_wait 60 s, a history whose writes another
    process holds for HELD s past the first failed write (longer than the old 10 s) delays the session's saved
    state, which is then recorded, and the tuning goes on and is applied."""
    plant = ThreadedPlc(SLOW)
    try:
        config = config_for(tmp_path, plant)
        config.write_text(yaml.safe_dump({**yaml.safe_load(config.read_text()), "record_wait": 60.0}))
        History(str(tmp_path / "h.db")).close()
        log = tmp_path / "tune.err"
        with locked(tmp_path / "h.db", "IMMEDIATE"), log.open("w") as err_file:
            proc = subprocess.Popen([sys.executable, "-m", "autotuner.cli", "tune", "--config", str(config), "--loop",
                                     "TIC", "--apply", "--json"], stdout=subprocess.PIPE, stderr=err_file, text=True)
            wait_for(lambda: "retrying" in log.read_text() or proc.poll() is not None, 120, "a write held")
            time.sleep(HELD)  # the fault's length, not a wait for a condition
        out, _ = proc.communicate(timeout=300)
        result = json.loads(out.strip().splitlines()[-1])
        assert proc.returncode == 0, (result["message"], log.read_text())
        [record] = History(str(tmp_path / "h.db")).of_loop("TIC")
        assert record["state"] == "finished" and record["outcome"] == "success" and record["saved"]["mode"] == "AUTO"
        assert record["gains_after"]["pk"] == pytest.approx(plant.plc.gains.k, rel=1e-6)
    finally:
        plant.close()
