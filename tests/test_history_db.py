"""The history on its two kinds of database: an SQLite file and a real PostgreSQL server (SQLAlchemy URL).

The PostgreSQL server is the distribution's (Debian: ``apt-get install
postgresql``; ``tests/setup-and-run.sh`` installs it), started for this module in a
temporary directory on a free localhost port, as user ``postgres`` when the
tests run as root; each test gets a database of its own.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
import sqlalchemy as sa

from autotuner.service.config import ConfigError, load_config
from autotuner.engine.control.gains import Gains
from autotuner.service.history import History, database_url
from autotuner.engine.outcome import Code
from autotuner.engine.result import ExperimentRecord, GainsRecord, ResultRecord
from drivers.link import LoopState, Mode
from helpers import free_port, record_ticks
from test_daemon import loop, manager, running

SAVED = LoopState(mode=Mode.AUTO, mv=50.0, sp=50.0, gains=Gains(k=0.7, ti=3.0))


def postgres_bin() -> Path:
    """The directory of the distribution's PostgreSQL server programs; a clear failure without them."""
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin/pg_ctl"), key=lambda p: int(p.parts[-3]))
    if os.environ.get("AUTOTUNER_PG_BIN"):
        return Path(os.environ["AUTOTUNER_PG_BIN"])
    if not found:
        pytest.fail("the PostgreSQL history tests need a PostgreSQL server: apt-get install postgresql (Debian), "
                    "or set AUTOTUNER_PG_BIN to the directory of initdb and pg_ctl", pytrace=False)
    return found[-1].parent


@pytest.fixture(scope="module")
def postgres() -> Iterator[str]:
    """A PostgreSQL server of its own; the URL of its maintenance database."""
    bin_dir = postgres_bin()
    as_server = ["runuser", "-u", "postgres", "--"] if os.geteuid() == 0 else []
    home = Path(tempfile.mkdtemp(prefix="autotuner-pg-"))
    if as_server:
        shutil.chown(home, "postgres")
    data, port = home / "data", free_port()
    subprocess.run([*as_server, str(bin_dir / "initdb"), "-D", str(data), "-A", "trust", "-U", "postgres",
                    "-E", "UTF8", "--no-sync"], check=True, capture_output=True)
    options = f"-p {port} -k {home} -c listen_addresses=127.0.0.1 -c fsync=off"
    subprocess.run([*as_server, str(bin_dir / "pg_ctl"), "-D", str(data), "-o", options, "-l", str(home / "log"),
                    "-w", "-t", "60", "start"], check=True, capture_output=True)
    try:
        yield f"postgresql+psycopg://postgres@127.0.0.1:{port}/postgres"
    finally:
        subprocess.run([*as_server, str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "fast", "stop"],
                       capture_output=True)
        shutil.rmtree(home, ignore_errors=True)


@pytest.fixture(params=["sqlite", "postgresql"])
def database(request, tmp_path) -> str:
    """A fresh, empty history database: an SQLite file path, or a PostgreSQL URL."""
    if request.param == "sqlite":
        return str(tmp_path / "history.db")
    server = request.getfixturevalue("postgres")
    name = f"history_{uuid.uuid4().hex[:12]}"
    engine = sa.create_engine(server, isolation_level="AUTOCOMMIT")
    with engine.connect() as db:
        db.execute(sa.text(f"CREATE DATABASE {name}"))
    engine.dispose()
    return server.rsplit("/", 1)[0] + "/" + name


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
