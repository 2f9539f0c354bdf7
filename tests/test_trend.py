"""The trend a loop keeps in memory (autotuner/service/trend.py): seeded after a restart from the history."""

from __future__ import annotations

from datetime import datetime

from autotuner.service.trend import Trend

RECORD = {"id": "s1", "started_at": "2026-12-01T20:00:00.000Z", "saved": {"mode": "AUTO", "sp": 50.0, "mv": 50.0},
          "trace": {"t": [0.0, 1.0, 2.0, 3.0], "pv": [50.0, 50.1, 50.3, 49.8], "mv": [50.0, 50.0, 55.0, 47.0]}}


def test_a_trend_is_seeded_with_the_newest_session_of_the_history():
    trend = Trend()
    trend.seed(RECORD, speed=2.0)
    trend.add({"time": 2e9, "pv": 50.0, "sp": 50.0, "mv": 50.0, "mode": "AUTO"})  # the monitor goes on after it
    replay = trend.replay()
    start = datetime.fromisoformat(RECORD["started_at"]).timestamp()
    assert replay["session"] == "s1"
    assert replay["time"] == [start, start + 0.5, start + 1.0, start + 1.5, 2e9]  # plant seconds at 2× real time
    assert replay["t"] == [0.0, 1.0, 2.0, 3.0, None] and replay["pv"][:4] == RECORD["trace"]["pv"]
    assert replay["sp"] == [50.0] * 5 and replay["mv"][:4] == RECORD["trace"]["mv"]
    # The relay's output is not stored: the sign of MV − the saved MV (0 while the MV is the saved one).
    assert replay["relay"] == [0.0, 0.0, 1.0, -1.0, None]


def test_a_trend_with_a_session_or_a_record_without_trace_is_not_seeded():
    running = Trend()
    running.start("s2")
    running.seed(RECORD, speed=1.0)
    assert running.replay()["session"] == "s2" and running.replay()["time"] == []
    empty = Trend()
    empty.seed({**RECORD, "trace": None}, speed=1.0)
    empty.seed({**RECORD, "saved": None}, speed=1.0)
    assert empty.replay()["session"] is None and empty.replay()["time"] == []
