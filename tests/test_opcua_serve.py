"""`autotuner serve --opcua` as a process: the demo's users, the printed endpoint, SIGTERM; the missing extra."""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import signal
import socket
import subprocess
import sys
import time
from typing import Any

import pytest
from asyncua import Client, ua

from api.opcua import INSTALL_HINT
from api.opcua.address_space import NAMESPACE
from helpers import free_port
from tests.opcua_client import Changes, call, now, until


async def _tbsy(url: str, user: str, password: str) -> bool:
    client = Client(url, timeout=10)
    client.set_user(user)
    client.set_password(password)
    async with client:
        idx = await client.get_namespace_index(NAMESPACE)
        return await client.get_node(ua.NodeId("TIC-101.TBSY", idx)).read_value()


def _opcua_process(daemon: int) -> int:
    """The pid of the daemon's OPC UA server process (a child of the daemon running ``api.opcua.server``)."""
    for task in os.listdir(f"/proc/{daemon}/task"):
        for child in open(f"/proc/{daemon}/task/{task}/children").read().split():
            if "api.opcua.server" in open(f"/proc/{child}/cmdline").read():
                return int(child)
    raise AssertionError(f"no OPC UA server process under the daemon {daemon}")


def _gone(pid: int) -> bool:
    """Whether process ``pid`` has ended (a zombie not reaped yet counts as ended)."""
    try:
        return open(f"/proc/{pid}/stat").read().rpartition(")")[2].split()[0] == "Z"
    except FileNotFoundError:
        return True


