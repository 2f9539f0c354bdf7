"""What the API accepts: strict TUNE bodies (no coercion), relay amplitudes bounded per loop, and — against a real
``autotuner serve`` process — authentication before the body is read, and a body-size limit before it is read."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import httpx
import pytest
import yaml
from fastapi.testclient import TestClient

from api.app import create_app
from api.auth import token_hash
from api.gate import MAX_BODY
from autotuner.service.config import DEFAULT_MAX_AMP, ConfigError, DaemonConfig, load_config
from helpers import Daemon

OPERATOR, VIEWER = "op-secret", "view-secret"
API = "/api/v1"
# LIM has MV limits (its amplitude bound is their span, 40); FREE has none (tuning.max_amp, default 100).
LOOPS = [{"id": "LIM", "sim": {"plant": "exp(-s)/(2*s+1)"}, "ts": 0.1, "limits": {"mv": [30.0, 70.0]},
          "tuning": {"amp": 5.0}},
         {"id": "FREE", "sim": {"plant": "exp(-s)/(2*s+1)"}, "ts": 0.1, "tuning": {"amp": 5.0}}]


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@pytest.fixture(scope="module")
def client():
    config = DaemonConfig.model_validate({"history": ":memory:", "loops": LOOPS, "samplers": 0, "tokens": [
        {"name": "hmi", "role": "viewer", "sha256": token_hash(VIEWER)}]})
    with TestClient(create_app(config, env_token=OPERATOR), raise_server_exceptions=False) as c:
        yield c


@pytest.mark.parametrize("body, field", [
    ({"apply": "yes"}, "apply"), ({"apply": 0}, "apply"), ({"apply": 1}, "apply"), ({"apply": "true"}, "apply"),
    ({"amp": "5"}, "amp"), ({"amp": True}, "amp"), ({"phase": "135"}, "phase"), ({"ms": None, "amp": [5]}, "amp"),
    ({"controller": "pi"}, "controller"),
])
def test_tune_bodies_of_the_wrong_json_type_are_refused_naming_the_field_and_nothing_starts(client, body, field):
    response = client.post(f"{API}/loops/FREE/tune", json=body, headers=auth(OPERATOR))
    assert response.status_code == 422, response.text
    assert response.json()["code"] == "invalid" and response.json()["message"].startswith(f"{field}: ")
    assert client.get(f"{API}/loops/FREE", headers=auth(VIEWER)).json()["tbsy"] is False


@pytest.mark.parametrize("loop_id, amp, bound", [("LIM", 40.5, 40.0), ("FREE", 1e30, DEFAULT_MAX_AMP),
                                                 ("FREE", 100.5, DEFAULT_MAX_AMP)])
def test_an_amplitude_above_the_loops_bound_is_refused_and_nothing_starts(client, loop_id, amp, bound):
    response = client.post(f"{API}/loops/{loop_id}/tune", json={"amp": amp}, headers=auth(OPERATOR))
    assert response.status_code == 422, response.text
    assert response.json()["code"] == "invalid"
    assert response.json()["message"].startswith("amp: ") and f"largest relay amplitude {bound:g}" in \
        response.json()["message"]
    assert client.get(f"{API}/loops/{loop_id}", headers=auth(VIEWER)).json()["tbsy"] is False


def test_an_integer_amplitude_within_the_bound_is_a_number_and_accepted(client):
    response = client.post(f"{API}/loops/LIM/tune", json={"amp": 4, "apply": False}, headers=auth(OPERATOR))
    assert response.status_code == 202, response.text
    assert client.post(f"{API}/loops/LIM/break", headers=auth(OPERATOR)).status_code == 202


def test_a_configured_amplitude_above_the_bound_is_a_config_error(tmp_path: Path):
    path = tmp_path / "d.yaml"
    path.write_text(yaml.safe_dump({"loops": [{**LOOPS[0], "tuning": {"amp": 41.0}}]}))
    with pytest.raises(ConfigError, match=r"loops\[0\]: tuning.amp 41 is above the loop's largest relay amplitude 40"):
        load_config(path)
    path.write_text(yaml.safe_dump({"loops": [{**LOOPS[1], "tuning": {"amp": 150.0, "max_amp": 200.0}}]}))
    assert load_config(path).loops[0].max_amp == 200.0


# -- a real daemon process ------------------------------------------------------


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    folder = tmp_path_factory.mktemp("gate")
    config = folder / "daemon.yaml"
    config.write_text(yaml.safe_dump({"history": ":memory:", "loops": LOOPS, "tokens": [
        {"name": "hmi", "role": "viewer", "sha256": token_hash(VIEWER)}]}))
    with Daemon(config, token=OPERATOR) as d:
        yield d


def _rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise AssertionError("no VmRSS")


def _raw_post(port: int, path: str, headers: dict[str, str], body_bytes: int, chunked: bool = False) -> tuple[
        int, bytes, float]:
    """POST ``body_bytes`` of JSON-ish filler over a raw socket while reading the answer; (status, body, seconds)."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=30)
    head = f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
    head += "".join(f"{k}: {v}\r\n" for k, v in headers.items())
    head += "Transfer-Encoding: chunked\r\n\r\n" if chunked else f"Content-Length: {body_bytes}\r\n\r\n"
    start = time.monotonic()
    sock.sendall(head.encode())

    def feed() -> None:  # the body, until the daemon stops listening (it answers without reading it)
        block = b" " * 65536
        sent = 0
        try:
            while sent < body_bytes:
                n = min(len(block), body_bytes - sent)
                sock.sendall(f"{n:x}\r\n".encode() + block[:n] + b"\r\n" if chunked else block[:n])
                sent += n
            if chunked:
                sock.sendall(b"0\r\n\r\n")
        except OSError:
            pass

    writer = threading.Thread(target=feed, daemon=True)
    writer.start()
    answer = b""
    while b"\r\n\r\n" not in answer or len(answer.split(b"\r\n\r\n", 1)[1]) < 20:
        data = sock.recv(65536)
        if not data:
            break
        answer += data
    elapsed = time.monotonic() - start
    sock.close()
    writer.join(10)
    status = int(answer.split(b" ", 2)[1])
    return status, answer.split(b"\r\n\r\n", 1)[1], elapsed


