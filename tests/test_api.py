"""The REST API through HTTP: auth and roles, JSON errors, TUNE/TBRK/409s, history, events, OpenAPI."""

from __future__ import annotations

import dataclasses

import asyncio
import contextlib
import json
import queue
import socket
import threading
import time
from collections.abc import Iterator

import httpx
import pytest
import uvicorn
from fastapi.testclient import TestClient

from api.app import create_app
from api.models import LoopStatus, UnitsRecord
from api.auth import token_hash
from autotuner.service.config import DaemonConfig, Token
from autotuner.service.demo import demo_config
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.control.gains import Gains
from autotuner.engine.outcome import Code
from autotuner.service.remote_tuning import PLANT_TICKS_PER_SAMPLE, served
from autotuner.engine.simulated_tuning import default_sample_time
from drivers.link import Mode
from drivers.simplc import SimulatedPlc

OPERATOR, VIEWER, ADMIN = "op-secret", "view-secret", "admin-secret"
# 25 ms of wall time per sample: converges on a busy CI machine too.
SPEED = 12.0
API = "/api/v1"
# The demo plant's loops (drivers/data/demo_plant.yaml): the three healthy ones first, then the faulty ones.
DEMO = ["TIC-101", "LIC-201", "FIC-301", "TIC-102", "FIC-302", "TIC-103", "LIC-202"]


# samplers 0: the simulated plants in this process, where the tests read them (tests/test_sampler.py runs the
# daemon with its sampler processes).
CONFIG = demo_config(SPEED).model_copy(update={"samplers": 0, "tokens": [
    Token(name="hmi", role="viewer", sha256=token_hash(VIEWER)),
    Token(name="root", role="admin", sha256=token_hash(ADMIN)),
]})


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@pytest.fixture
def client():
    with TestClient(create_app(CONFIG, env_token=OPERATOR), raise_server_exceptions=False) as c:
        yield c


def wait_idle(client: TestClient, loop_id: str, timeout: float = 60.0, token: str = VIEWER) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status = client.get(f"{API}/loops/{loop_id}", headers=auth(token)).json()
        if not status["tbsy"]:
            return status
        time.sleep(0.1)
    raise AssertionError(f"{loop_id} still busy after {timeout} s")


def test_health_needs_no_token_and_everything_else_does(client):
    assert client.get(f"{API}/health").json() == {"status": "ok", "loops": len(DEMO)}
    for method, path in (("GET", "/loops"), ("GET", "/loops/TIC-101"), ("POST", "/loops/TIC-101/tune"),
                         ("POST", "/loops/TIC-101/break"), ("GET", "/loops/TIC-101/history"),
                         ("GET", "/sessions/x"), ("GET", "/loops/TIC-101/events"), ("GET", "/events")):
        r = client.request(method, API + path)
        assert r.status_code == 401, path
        assert r.json()["code"] == "unauthorized" and r.headers["www-authenticate"] == "Bearer"
    r = client.get(f"{API}/loops", headers=auth("wrong"))
    assert r.status_code == 401 and "token" in r.json()["message"]


def test_viewer_reads_but_cannot_write(client):
    loops = client.get(f"{API}/loops", headers=auth(VIEWER)).json()
    assert [loop["id"] for loop in loops] == DEMO
    assert loops[0]["tbsy"] is False and loops[0]["te"] is False and loops[0]["ite"] == 0
    for path in ("/loops/TIC-101/tune", "/loops/TIC-101/break"):
        r = client.post(API + path, headers=auth(VIEWER))
        assert r.status_code == 403 and r.json()["code"] == "forbidden"
    assert client.get(f"{API}/loops/TIC-101", headers=auth(VIEWER)).json()["tbsy"] is False  # no state change


def test_unknown_loop_or_session_is_404(client):
    for method, path in (("GET", "/loops/nope"), ("POST", "/loops/nope/tune"), ("POST", "/loops/nope/break"),
                         ("GET", "/loops/nope/history"), ("GET", "/loops/nope/events"), ("GET", "/sessions/nope"),
                         ("GET", "/no/such/path")):
        r = client.request(method, API + path, headers=auth(OPERATOR))
        assert r.status_code == 404, path
        assert r.json()["code"] == "not_found" and r.json()["message"]


