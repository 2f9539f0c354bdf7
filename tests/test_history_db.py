"""The history on its two kinds of database: an SQLite file and a real PostgreSQL server (SQLAlchemy URL).

The PostgreSQL server is the distribution's (Debian: ``apt-get install
postgresql``; ``tests/setup-and-run.sh`` installs it), started for this module in a
temporary directory on a free localhost port, as user ``postgres`` when the
tests run as root; each test gets a database of its own.
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterator

import pytest
import sqlalchemy as sa

from autotuner.benchmarks.postgres import new_database, temporary_postgres
from autotuner.service.config import ConfigError, load_config
from autotuner.engine.control.gains import Gains
from autotuner.service.history import History, database_url
from autotuner.engine.outcome import Code
from autotuner.engine.result import ExperimentRecord, GainsRecord, ResultRecord
from drivers.link import LoopState, Mode
from helpers import free_port, record_ticks
from test_daemon import loop, manager, running

SAVED = LoopState(mode=Mode.AUTO, mv=50.0, sp=50.0, gains=Gains(k=0.7, ti=3.0))


@pytest.fixture(scope="module")
def postgres() -> Iterator[str]:
    """A PostgreSQL server of its own; the URL of its maintenance database."""
    try:
        server = temporary_postgres()
        url = server.__enter__()
    except FileNotFoundError as exc:
        pytest.fail(f"the PostgreSQL history tests need a PostgreSQL server: {exc}", pytrace=False)
    try:
        yield url
    finally:
        server.__exit__(None, None, None)


@pytest.fixture(params=["sqlite", "postgresql"])
def database(request, tmp_path) -> str:
    """A fresh, empty history database: an SQLite file path, or a PostgreSQL URL."""
    if request.param == "sqlite":
        return str(tmp_path / "history.db")
    return new_database(request.getfixturevalue("postgres"))


def test_sessions_round_trip_newest_first_and_survive_reopening(database):
    history = History(database)
    history.begin("s1", "A", "alice", {"controller": "PI", "amp": 5.0})
    history.saved("s1", SAVED)
    result = ResultRecord(False, False, 0, "ok", "PI", None, None, GainsRecord.of(Gains(k=1.0)),
                          ExperimentRecord(0.0, None, 0))
    history.finish("s1", result, Gains(k=1.0, ti=2.0), {"t": [0.0, 0.5], "pv": [1.0, 2.0], "mv": [0.0, 5.0]})
    history.begin("s2", "A", "bob", {"controller": "PID"})
    history.begin("s3", "B", "bob", {})
    history.applied("s1", "carol", Gains(k=1.1, ti=2.0))
    history.close()

    history = History(database)  # another process's view: everything was committed
    try:
        assert [r["id"] for r in history.of_loop("A")] == ["s2", "s1"]
        assert [r["id"] for r in history.of_loop("A", limit=1)] == ["s2"]
        assert {r["id"] for r in history.running()} == {"s2", "s3"}
        full = history.get("s1")
        assert full["user"] == "alice" and full["state"] == "finished" and full["outcome"] == "success"
        assert full["request"] == {"controller": "PI", "amp": 5.0}
        assert full["gains_before"] == SAVED.gains.as_json() and full["saved"]["mode"] == "AUTO"
        assert full["gains_after"] == Gains(k=1.1, ti=2.0).as_json() and full["applied_by"] == "carol"
        assert full["trace"] == {"t": [0.0, 0.5], "pv": [1.0, 2.0], "mv": [0.0, 5.0]}
        assert full["started_at"] <= full["finished_at"] <= full["applied_at"]
        assert "trace" not in history.of_loop("A")[1]
        assert history.latest("A")["id"] == "s1"  # the newest *finished* one
        assert history.latest("C") is None and history.get("nope") is None
    finally:
        history.close()


def test_a_crash_left_session_is_closed_and_its_loop_restored_from_either_database(database):
    crashed = History(database)
    crashed.begin("s1", "A", "alice", {"controller": "PI", "amp": 5.0})
    crashed.saved("s1", SAVED, (47.0, 55.0))  # with the relay's levels, as the daemon records them
    crashed.close()

    m = manager(loop("A"), history=History(database))
    plc = m.loops["A"].plc
    plc.mode, plc.hv = Mode.MAN, 55.0  # where the relay left it
    ticks: list[tuple[Mode, float]] = []
    record_ticks(plc, ticks)

    async def body(m):
        return m.loops["A"].as_json()

    asyncio.run(running(m, body))
    # Handed back at the saved MV: the first AUTO sample starts from 50 (from 55 had the relay's level stayed),
    # and the PI moves on from there while the daemon runs.
    first = next(mv for mode, mv in ticks if mode is Mode.AUTO)
    assert plc.mode is Mode.AUTO and abs(first - 50.0) < 0.05
    record = m.history.get("s1")
    assert record["state"] == "interrupted" and record["code"] == int(Code.ABORTED)
    assert m.history.running() == []
    m.history.close()


def test_database_urls_in_the_config_are_kept_and_files_are_next_to_it(tmp_path):
    path = tmp_path / "daemon.yaml"
    loops = "loops:\n  - {id: A, ts: 0.1, sim: {plant: '1/(s+1)'}}\n"
    path.write_text("history: postgresql+psycopg://autotuner:secret@db.example:5432/tuning\n" + loops)
    assert load_config(path).history == "postgresql+psycopg://autotuner:secret@db.example:5432/tuning"
    path.write_text("history: sessions.db\n" + loops)
    assert load_config(path).history == str(tmp_path / "sessions.db")
    assert database_url(str(tmp_path / "sessions.db")) == f"sqlite:///{tmp_path / 'sessions.db'}"
    path.write_text("history: 'postgresql://:bad:port'\n" + loops)
    with pytest.raises(ConfigError, match=r"daemon.yaml: history: .*not a database URL"):
        load_config(path)


def test_an_unreachable_database_is_a_clear_error_without_the_password():
    url = f"postgresql+psycopg://autotuner:secret@127.0.0.1:{free_port()}/tuning"
    with pytest.raises(ValueError, match=r"history database postgresql\+psycopg://autotuner:\*\*\*@127.0.0.1") as err:
        History(url)
    assert "secret" not in str(err.value)


def test_the_order_is_the_databases_not_the_clocks(database):
    """Sessions recorded under a wall clock stepped back (their started_at earlier than an older session's) are
    still the newest: newest first, the latest finished, the running and open intents in order."""
    history = History(database)
    try:
        result = ResultRecord(False, False, 0, "ok", "PI", None, None, GainsRecord.of(Gains(k=1.0)),
                              ExperimentRecord(0.0, None, 0))
        for sid in ("old", "new"):
            history.begin(sid, "A", "alice", {})
            history.finish(sid, result, Gains(k=1.0), None)
        history.begin("running", "A", "alice", {})
        with history._engine.begin() as db:  # the clock stepped back an hour for the later sessions
            db.execute(sa.text("UPDATE sessions SET started_at = '2020-01-01T00:00:00+00:00' "
                               "WHERE id IN ('new', 'running')"))
            db.execute(sa.text("UPDATE sessions SET finished_at = '2020-01-01T00:01:00+00:00' WHERE id = 'new'"))
        assert [r["id"] for r in history.of_loop("A")] == ["running", "new", "old"]
        seqs = [r["seq"] for r in history.of_loop("A")]
        assert seqs == sorted(seqs, reverse=True) and len(set(seqs)) == 3
        assert history.latest("A")["id"] == "new"
        history.intend("old", "bob", Gains(k=2.0))
        history.intend("new", "bob", Gains(k=3.0))
        assert [r["id"] for r in history.open_intents()] == ["old", "new"]
    finally:
        history.close()


def test_an_older_history_gets_its_order_from_the_start_times(database):
    """A history written before the order existed (no ``seq``) gets one on open, in the order its sessions
    started; sessions recorded after it come after them."""
    engine = sa.create_engine(database if "://" in database else f"sqlite:///{database}")
    with engine.begin() as db:
        db.execute(sa.text("CREATE TABLE sessions (id VARCHAR(64) PRIMARY KEY, loop VARCHAR(64) NOT NULL, "
                           "\"user\" TEXT NOT NULL, started_at VARCHAR(40) NOT NULL, finished_at VARCHAR(40), "
                           "state VARCHAR(16) NOT NULL, request TEXT NOT NULL, saved TEXT, result TEXT, "
                           "gains_after TEXT, trace TEXT)"))
        for sid, started in (("b", "2024-01-02"), ("c", "2024-01-03"), ("a", "2024-01-01")):
            db.execute(sa.text("INSERT INTO sessions (id, loop, \"user\", started_at, state, request) VALUES "
                               f"('{sid}', 'A', 'bob', '{started}T00:00:00+00:00', 'running', '{{}}')"))
    engine.dispose()
    history = History(database)
    try:
        assert [(r["id"], r["seq"]) for r in history.of_loop("A")] == [("c", 3), ("b", 2), ("a", 1)]
        history.begin("d", "A", "bob", {})
        assert history.get("d")["seq"] == 4 and history.of_loop("A", limit=1)[0]["id"] == "d"
    finally:
        history.close()
    reopened = History(database)  # opening it again: nothing to add, the order kept
    try:
        assert [r["id"] for r in reopened.of_loop("A")] == ["d", "c", "b", "a"]
    finally:
        reopened.close()


def test_health_assessments_round_trip_newest_first_bounded_per_loop(database, monkeypatch):
    import autotuner.service.history as history_module

    monkeypatch.setattr(history_module, "HEALTH_KEPT", 5)
    history = History(database)
    for i in range(8):  # A's eight, B's one between: each loop keeps its own newest five
        flags = ["oscillating", "stiction"] if i % 2 else []
        history.add_health("A", {"time": 1000.0 + i, "flags": flags, "recommendation": "check_valve" if flags
                                 else "none", "reasons": {}, "severities": {}, "indices": {"harris": 0.5 + i}},
                           "medium" if flags else "none", "s1" if i < 4 else "s2")
        if i == 3:
            history.add_health("B", {"time": 5.0, "flags": ["manual"], "recommendation": "put_in_auto"}, "high",
                               None)
    history.close()

    history = History(database)  # another process's view: committed
    try:
        rows = history.health_of("A")
        assert [r["time"] for r in rows] == [1007.0, 1006.0, 1005.0, 1004.0, 1003.0]
        assert rows[0] == {"time": 1007.0, "state": "ok", "severity": "medium", "flags": ["oscillating", "stiction"],
                           "recommendation": "check_valve", "session": "s2", "assessment": {
                               "time": 1007.0, "flags": ["oscillating", "stiction"], "recommendation": "check_valve",
                               "reasons": {}, "severities": {}, "indices": {"harris": 7.5}}}
        assert [r["time"] for r in history.health_of("A", limit=2)] == [1007.0, 1006.0]
        assert [r["time"] for r in history.health_of("A", before=1005.0)] == [1004.0, 1003.0]
        assert [(r["severity"], r["session"]) for r in history.health_of("B")] == [("high", None)]
        assert history.health_of("C") == []
    finally:
        history.close()
