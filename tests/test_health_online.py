"""The daemon's online health assessment (docs/health.md, "Online") with real daemons over REST.

A daemon of the demo plant's loops (drivers/data/demo_plant.yaml: the healthy TIC-101, the sticky valve
TIC-102, LIC-202 left in MAN) at 40× real time, monitored every 2 plant seconds, assessed over a 20-minute
window every 30 plant seconds: the sticky valve comes out ``stiction``/``check_valve`` (never ``retune``), the
loop in MAN ``manual``/``put_in_auto``, the healthy one without flags. A tuning makes its loop pending again
and keeps the assessment before it; the assessments survive a restart. Every wait is on a condition, with
deadlines far beyond what an idle machine needs.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from fastapi.testclient import TestClient

from api.app import create_app
from autotuner.service.demo import demo_config
from tests.helpers import Daemon

LOOPS = ("TIC-101", "TIC-102", "LIC-202")
SPEED = 40.0
WINDOW, EVERY = 1800.0, 30.0  # plant s: 45 and 0.75 wall seconds at 40× (a dozen of TIC-102's cycles)


def write_config(tmp: Path, window: float = WINDOW) -> Path:
    """The demo plant's three loops at :data:`SPEED` with a health window of ``window`` plant s, history in
    ``tmp``; the config file's path."""
    config = demo_config(SPEED).model_dump(mode="json", exclude_defaults=True)
    config["history"] = str(tmp / "history.sqlite")
    config["loops"] = [loop for loop in config["loops"] if loop["id"] in LOOPS]
    for loop in config["loops"]:
        loop["health"] = {"window": window, "every": EVERY}
    path = tmp / "daemon.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def get(daemon: Daemon, path: str) -> Any:
    r = httpx.get(f"{daemon.base}{path}", headers=daemon.headers, timeout=30)
    assert r.status_code == 200, (path, r.text)
    return r.json()


def summary(daemon: Daemon, loop_id: str) -> dict[str, Any]:
    return get(daemon, f"/loops/{loop_id}")["health"]


def assessed(daemon: Daemon, loop_id: str, flags: set[str], recommendation: str, timeout: float) -> dict[str, Any]:
    """The loop's health (``GET /loops/{id}/health``) once an assessment has ``flags`` (at least) and
    ``recommendation``; AssertionError after ``timeout`` wall seconds."""
    found: list[dict[str, Any]] = []

    def seen() -> bool:
        detail = get(daemon, f"/loops/{loop_id}/health")
        assessment = detail["assessment"]
        if assessment is None or not flags <= set(assessment["flags"]):
            return False
        found.append(detail)
        return assessment["recommendation"] == recommendation

    daemon.wait_until(seen, timeout, f"{loop_id} assessed {sorted(flags)} → {recommendation}")
    return found[-1]