@pytest.mark.parametrize("body, field", [
    ({"amp": -1}, "amp"), ({"phase": 200}, "phase"), ({"controller": "PIDX"}, "controller"),
    ({"ms": "high"}, "ms"), ({"ampp": 2}, "ampp"), ({"apply": "perhaps"}, "apply"),
])
def test_invalid_body_is_422_naming_the_field(client, body, field):
    r = client.post(f"{API}/loops/TIC-101/tune", headers=auth(OPERATOR), json=body)
    assert r.status_code == 422
    assert r.json()["code"] == "invalid" and r.json()["message"].startswith(f"{field}: ")
    assert client.get(f"{API}/loops/TIC-101", headers=auth(VIEWER)).json()["tbsy"] is False


def test_break_while_idle_is_409(client):
    r = client.post(f"{API}/loops/LIC-201/break", headers=auth(OPERATOR))
    assert r.status_code == 409 and r.json()["code"] == "idle"


def test_tune_through_http_to_success_with_gains_applied(client):
    plc = client.app.state.manager.loops["TIC-101"].plc
    before = plc.gains
    r = client.post(f"{API}/loops/TIC-101/tune", headers=auth(OPERATOR), json={"apply": True, "controller": "PI"})
    assert r.status_code == 202
    sid = r.json()["session"]
    assert r.json() == {"loop": "TIC-101", "session": sid}
    busy = client.post(f"{API}/loops/TIC-101/tune", headers=auth(ADMIN))
    assert busy.status_code == 409 and busy.json()["code"] == "busy"
    running = client.get(f"{API}/loops/TIC-101", headers=auth(VIEWER)).json()
    assert running["tbsy"] is True and running["session"] == sid
    done = wait_idle(client, "TIC-101")
    assert done["te"] is False and done["ite"] == 0 and done["message"] == "ok"
    assert done["point"]["phase_deg"] == pytest.approx(-135.0, abs=1.5)
    gains = Gains.from_json(done["gains"])
    assert plc.gains.k == pytest.approx(gains.k) and plc.mode is Mode.AUTO
    history = client.get(f"{API}/loops/TIC-101/history", headers=auth(VIEWER)).json()
    assert [h["id"] for h in history] == [sid]
    assert history[0]["user"] == "AUTOTUNER_TOKEN" and history[0]["outcome"] == "success"
    assert "trace" not in history[0]
    record = client.get(f"{API}/sessions/{sid}", headers=auth(VIEWER)).json()
    assert record["gains_before"]["pk"] == pytest.approx(before.k)
    assert record["gains_after"]["pk"] == pytest.approx(gains.k)
    assert record["request"]["apply"] is True and len(record["trace"]["t"]) > 10


def test_tbrk_through_http_restores_the_loop_and_history_is_newest_first(client):
    plc = client.app.state.manager.loops["FIC-301"].plc
    gains = plc.gains
    first = client.post(f"{API}/loops/FIC-301/tune", headers=auth(OPERATOR)).json()["session"]
    time.sleep(0.3)
    r = client.post(f"{API}/loops/FIC-301/break", headers=auth(OPERATOR))
    assert r.status_code == 202 and r.json()["session"] == first
    status = wait_idle(client, "FIC-301")
    assert status["te"] is True and status["ite"] == int(Code.ABORTED)
    assert plc.mode is Mode.AUTO and plc.gains == gains
    second = client.post(f"{API}/loops/FIC-301/tune", headers=auth(OPERATOR)).json()["session"]
    client.post(f"{API}/loops/FIC-301/break", headers=auth(OPERATOR))
    wait_idle(client, "FIC-301")
    history = client.get(f"{API}/loops/FIC-301/history", headers=auth(VIEWER)).json()
    assert [h["id"] for h in history] == [second, first]
    assert history[1]["code"] == int(Code.ABORTED) and history[1]["outcome"] == "failure"


def test_openapi_describes_the_endpoints(client):
    spec = client.get(f"{API}/openapi.json").json()
    assert {f"{API}/loops", f"{API}/loops/{{loop_id}}", f"{API}/loops/{{loop_id}}/tune",
            f"{API}/loops/{{loop_id}}/break", f"{API}/loops/{{loop_id}}/events", f"{API}/loops/{{loop_id}}/history",
            f"{API}/sessions/{{sid}}", f"{API}/health", f"{API}/events"} <= spec["paths"].keys()
    assert "409" in spec["paths"][f"{API}/loops/{{loop_id}}/tune"]["post"]["responses"]