def _port_free(port: int) -> bool:
    """Whether nothing listens on ``port`` any more: a new server could bind it (as asyncua does, with
    SO_REUSEADDR: the closed connections' TIME_WAIT does not count)."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


def _serve_demo(port: int, opcua_port: int) -> tuple[subprocess.Popen[str], str]:
    """``autotuner serve --opcua-port`` (the demo) with known passwords, once its OPC UA server answers."""
    env = {**os.environ, "AUTOTUNER_TOKEN": "demo-operator", "AUTOTUNER_VIEWER_PASSWORD": "demo-viewer"}
    proc = subprocess.Popen([sys.executable, "-m", "autotuner.cli", "serve", "--port", str(port), "--opcua-port",
                             str(opcua_port)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    url = f"opc.tcp://127.0.0.1:{opcua_port}/autotuner/"
    deadline = time.monotonic() + 60
    while True:
        try:
            assert asyncio.run(_tbsy(url, "viewer", "demo-viewer")) is False
            return proc, url
        except (OSError, TimeoutError, ua.UaError):
            assert time.monotonic() < deadline and proc.poll() is None, "the OPC UA server did not come up"
            time.sleep(0.2)


def test_the_opcua_server_process_ends_with_a_daemon_killed_by_sigkill_and_frees_its_port():
    port, opcua_port = free_port(), free_port()
    proc, _ = _serve_demo(port, opcua_port)
    try:
        server = _opcua_process(proc.pid)
        assert not _port_free(opcua_port)
        proc.kill()  # no shutdown at all: the server sees its end of the socket pair close
        proc.wait(10)
        deadline = time.monotonic() + 30
        while not (_gone(server) and _port_free(opcua_port)):
            assert time.monotonic() < deadline, "the OPC UA server process outlived the daemon, holding its port"
            time.sleep(0.1)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_demo_accepts_operator_with_the_token_and_the_viewer_and_stops_on_sigterm():
    port, opcua_port = free_port(), free_port()
    proc, url = _serve_demo(port, opcua_port)
    try:
        line = proc.stdout.readline()
        assert line.startswith(f"autotuner OPC UA at {url}") and "operator" in line and "viewer" in line, line
        assert asyncio.run(_tbsy(url, "operator", "demo-operator")) is False
        with pytest.raises(ua.UaStatusCodeError):
            asyncio.run(_tbsy(url, "operator", "demo-viewer"))
        server = _opcua_process(proc.pid)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(40) in (0, -signal.SIGTERM)
        assert "Application shutdown complete" in proc.stderr.read()
        assert _gone(server) and _port_free(opcua_port)  # the daemon stopped its OPC UA process before exiting
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
    _, n, r, p, salt, hashed = digest.split("$")
    for bad in ("99999999999999999999", str(2**30), "1000"):  # overflows scrypt, 1 TiB per login, no power of 2
        with pytest.raises(ValueError, match=rf"(?s)password_hash.*N={bad}, r={r}, p={p} out of range"):
            OpcUaUser(name="scada", role="operator", password_hash="$".join(("scrypt", bad, r, p, salt, hashed)))
        assert not verify_password("s3cret", "$".join(("scrypt", bad, r, p, salt, hashed)))


def test_a_second_daemon_on_a_port_in_use_says_so_in_one_line_and_exits_3():
    # Another program (another daemon's OPC UA server) listens on the port: a clear line, not a traceback.
    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen()
        taken = other.getsockname()[1]
        env = {**os.environ, "AUTOTUNER_TOKEN": "demo-operator"}
        done = subprocess.run([sys.executable, "-m", "autotuner.cli", "serve", "--port", str(free_port()),
                               "--opcua-port", str(taken)], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 3, done.stderr
    assert (f"the OPC UA server could not start: cannot listen on 127.0.0.1:{taken}: address already in use"
            in done.stderr), done.stderr
    assert "--opcua-port" in done.stderr and "Traceback" not in done.stderr, done.stderr


def test_an_unusable_certificate_is_named_at_start_and_a_missing_one_at_load(tmp_path):
    from autotuner.service.config import ConfigError, load_config

    (tmp_path / "garbage.der").write_bytes(b"not a certificate")
    (tmp_path / "key.pem").write_bytes(b"not a key either")
    body = ("history: history.db\nloops:\n  - {id: A-1, sim: {plant: 'exp(-1*s)/(2*s+1)'}, ts: 0.2}\n"
            f"opcua: {{port: {free_port()}, certificate: CERT, private_key: key.pem}}\n")
    missing = tmp_path / "missing.yaml"
    missing.write_text(body.replace("CERT", "nowhere.der"))
    with pytest.raises(ConfigError, match=r"opcua\.certificate: .*nowhere\.der is not a file"):
        load_config(missing)
    garbage = tmp_path / "garbage.yaml"
    garbage.write_text(body.replace("CERT", "garbage.der"))
    done = subprocess.run([sys.executable, "-m", "autotuner.cli", "serve", "--config", str(garbage), "--port",
                           str(free_port())], env={**os.environ, "AUTOTUNER_TOKEN": "x"}, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 3, done.stderr
    assert f"opcua.certificate: {tmp_path / 'garbage.der'} is not a usable certificate" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr, done.stderr


def test_sigterm_while_tuning_hands_back_and_the_subscribed_client_sees_it_before_the_server_goes(tmp_path):
    # The monitor publishes once a minute here: what the client sees of the hand-back is what the stop sends.
    port, opcua_port = free_port(), free_port()
    config = tmp_path / "daemon.yaml"
    config.write_text(f"history: history.db\nopcua: {{port: {opcua_port}}}\nloops:\n"
                      "  - {id: TIC-101, sim: {plant: 'exp(-1*s)/(5*s+1)'}, ts: 0.1, monitor_period: 60,\n"
                      "     tuning: {amp: 5}, limits: {pv: [0, 100], mv: [0, 100]}}\n")
    env = {**os.environ, "AUTOTUNER_TOKEN": "demo-operator"}
    proc = subprocess.Popen([sys.executable, "-m", "autotuner.cli", "serve", "--config", str(config), "--port",
                             str(port)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    url = f"opc.tcp://127.0.0.1:{opcua_port}/autotuner/"

    async def main() -> tuple[int, list[bool], list[Any]]:
        deadline = time.monotonic() + 60
        while True:
            try:
                c = Client(url, timeout=10)
                c.set_user("operator")
                c.set_password("demo-operator")
                await c.connect()
                break
            except (OSError, TimeoutError, ua.UaError):
                assert time.monotonic() < deadline and proc.poll() is None, "the OPC UA server did not come up"
                await asyncio.sleep(0.2)
        server = _opcua_process(proc.pid)
        changes = Changes()
        try:
            idx = await c.get_namespace_index(NAMESPACE)
            tbsy = c.get_node(ua.NodeId("TIC-101.TBSY", idx))
            changes.names[tbsy.nodeid] = "TBSY"
            sub = await c.create_subscription(50, changes)
            await sub.subscribe_data_change([tbsy])
            await sub.subscribe_events(c.nodes.server, c.get_node(ua.NodeId("TuningErrorEventType", idx)))
            assert (await call(c, "TIC-101", "AutoTuningOn")).StatusCode.is_good()
            await until(lambda: now(changes.values.get("TBSY", [])[-1:] == [True]), 30, "TBSY rising")
            proc.send_signal(signal.SIGTERM)
            await until(lambda: now(changes.values["TBSY"][-1] is False and len(changes.events) == 1), 60,
                        "TBSY falling and the TE event before the server stopped")
        finally:
            with contextlib.suppress(Exception):  # the server is gone (or going)
                await c.disconnect()
        return server, changes.values["TBSY"], changes.events

    try:
        server, values, events = asyncio.run(asyncio.wait_for(main(), 180))
        assert values[-1] is False and (events[0].Loop, events[0].Ite) == ("TIC-101", 1.0), (values, events)
        assert proc.wait(60) == 0  # every loop handed back
        assert "Traceback" not in proc.stderr.read()
        assert _gone(server) and _port_free(opcua_port)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