@pytest.mark.parametrize("headers, status, code", [({}, 401, "unauthorized"),
                                                   (auth(VIEWER), 403, "forbidden"),
                                                   (auth(OPERATOR), 413, "too_large")])
def test_a_100_mb_body_is_answered_before_it_is_read(daemon, headers, status, code):
    rss = _rss_kib(daemon.proc.pid)
    got, body, seconds = _raw_post(daemon.port, f"{API}/loops/FREE/tune", headers, 100_000_000)
    assert got == status and f'"code":"{code}"'.encode() in body.replace(b" ", b""), body
    assert seconds < 5.0  # the body itself would take longer to read and parse (issue 12: 3.4 s, +650 MB)
    assert _rss_kib(daemon.proc.pid) - rss < 20_000


def test_a_chunked_body_is_read_only_up_to_the_limit(daemon):
    got, body, _ = _raw_post(daemon.port, f"{API}/loops/FREE/tune", auth(OPERATOR), 10 * MAX_BODY, chunked=True)
    assert got == 413 and b"too_large" in body
    got, body, _ = _raw_post(daemon.port, f"{API}/loops/FREE/tune", {}, 10 * MAX_BODY, chunked=True)
    assert got == 401


def test_a_small_body_passes_the_gate_unchanged(daemon):
    bad = httpx.post(f"{daemon.base}/loops/FREE/tune", json={"apply": "yes"}, headers=daemon.headers)
    assert bad.status_code == 422 and bad.json()["message"].startswith("apply: ")
    good = httpx.post(f"{daemon.base}/loops/FREE/tune", json={"amp": 2.5, "apply": False}, headers=daemon.headers)
    assert good.status_code == 202, good.text
    session = httpx.get(f"{daemon.base}/sessions/{good.json()['session']}", headers=daemon.headers).json()
    assert session["request"]["amp"] == 2.5
    assert httpx.post(f"{daemon.base}/loops/FREE/break", headers=daemon.headers).status_code == 202


def test_tune_on_a_nan_pv_is_409_with_its_code_and_the_loop_untouched(client):
    plc = client.app.state.manager.loops["FREE"].plc
    plc.nan_pv = True
    try:
        response = client.post(f"{API}/loops/FREE/tune", headers=auth(OPERATOR))
    finally:
        plc.nan_pv = False
    assert response.status_code == 409 and response.json()["code"] == "pv_invalid", response.text
    assert plc.mode.name == "AUTO"