@contextlib.contextmanager
def server():
    """The app behind a real uvicorn server on an ephemeral localhost port; yields its base URL."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    srv = uvicorn.Server(uvicorn.Config(create_app(CONFIG, env_token=OPERATOR), log_level="warning"))
    thread = threading.Thread(target=srv.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    try:
        while not srv.started:
            time.sleep(0.02)
        yield f"http://127.0.0.1:{port}"
    finally:
        srv.should_exit = True
        thread.join(30)
        sock.close()


def sse(stream: httpx.Response) -> Iterator[tuple[str, dict]]:
    """The (event type, data) pairs of a Server-Sent Events response as they arrive."""
    assert stream.headers["content-type"].startswith("text/event-stream")
    kind = "message"
    for line in stream.iter_lines():
        if line.startswith("event: "):
            kind = line[7:]
        elif line.startswith("data: "):
            yield kind, json.loads(line[6:])


def test_events_stream_samples_and_state_changes():
    with server() as url, httpx.Client(base_url=url + API, headers=auth(OPERATOR), timeout=30) as http:
        events: list[tuple[str, dict]] = []
        with http.stream("GET", "/loops/TIC-101/events") as stream:
            for event in sse(stream):
                events.append(event)
                if len(events) == 2:
                    assert http.post("/loops/TIC-101/tune").status_code == 202
                if sum(k == "sample" for k, _ in events) >= 40:
                    break
        assert http.post("/loops/TIC-101/break").status_code == 202
    # The stream opens with the state and the replay of the trend kept (here the monitor's readings so far); then
    # state, sample (monitor or experiment) events, and the health summary's change the tuning makes (pending: the
    # samples before it were another loop's).
    assert events[0][0] == "state" and events[0][1]["tbsy"] is False
    assert events[1][0] == "replay" and events[1][1]["session"] is None
    assert set(events[1][1]) == {"session", "time", "t", "pv", "sp", "mv", "relay"}
    assert {k for k, _ in events[2:]} == {"state", "sample", "health"}
    health = [d for k, d in events if k == "health"]
    assert health[-1]["loop"] == "TIC-101" and health[-1]["state"] == "pending" and health[-1]["flags"] == []
    assert next(d for k, d in events[2:] if k == "state")["tbsy"] is True
    samples = [d for k, d in events if k == "sample"]
    assert {"t", "pv", "mv", "relay", "filter_phase_deg", "ite", "stage", "progress"} <= samples[-1].keys()
    # The experiment's samples (a monitor reading, without t, may come first on a loaded machine: the monitor reads
    # every 0.25 s until the session starts).
    experiment = [d for d in samples if "t" in d]
    assert experiment[-1]["t"] > experiment[0]["t"]


def test_the_overview_stream_carries_every_loops_state_and_throttled_live_values():
    from api.events import LIVE_PERIOD

    with server() as url, httpx.Client(base_url=url + API, headers=auth(VIEWER), timeout=30) as http:
        events: list[tuple[str, dict]] = []
        tuning_since = None
        with http.stream("GET", "/events") as stream:
            for kind, data in sse(stream):
                events.append((kind, data))
                if len(events) == len(DEMO):
                    assert httpx.post(f"{url}{API}/loops/TIC-101/tune", headers=auth(OPERATOR)).status_code == 202
                if kind == "state" and data["id"] == "TIC-101" and data["tbsy"]:
                    tuning_since = tuning_since or time.monotonic()
                # 3 s of wall time into the tuning: many experiment samples (about 20 a second), few live events.
                if tuning_since is not None and time.monotonic() > tuning_since + 3.0:
                    break
        assert httpx.post(f"{url}{API}/loops/TIC-101/break", headers=auth(OPERATOR)).status_code == 202
    # Opens with every loop's state in the config's order (the status of GET /loops/{id}); then state and live only.
    assert [k for k, _ in events[:len(DEMO)]] == ["state"] * len(DEMO)
    assert [d["id"] for _, d in events[:len(DEMO)]] == DEMO
    assert set(events[0][1]) == {f.name for f in dataclasses.fields(LoopStatus)}
    assert {"state", "live"} <= {k for k, _ in events[len(DEMO):]} <= {"state", "live", "health"}
    live = [d for k, d in events if k == "live"]
    assert {d["loop"] for d in live} == set(DEMO)  # the idle loops' monitor readings too
    tuning = [d for d in live if d["loop"] == "TIC-101" and "relay" in d]
    assert tuning and {"time", "pv", "sp", "mv", "relay", "ite", "stage", "progress"} <= tuning[-1].keys()
    idle = [d for d in live if d["loop"] == "LIC-201"]
    assert set(idle[-1]) == {"loop", "time", "pv", "sp", "mv", "mode"}
    # At most one live event per loop every LIVE_PERIOD (the newest sample): the experiment's samples are thinned.
    # (TIC-101's last one left out: its experiment, 2.4 periods on the demo's noisy loop since the noisy model rule,
    # can end within the 3 s, and then the last live event carries the experiment's last sample, whenever it came
    # after the one before — 0.1 s of samples in a CI run.)
    for loop_id in ("TIC-101", "LIC-201"):
        times = [d["time"] for d in live if d["loop"] == loop_id]
        times = times[:-1] if loop_id == "TIC-101" else times
        assert len(times) >= 2, loop_id
        gaps = [b - a for a, b in zip(times, times[1:])]
        # Two sends are LIVE_PERIOD apart; the samples they carry, within one sample interval of that.
        assert min(gaps) > LIVE_PERIOD - 0.3, (loop_id, gaps)


@contextlib.contextmanager
def modbus_plant(plc: SimulatedPlc, speed: float):
    """``plc`` run ``speed`` × real time behind a Modbus TCP server on localhost, in its own thread; yields the URL."""
    urls: queue.Queue[str] = queue.Queue()
    done = threading.Event()

    async def main() -> None:
        async with served(plc, "modbus", speed) as (url, _):
            urls.put(url)
            while not done.is_set():
                await asyncio.sleep(0.05)

    thread = threading.Thread(target=asyncio.run, args=(main(),), daemon=True)
    thread.start()
    try:
        yield urls.get(timeout=30)
    finally:
        done.set()
        thread.join(30)


def test_tune_over_modbus_tcp_through_http_writes_the_gains():
    plant = "exp(-s)/(2*s+1)"
    ts = default_sample_time(parse_process(plant)) * 100 / 40
    plc = SimulatedPlc(parse_process(plant), ts=ts / PLANT_TICKS_PER_SAMPLE)
    with modbus_plant(plc, 10.0) as url:
        config = DaemonConfig.model_validate({"history": ":memory:", "loops": [
            {"id": "TIC-1", "link": url, "ts": ts, "speed": 10.0, "apply": True,
             "tuning": {"amp": 5.0, "time_limit": 500.0}}]})
        with TestClient(create_app(config, env_token=OPERATOR)) as client:
            sid = client.post(f"{API}/loops/TIC-1/tune", headers=auth(OPERATOR)).json()["session"]
            assert client.post(f"{API}/loops/TIC-1/tune", headers=auth(OPERATOR)).status_code == 409
            done = wait_idle(client, "TIC-1", token=OPERATOR)
            record = client.get(f"{API}/sessions/{sid}", headers=auth(OPERATOR)).json()
    assert done["te"] is False and done["ite"] == 0, done["message"]
    assert record["gains_after"]["pk"] == pytest.approx(done["gains"]["pk"])  # read back over Modbus
    assert plc.gains.k == pytest.approx(done["gains"]["pk"], rel=1e-3) and plc.mode is Mode.AUTO


def test_whoami_names_the_token_and_its_role_and_status_carries_the_loop_defaults(client):
    assert client.get(f"{API}/whoami", headers=auth(VIEWER)).json() == {"name": "hmi", "role": "viewer"}
    assert client.get(f"{API}/whoami", headers=auth(ADMIN)).json() == {"name": "root", "role": "admin"}
    assert client.get(f"{API}/whoami", headers=auth(OPERATOR)).json()["role"] == "operator"
    assert client.get(f"{API}/whoami").status_code == 401
    loop = CONFIG.loops[0]
    defaults = client.get(f"{API}/loops/{loop.id}", headers=auth(VIEWER)).json()["defaults"]
    assert defaults == {"controller": loop.tuning.controller, "amp": loop.tuning.amp,
                        "hysteresis": loop.tuning.hysteresis, "phase": loop.tuning.phase, "ms": loop.tuning.ms,
                        "apply": loop.apply}


def test_the_page_is_served_with_a_strict_content_security_policy_and_the_api_with_nosniff(client):
    page = client.get("/")
    assert page.status_code == 200 and "<main" in page.text
    policy = page.headers["Content-Security-Policy"]
    assert "default-src 'self'" in policy and "frame-ancestors 'none'" in policy and "unsafe" not in policy
    assert page.headers["X-Frame-Options"] == "DENY" and page.headers["X-Content-Type-Options"] == "nosniff"
    assert client.get("/app.js").headers["Content-Security-Policy"] == policy
    api = client.get(f"{API}/loops", headers=auth(VIEWER))
    assert api.headers["X-Content-Type-Options"] == "nosniff" and "Content-Security-Policy" not in api.headers


def test_codes_lists_every_outcome_code_for_the_page(client):
    from autotuner.engine.outcome import MESSAGES, WARNINGS

    assert client.get(f"{API}/codes").status_code == 401  # reads need a viewer (design.md)
    codes = client.get(f"{API}/codes", headers=auth(VIEWER)).json()
    assert [c["value"] for c in codes] == [int(c) for c in Code]
    for c in codes:
        code = Code(c["value"])
        assert c == {"value": int(code), "name": code.name, "message": MESSAGES[code], "warning": code in WARNINGS}


def test_status_has_exactly_the_documented_keys_and_the_loops_units(client):
    statuses = client.get(f"{API}/loops", headers=auth(VIEWER)).json()
    for status in statuses:
        # The REST contract (docs/daemon.md): these keys and no others; units from the config.
        assert set(status) == {f.name for f in dataclasses.fields(LoopStatus)}
        assert set(status["units"]) == {f.name for f in dataclasses.fields(UnitsRecord)} == {
            "pv", "mv", "decimals", "pv_range", "mv_range"}
        assert status["units"] == CONFIG.loop(status["id"]).units.as_json()
    assert next(s for s in statuses if s["id"] == "TIC-101")["units"] == {
        "pv": "°C", "mv": "%", "decimals": 2, "pv_range": None, "mv_range": None}
    config = DaemonConfig.model_validate({"history": ":memory:", "loops": [
        {"id": "A", "sim": {"plant": "1/(s+1)"}, "ts": 0.1, "units": {"pv": "bar", "pv_range": [0, 16]}},
        {"id": "B", "sim": {"plant": "1/(s+1)"}, "ts": 0.1}]})
    with TestClient(create_app(config, env_token=OPERATOR)) as other:
        a, b = (other.get(f"{API}/loops/{i}", headers=auth(OPERATOR)).json()["units"] for i in "AB")
    assert a == {"pv": "bar", "mv": "", "decimals": None, "pv_range": [0.0, 16.0], "mv_range": None}
    assert b == {"pv": "", "mv": "", "decimals": None, "pv_range": None, "mv_range": None}


def test_the_docs_pages_are_served_offline_under_their_own_policies(client):
    from api.docs import DOCS_POLICY, REDOC_LOGO, REDOC_POLICY

    swagger, redoc = client.get(f"{API}/docs"), client.get(f"{API}/redoc")
    assert swagger.headers["Content-Security-Policy"] == DOCS_POLICY
    assert redoc.headers["Content-Security-Policy"] == REDOC_POLICY and "worker-src 'self' blob:" in REDOC_POLICY
    assert "unsafe-eval" not in REDOC_POLICY and "script-src 'self';" in REDOC_POLICY
    # Every script and style the pages name is the daemon's own (relative URLs), and is served.
    import re

    for page in (swagger, redoc):
        for url in re.findall(r'(?:src|href)="([^"]+)"', page.text):
            assert "//" not in url, url
            assert client.get(f"{API}/{url}").status_code == 200, url
    bundle = client.get(f"{API}/docs/redoc.standalone.js")
    assert bundle.headers["content-type"].startswith("text/javascript") and len(bundle.content) > 500_000
    assert REDOC_LOGO not in bundle.text and "cdn." not in bundle.text