def test_the_demo_plants_loops_are_told_apart_online_kept_and_pending_again_after_a_tuning(tmp_path: Path) -> None:
    with Daemon(write_config(tmp_path)) as daemon:
        # at once: every loop pending, collecting its samples
        first = get(daemon, "/loop-health")
        assert {row["loop"] for row in first} == set(LOOPS)
        assert all(row["flags"] == [] and row["state"] in ("pending", "ok") for row in first)

        manual = assessed(daemon, "LIC-202", {"manual"}, "put_in_auto", 240)
        assert manual["assessment"]["indices"]["utilization"] == 0.0 and manual["severity"] == "high"
        sticky = assessed(daemon, "TIC-102", {"oscillating", "stiction"}, "check_valve", 240)
        healthy = assessed(daemon, "TIC-101", set(), "none", 240)
        assert healthy["assessment"]["flags"] == [] and healthy["severity"] == "none" and healthy["rank"] == 0
        # the sticky valve's reason: its worst flag's (the first of the worst)
        severities = sticky["assessment"]["severities"]
        worst = max(sticky["assessment"]["flags"], key=lambda f: ("low", "medium", "high").index(severities[f]))
        assert sticky["reason"] == sticky["assessment"]["reasons"][worst] and sticky["severity"] == severities[worst]

        # the overview stream: each new assessment as a health event (the status's summary, with the loop's id)
        with httpx.stream("GET", f"{daemon.base}/events", headers=daemon.headers, timeout=30) as stream:
            event = ""
            for line in stream.iter_lines():
                if line.startswith("event: "):
                    event = line[7:]
                elif line.startswith("data: ") and event == "health":
                    health_event = json.loads(line[6:])
                    break
        assert health_event["loop"] in LOOPS and health_event["state"] == "ok"
        assert set(health_event) == {"loop", "state", "severity", "rank", "flags", "recommendation", "reason", "time"}

        # the list: every loop, worst first (rank descending, then id), as its status says
        rows = get(daemon, "/loop-health")
        assert [(row["loop"], row["rank"]) for row in rows] == sorted(
            ((row["loop"], row["rank"]) for row in rows), key=lambda item: (-item[1], item[0]))
        for row in rows:  # the rank: 10 × the worst severity + the number of flags (docs/health.md, "Online")
            level = ("none", "low", "medium", "high").index(row["severity"])
            assert row["rank"] == (10 * level + len(row["flags"]) if row["flags"] else 0), row
        assert next(row for row in rows if row["loop"] == "LIC-202")["rank"] == 31  # manual, high: 10·3 + 1

        # the detail: the assessment, the window, the evidence the page draws
        assessment, evidence = sticky["assessment"], sticky["evidence"]
        assert sticky["state"] == "ok" and sticky["window_setting"] == WINDOW and sticky["before_tuning"] is None
        assert assessment["dead_time_source"] == "one sample"  # never tuned: no model
        window = assessment["window"]
        assert window["end"] - window["start"] <= WINDOW + window["ts"] and window["samples"] >= 0.1 * WINDOW / 2
        assert 2 <= len(evidence["t"]) <= 1000 and evidence["t"][0] == 0.0
        assert evidence["t"][-1] == pytest.approx(window["end"] - window["start"])
        assert len(evidence["sp"]) == len(evidence["pv"]) == len(evidence["mv"]) == len(evidence["t"])
        assert evidence["period"] == pytest.approx(assessment["indices"]["oscillation_period"])
        crossings = evidence["crossings"]
        assert crossings == sorted(crossings) and 0.0 <= crossings[0] and crossings[-1] <= evidence["t"][-1]
        # two zero crossings per period: the crossings' own spacing gives the period the detector reported
        spacing = 2.0 * (crossings[-1] - crossings[0]) / (len(crossings) - 1)
        assert spacing == pytest.approx(evidence["period"], rel=0.2)

        # a tuning: pending at once (the samples before it were another loop's), the assessment before it kept
        before = get(daemon, "/loops/TIC-101/health")["assessment"]
        r = httpx.post(f"{daemon.base}/loops/TIC-101/tune", headers=daemon.headers, timeout=30)
        assert r.status_code == 202
        sid = r.json()["session"]
        pending = get(daemon, "/loops/TIC-101/health")
        assert pending["state"] == "pending" and pending["assessment"] is None and pending["evidence"] is None
        assert pending["reason"].startswith("collecting: ")
        assert pending["before_tuning"]["session"] == sid and pending["before_tuning"]["time"] >= before["time"]
        httpx.post(f"{daemon.base}/loops/TIC-101/break", headers=daemon.headers, timeout=30)
        daemon.wait_until(lambda: not get(daemon, "/loops/TIC-101")["tbsy"], 120, "TIC-101 handed back")
        daemon.wait_until(lambda: summary(daemon, "TIC-101")["state"] == "ok", 240, "TIC-101 assessed again")
        newest = get(daemon, "/loops/TIC-101/health/history?limit=1")[0]
        assert newest["session"] == sid and newest["time"] > pending["before_tuning"]["time"]
        kept = {loop_id: get(daemon, f"/loops/{loop_id}/health") for loop_id in LOOPS}
        history = {loop_id: get(daemon, f"/loops/{loop_id}/health/history?limit=1000") for loop_id in LOOPS}
    assert daemon.proc.returncode == 0

    # restarted with a window of a day: no new assessment for minutes (4320 readings needed), so what it shows is
    # what the history kept — the assessments read above and those the first daemon made after the read
    with Daemon(write_config(tmp_path, window=86400.0)) as daemon:
        for loop_id in LOOPS:
            read = history[loop_id]
            stored = get(daemon, f"/loops/{loop_id}/health/history?limit=1000")
            assert [row["time"] for row in stored] == sorted((row["time"] for row in stored), reverse=True)
            assert stored[len(stored) - len(read):] == read  # nothing lost, the newer ones in front
            back = get(daemon, f"/loops/{loop_id}/health")
            assert back["state"] == "ok" and back["assessment"]["time"] == stored[0]["time"]
            assert back["assessment"]["flags"] == stored[0]["flags"]
            assert back["assessment"]["recommendation"] == stored[0]["recommendation"]
            if stored[0]["time"] == kept[loop_id]["assessment"]["time"]:
                assert back["assessment"] == kept[loop_id]["assessment"]
            assert back["window_setting"] == 86400.0 and back["evidence"] is None  # the samples are not kept
        restored = get(daemon, "/loops/TIC-101/health")["before_tuning"]
        assert restored["session"] == sid and restored["time"] == kept["TIC-101"]["before_tuning"]["time"]


