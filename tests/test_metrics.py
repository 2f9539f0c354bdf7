"""``GET /metrics``: the daemon's own health in the Prometheus text format, parsed by prometheus_client's parser."""

from __future__ import annotations

import time

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from api.app import create_app
from test_api import API, CONFIG, OPERATOR, VIEWER, auth


def scrape(client: TestClient) -> dict[str, dict[tuple[tuple[str, str], ...], float]]:
    """Every sample of the exposition: metric sample name → labels → value."""
    r = client.get("/metrics", headers=auth(VIEWER))
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain"), r.text
    out: dict[str, dict[tuple[tuple[str, str], ...], float]] = {}
    for family in text_string_to_metric_families(r.text):
        for sample in family.samples:
            out.setdefault(sample.name, {})[tuple(sorted(sample.labels.items()))] = sample.value
    return out


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(CONFIG, env_token=OPERATOR)) as c:
        yield c


def test_metrics_need_a_token_and_say_what_the_daemon_holds(client):
    assert client.get("/metrics").status_code == 401
    m = scrape(client)
    assert m["autotuner_loops"][()] == len(CONFIG.loops) and m["autotuner_loops_tuning"][()] == 0.0
    assert m["autotuner_health_assessments_total"][()] == client.app.state.manager.health_assessed
    assert m["autotuner_health_cpu_seconds_total"][()] >= 0.0
    assert m["autotuner_history_queue"][()] >= 0.0
    assert m["autotuner_history_failing"][()] == 0.0
    assert "process_resident_memory_bytes" in m  # the process's own figures too


def test_a_tuning_shows_in_the_sessions_the_lateness_and_the_analysis_cpu(client):
    before = scrape(client)
    assert client.post(f"{API}/loops/TIC-101/tune", headers=auth(OPERATOR), json={}).status_code == 202
    deadline = time.monotonic() + 120
    while client.get(f"{API}/loops/TIC-101", headers=auth(VIEWER)).json()["tbsy"]:
        assert time.monotonic() < deadline, "the tuning did not end"
        time.sleep(0.2)
    time.sleep(1.0)  # the field hands its timings over every 0.5 s
    status = client.get(f"{API}/loops/TIC-101", headers=auth(VIEWER)).json()
    session = client.get(f"{API}/sessions/{status['session']}", headers=auth(VIEWER)).json()
    samples = session["result"]["experiment"]["samples"]
    m = scrape(client)
    ok = (("code", "0"), ("name", "OK"))
    assert m["autotuner_sessions_total"][ok] == before.get("autotuner_sessions_total", {}).get(ok, 0.0) + 1
    late = m["autotuner_sample_lateness_seconds_count"][()] - \
        before.get("autotuner_sample_lateness_seconds_count", {}).get((), 0.0)
    # Every sample of the session was timed (and a read or two after its end, for a sample not used).
    assert samples <= late <= samples + 3, (samples, late)
    buckets = m["autotuner_sample_lateness_seconds_bucket"]
    counts = [buckets[(("le", le),)] for le in ("0.001", "0.01", "0.1", "1", "+Inf")]
    assert counts == sorted(counts) and counts[-1] == m["autotuner_sample_lateness_seconds_count"][()]
    periods = m["autotuner_analysis_cpu_seconds_count"][()]
    assert periods >= session["result"]["experiment"]["periods"] - 1  # one analysis per period at least
    assert m["autotuner_loops_tuning"][()] == 0.0


def test_an_open_event_stream_is_counted(client):
    with client.stream("GET", f"{API}/loops/LIC-201/events", headers=auth(VIEWER)) as r:
        assert next(r.iter_lines()).startswith("event: state")
        assert scrape(client)["autotuner_event_streams"][()] == 1.0
