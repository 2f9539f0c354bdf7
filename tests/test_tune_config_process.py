"""``autotuner tune --config FILE --loop ID`` as a process against an external ``autotuner sim --modbus`` PLC, the
PLC read by a separate Modbus client: the CLI refuses a loop the daemon would refuse (the same fresh read, the same
codes 23-26) before it writes anything; every holding register and coil reads back as before."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from autotuner.engine.outcome import Code
from drivers.modbus_map import DEFAULT_MAP
from test_handback import SAVED_MV, Plc

# Holding registers 0..24 and coils 0..3 of the default map: SP, manual MV, gains, ite, mode, heartbeat, watchdog;
# TUNE, TBRK, TBSY, TE.
HOLDINGS = max(reg.address + reg.size for reg in (DEFAULT_MAP[n] for n in ("wd_mode", "wd_time", "mode", "ite")))
COILS = 4
# A hang bound for the CLI process, wall seconds (it ends in about a second).
CLI_BOUND = 120.0


def registers(plc: Plc) -> tuple[list[int], list[bool]]:
    """Every holding register and coil the tuner could write, as the PLC serves them now."""
    holding = plc.client.read_holding_registers(0, count=HOLDINGS, device_id=1)
    coils = plc.client.read_coils(0, count=COILS, device_id=1)
    assert not holding.isError() and not coils.isError(), (holding, coils)
    return list(holding.registers), list(coils.bits[:COILS])


def tune_config(tmp: Path, plc: Plc, pv_limits: list[float], *options: str) -> tuple[int, dict, str]:
    """Run ``autotuner tune --config … --loop L1 --json`` on ``plc``; exit code, the JSON printed, stderr."""
    config = tmp / "daemon.yaml"
    config.write_text(json.dumps({"history": str(tmp / "history.sqlite"), "loops": [{
        "id": "L1", "link": plc.url, "ts": 0.3, "speed": plc.speed,
        "tuning": {"controller": "PI", "amp": 5.0, "time_limit": 2000},
        "limits": {"pv": pv_limits, "mv": [0, 100]}}]}))
    done = subprocess.run([sys.executable, "-m", "autotuner.cli", "tune", "--config", str(config), "--loop", "L1",
                           "--json", *options], capture_output=True, text=True, timeout=CLI_BOUND)
    lines = done.stdout.strip().splitlines()
    assert lines, (done.returncode, done.stderr)
    return done.returncode, json.loads(lines[-1]), done.stderr


@pytest.mark.parametrize("fault, pv_limits, ite, says", [
    (None, [60, 100], Code.REFUSED_PV_LIMITS, "PV 50 is outside its limits [60, 100]"),
    ("tbsy", [0, 100], Code.REFUSED_DEVICE_BUSY, "already shows TBSY"),
])
def test_tune_config_refuses_as_the_daemon_does_and_leaves_the_plc_untouched(tmp_path, fault, pv_limits, ite, says):
    plc = Plc(tmp_path)
    try:
        if fault == "tbsy":  # another tuner owns the loop
            assert not plc.client.write_coil(DEFAULT_MAP["tbsy"].address, True, device_id=1).isError()
        before = registers(plc)
        state = plc.read()
        assert state["mode"] == "AUTO" and state["hv"] == SAVED_MV
        code, out, _ = tune_config(tmp_path, plc, pv_limits, "--apply")
        assert code == 1, out
        assert out["te"] is True and out["ite"] == int(ite) and says in out["message"], out
        assert out["message"].startswith("refused:") and "untouched" in out["message"]
        assert registers(plc) == before  # nothing written: mode, manual MV, gains, flags, watchdog, heartbeat
        assert plc.read()["mode"] == "AUTO"
    finally:
        plc.close()


def test_tune_config_on_an_offline_plc_is_refused_as_an_unhealthy_link(tmp_path):
    plc = Plc(tmp_path)
    plc.close()  # its port now answers nothing
    code, out, _ = tune_config(tmp_path, plc, [0, 100])
    assert code == 1 and out["ite"] == int(Code.REFUSED_LINK), out


def test_a_load_step_the_plc_makes_during_the_experiment_is_estimated_through(tmp_path):
    # The external PLC steps its load by 0.2 × amp 28 plant seconds (1.3 periods; a quiet run ends at 2.2, the
    # model rule's) after the tuner takes the loop over. Load following was off over links: the relay took the
    # load's response for its own.
    # At 10× real time (30 ms of wall time per sample; at 20× a machine loaded beyond its cores refused with 11
    # now and then: see test_hil's load test).
    plc = Plc(tmp_path, speed=10.0, options=("--plant", "exp(-4*s)/(8*s+1)", "--load", "28:1"))
    try:
        code, out, err = tune_config(tmp_path, plc, [0, 100])
        assert code == 0 and out["ite"] == 0, (out, err)
        assert out["experiment"]["disturbance"] is True
        assert out["experiment"]["load_estimate"] == pytest.approx(1.0, abs=0.15)
        assert out["static_gain"] == pytest.approx(1.0, rel=0.05)
        state = plc.read()  # handed back, as a separate client reads the PLC
        assert state["mode"] == "AUTO" and state["tbsy"] is False and state["te"] is False
    finally:
        plc.close()