def test_health_reads_need_a_token_and_name_what_is_wrong() -> None:
    config = demo_config(20.0)
    with TestClient(create_app(config, env_token="op-secret"), raise_server_exceptions=False) as client:
        auth = {"Authorization": "Bearer op-secret"}
        assert client.get("/api/v1/health").json() == {"status": "ok", "loops": len(config.loops)}  # liveness
        for path in ("/loop-health", "/loops/TIC-102/health", "/loops/TIC-102/health/history"):
            r = client.get(f"/api/v1{path}")
            assert r.status_code == 401 and r.json()["code"] == "unauthorized", path
        for path in ("/loops/nope/health", "/loops/nope/health/history"):
            r = client.get(f"/api/v1{path}", headers=auth)
            assert r.status_code == 404 and r.json()["code"] == "not_found" and "nope" in r.json()["message"]
        for limit in ("0", "1001", "many"):
            r = client.get(f"/api/v1/loops/TIC-102/health/history?limit={limit}", headers=auth)
            assert r.status_code == 422 and r.json()["code"] == "invalid" and "limit" in r.json()["message"]
        assert client.get("/api/v1/loops/TIC-102/health/history?limit=1000", headers=auth).json() == []
        detail = client.get("/api/v1/loops/TIC-102/health", headers=auth).json()
        assert detail["state"] == "pending" and detail["assessment"] is None and detail["window_setting"] == 3600.0


def test_the_record_keeps_the_newest_readings_in_order_and_drops_what_cannot_be_assessed() -> None:
    from autotuner.service.daemon.health import Readings

    ring = Readings(4)
    for k in range(6):
        ring.add(float(k), 50.0, 50.0 + k, 40.0 - k, k % 2 == 0)
    ring.add(5.0, 50.0, 1.0, 1.0, True)  # no later than the newest: a clock stepped back
    ring.add(6.0, 50.0, math.nan, 1.0, True)  # not a number
    t, sp, pv, mv, auto = ring.columns()
    assert list(t) == [2.0, 3.0, 4.0, 5.0] and list(pv) == [52.0, 53.0, 54.0, 55.0]
    assert list(mv) == [38.0, 37.0, 36.0, 35.0] and list(auto) == [1.0, 0.0, 1.0, 0.0]
    assert len(ring) == 4 and ring.span == 3.0
    ring.clear()
    assert len(ring) == 0 and ring.span == 0.0
    sparse = Readings(10, stride=3)  # one reading in three: the ring spans a longer window
    for k in range(10):
        sparse.add(float(k), 0.0, 0.0, 0.0, True)
    assert list(sparse.columns()[0]) == [0.0, 3.0, 6.0, 9.0]


def test_a_loops_assessments_are_due_on_its_own_staggered_grid() -> None:
    from autotuner.service.config import LoopConfig
    from autotuner.service.daemon.health import LoopHealth

    config = LoopConfig.model_validate({"id": "A", "sim": {"plant": "1/(s+1)"}, "ts": 0.1, "monitor_period": 1.0,
                                        "health": {"window": 600.0, "every": 60.0}})
    health = LoopHealth(config, origin=1000.0, phase=0.25)
    for k in range(59):  # 59 readings over 58 s: fewer than a tenth of the window
        health.add(1000.0 + k, 50.0, 50.0, 50.0, True)
    assert not health.is_due(1059.0) and health.summary()["reason"] == "collecting: 59 of 60 samples"
    health.add(1059.0, 50.0, 50.0, 50.0, True)
    assert not health.is_due(1059.5)  # ready, but the grid's next time is 60·(0 + 0.25) + 60 = 75 plant s
    assert health.due == 75.0 and not health.is_due(1074.9) and health.is_due(1075.0)
    job = health.job(1075.0)
    assert job.columns.shape == (5, 60) and job.window == 600.0 and job.limits.mv == (0.0, 100.0)
    assert health.due == 135.0 and not health.is_due(1080.0)  # then at 60·(k + 0.25): 135, 195, ... plant s
    health.done({"error": "no"}, 1076.0, health.generation)
    assert not health.is_due(1134.0) and health.is_due(1135.0)
