"""`autotuner serve --opcua` as a process: the demo's users, the printed endpoint, SIGTERM; the missing extra."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import subprocess
import sys
import time

import pytest
from asyncua import Client, ua

from api.opcua import INSTALL_HINT
from api.opcua.address_space import NAMESPACE
from helpers import free_port


async def _tbsy(url: str, user: str, password: str) -> bool:
    client = Client(url, timeout=10)
    client.set_user(user)
    client.set_password(password)
    async with client:
        idx = await client.get_namespace_index(NAMESPACE)
        return await client.get_node(ua.NodeId("TIC-101.TBSY", idx)).read_value()


def test_demo_accepts_operator_with_the_token_and_the_viewer_and_stops_on_sigterm():
    port, opcua_port = free_port(), free_port()
    env = {**os.environ, "AUTOTUNER_TOKEN": "demo-operator", "AUTOTUNER_VIEWER_PASSWORD": "demo-viewer"}
    proc = subprocess.Popen([sys.executable, "-m", "autotuner.cli", "serve", "--port", str(port), "--opcua-port",
                             str(opcua_port)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        url = f"opc.tcp://127.0.0.1:{opcua_port}/autotuner/"
        assert line.startswith(f"autotuner OPC UA at {url}") and "operator" in line and "viewer" in line, line
        deadline = time.monotonic() + 60
        while True:
            try:
                assert asyncio.run(_tbsy(url, "viewer", "demo-viewer")) is False
                break
            except (OSError, TimeoutError, ua.UaError):
                assert time.monotonic() < deadline and proc.poll() is None, "the OPC UA server did not come up"
                time.sleep(0.2)
        assert asyncio.run(_tbsy(url, "operator", "demo-operator")) is False
        with pytest.raises(ua.UaStatusCodeError):
            asyncio.run(_tbsy(url, "operator", "demo-viewer"))
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(40) in (0, -signal.SIGTERM)
        assert "Application shutdown complete" in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_serve_opcua_without_asyncua_is_a_clear_error():
    hide = "import sys; sys.modules['asyncua'] = None; from autotuner.cli import main; main()"
    done = subprocess.run([sys.executable, "-c", hide, "serve", "--opcua"], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2
    assert INSTALL_HINT in done.stderr and "Traceback" not in done.stderr


def test_password_hash_prints_a_hash_the_config_accepts():
    from api.opcua.passwords import verify_password
    from autotuner.service.config import OpcUaUser

    done = subprocess.run([sys.executable, "-m", "autotuner.cli", "password-hash"], input="s3cret\ns3cret\n",
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    digest = re.search(r"scrypt\$\S+", done.stdout).group(0)  # after the prompts (stdin is no terminal)
    assert "s3cret" not in done.stdout
    assert verify_password("s3cret", digest) and not verify_password("s3cret!", digest)
    OpcUaUser(name="scada", role="operator", password_hash=digest)
    with pytest.raises(ValueError, match="password_hash"):
        OpcUaUser(name="scada", role="operator", password_hash="s3cret")
