"""A second, independent OPC UA client stack: node-opcua (npm) against the daemon's OPC UA server.

tests/opcua_node/client.mjs plays the SCADA: anonymous refused; a viewer
browses, reads, and is refused Tune and writes; an operator over
Basic256Sha256 SignAndEncrypt gets REST's validation message, starts a
tuning with AutoTuningOn, watches AutoTuningActive, and stops it with
AutoTuningOff (TE, ite 1). Needs Node.js and ``npm install`` in
tests/opcua_node (``tests/setup-and-run.sh`` does both); without them the test fails saying so.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from autotuner.service.config import DaemonConfig
from api.opcua.passwords import hash_password
from helpers import free_port

HERE = Path(__file__).parent / "opcua_node"
OPERATOR, VIEWER = "node-operator", "node-viewer"


def node() -> str:
    """The node executable, with node-opcua-client installed beside the script; a clear failure otherwise."""
    path = shutil.which("node")
    if path is None:
        pytest.fail("the node-opcua test needs Node.js: tests/setup-and-run.sh installs it (apt-get install "
                    "nodejs, and npm if nodejs came without it)", pytrace=False)
    if not (HERE / "node_modules" / "node-opcua-client").is_dir():
        pytest.fail(f"the node-opcua test needs its package: npm ci --prefix {HERE} (tests/setup-and-run.sh "
                    "does it)", pytrace=False)
    return path


def test_node_opcua_client_browses_is_refused_as_viewer_and_tunes_and_breaks_as_operator(tmp_path):
    executable = node()
    config = DaemonConfig.model_validate({
        "history": str(tmp_path / "history.sqlite"),
        "opcua": {"port": free_port(), "users": [{"name": "viewer", "role": "viewer",
                                                  "password_hash": hash_password(VIEWER)}]},
        "loops": [{"id": "TIC-9", "sim": {"plant": "exp(-0.5*s)/(s+1)"}, "ts": 0.1, "speed": 2.5,
                   "monitor_period": 0.1, "tuning": {"amp": 5.0}, "limits": {"mv": [0.0, 100.0]}}]})
    app = create_app(config, env_token=OPERATOR)
    with TestClient(app):
        done = subprocess.run([executable, str(HERE / "client.mjs"), app.state.opcua_url, "TIC-9", OPERATOR, VIEWER,
                               str(tmp_path / "pki")], capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stdout + done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    # node-opcua does not even try: no endpoint offers an anonymous user token policy
    assert out["anonymous"] == "Cannot find ANONYMOUS user token policy in end point description", out
    assert out["loops"] == ["TIC-9"]
    assert {"PV", "TBSY", "TE", "ite", "pk", "AutoTuningActive", "PIDParameters", "Tune", "AutoTuningOn"} \
        <= set(out["children"])
    assert out["viewer_tbsy"] is False
    assert out["viewer_tune"] == "BadUserAccessDenied" and "BadUserAccessDenied" in out["viewer_write"], out
    assert out["viewer_message"] == ["", "forbidden: this needs the operator role"], out
    assert out["invalid"] == {"status": "BadInvalidArgument",
                              "message": ["", "invalid: amp: Input should be greater than 0"]}
    assert out["on"]["status"] == "Good" and out["on"]["outputs"][1] == "tuning"
    assert out["off"]["status"] == "Good" and out["off"]["outputs"][0] == out["on"]["outputs"][0]
    assert out["tbsy"][-2:] == [True, False], out["tbsy"]
    assert (out["te"], out["ite"], out["session"]) == (True, 1, out["on"]["outputs"][0])
