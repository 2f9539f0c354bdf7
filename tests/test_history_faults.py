"""The history under faults, with real processes: a daemon (``autotuner serve``) whose SQLite file another process
locks; a gains write interrupted by SIGKILL between the device write and its record, reconciled at the next start
with the gains read back from a real Modbus server; a daemon restarted with its wall clock stepped back an hour
(libfaketime); the history on a full disk (a small tmpfs mounted for the test, filled to the last byte)."""

from __future__ import annotations

import asyncio
import errno
import os
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
import sqlalchemy
import yaml

from autotuner.engine.outcome import Code
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.simulated_tuning import default_sample_time
from drivers.modbus_server import ModbusPlcServer, serve_modbus
from drivers.simplc import SimulatedPlc, run
from helpers import Daemon, libfaketime
from test_handback import Plc, daemon as handback_daemon, history_row, wait_for

PLANT = "exp(-s)/(2*s+1)"
SPEED = 10.0
# The experiment whose gains are written runs slower: a PLC served in a thread of the test jitters more.
SLOW = 4.0
# Sessions that must succeed on a loaded machine (not end OVERLOADED): 44 ms of wall time between samples.
CALM = 3.0
TS = default_sample_time(parse_process(PLANT)) * 100 / 40
# The daemon's bound for a session's records (its config's record_wait, default 10 s), wall seconds, where the
# history is made to fail: what is checked is what a session does once the bound has passed, not how long the
# bound is, and a session with the history out waited 3 bounds (saved state, end, status) — 32 s a session at 10 s.
# Still hundreds of times an SQLite commit on a loaded machine, for the records that must go through.
RECORD_WAIT = 4.0

# A separate process holding a lock on an SQLite file until its stdin closes: EXCLUSIVE (no reads, no writes) or
# IMMEDIATE (reads go on, writes wait).
LOCKER = """
import sqlite3, sys
db = sqlite3.connect(sys.argv[1], isolation_level=None)
db.execute("BEGIN " + sys.argv[2])
print("locked", flush=True)
sys.stdin.read()
db.execute("ROLLBACK")
"""


@contextmanager
def locked(path: Path, kind: str = "EXCLUSIVE") -> Iterator[None]:
    """While inside: another process holds a ``kind`` lock (EXCLUSIVE, IMMEDIATE) on the SQLite file ``path``."""
    proc = subprocess.Popen([sys.executable, "-c", LOCKER, str(path), kind], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "locked"
        yield
    finally:
        proc.stdin.close()
        proc.wait(30)


def status(daemon: Daemon, loop_id: str) -> dict:
    return httpx.get(f"{daemon.base}/loops/{loop_id}", headers=daemon.headers, timeout=30).json()


def test_a_history_locked_by_another_process_never_leaves_a_loop_busy_nor_stalls_the_daemon(tmp_path: Path):
    db = tmp_path / "h.db"
    config = tmp_path / "daemon.yaml"
    loop = {"sim": {"plant": PLANT}, "ts": TS, "speed": SPEED, "tuning": {"amp": 5.0, "time_limit": 1000.0},
            "monitor_period": 0.1}
    config.write_text(yaml.safe_dump({"history": str(db), "record_wait": RECORD_WAIT,
                                      "loops": [{"id": "A", **loop}, {"id": "B", **loop}]}))
    with Daemon(config) as daemon:
        first = httpx.post(f"{daemon.base}/loops/A/tune", headers=daemon.headers).json()["session"]
        daemon.wait_until(lambda: status(daemon, "A")["stage"] == "relay", 60, "A's relay")
        with locked(db):
            # TBRK: the session ends while its end cannot be written; the loop is idle again all the same.
            assert httpx.post(f"{daemon.base}/loops/A/break", headers=daemon.headers).status_code == 202
            daemon.wait_until(lambda: not status(daemon, "A")["tbsy"], 40, "A idle with the history locked")
            assert status(daemon, "A")["mode"] == "AUTO"
            # The event loop is never blocked: every request is answered at once, B's monitor goes on.
            worst = 0.0
            for _ in range(20):
                start = time.monotonic()
                assert httpx.get(f"{daemon.base}/loops", headers=daemon.headers, timeout=30).status_code == 200
                worst = max(worst, time.monotonic() - start)
            assert worst < 1.0, worst
            # TUNE while locked: accepted, never 500 (its records wait in the history's thread); its saved state
            # cannot be recorded, so it ends before it touches the loop (TBRK meanwhile changes nothing).
            second = httpx.post(f"{daemon.base}/loops/B/tune", headers=daemon.headers)
            assert second.status_code == 202, second.text
            assert httpx.post(f"{daemon.base}/loops/B/break", headers=daemon.headers).status_code == 202
            daemon.wait_until(lambda: not status(daemon, "B")["tbsy"], 60, "B idle with the history locked")
            assert status(daemon, "B")["mode"] == "AUTO"
            assert status(daemon, "B")["ite"] == Code.HISTORY_UNAVAILABLE
            assert "retrying" in daemon.log()
        # The lock released: the retried writes land, the history agrees with what happened.
        def recorded() -> bool:
            record = httpx.get(f"{daemon.base}/sessions/{first}", headers=daemon.headers, timeout=30).json()
            return record.get("state") == "finished"

        daemon.wait_until(recorded, 60, "A's session recorded after the lock")
        record = httpx.get(f"{daemon.base}/sessions/{first}", headers=daemon.headers).json()
        assert record["code"] == Code.ABORTED and record["saved"]["mode"] == "AUTO"
        b = httpx.get(f"{daemon.base}/sessions/{second.json()['session']}", headers=daemon.headers).json()
        assert b["state"] == "finished" and b["code"] == Code.HISTORY_UNAVAILABLE
        assert "written after" in daemon.log()
    assert "Traceback" not in daemon.log()


def test_a_history_locked_at_the_start_is_said_to_be_locked_not_damaged(tmp_path: Path):
    """Opening a history another process holds locked fails with a message that says so — not the damaged file's
    advice to move it away, which would lose a sound history."""
    from autotuner.service.history import History

    History(str(tmp_path / "h.db")).close()
    with locked(tmp_path / "h.db"), pytest.raises(ValueError) as raised:
        History(str(tmp_path / "h.db"))
    assert "another process holds it locked" in str(raised.value) and "move it away" not in str(raised.value)
    History(str(tmp_path / "h.db")).close()  # released: it opens


def test_a_saved_state_that_cannot_be_recorded_ends_the_session_before_it_touches_the_loop(tmp_path: Path):
    """TUNE while another process locks the history: the session must not take the loop over without its saved
    state on record (a crash would leave nothing to restore it from), so it ends untouched. An external simulated
    PLC, read by a separate Modbus client from the TUNE to the end of the session."""
    plc = Plc(tmp_path)
    try:
        with handback_daemon(tmp_path, plc, record_wait=RECORD_WAIT) as d:
            before = plc.read()
            assert before["mode"] == "AUTO" and before["tbsy"] is False
            seen: list[dict] = []

            def ended() -> bool:
                seen.append(plc.read())
                return d.status()["tbsy"] is False

            with locked(d.history):
                sid = d.tune()
                wait_for(ended, 90, "the session to end with the history locked")
                status = d.status()
                seen.append(plc.read())
            assert len(seen) > 10
            for now in seen:  # never MAN, never the relay's MV, no TBSY, no watchdog: nothing written to the loop
                assert (now["mode"], now["hv"], now["tbsy"], now["wd_time"]) == ("AUTO", before["hv"], False, 0.0), now
            assert status["ite"] == Code.HISTORY_UNAVAILABLE and status["te"] is True, status
            assert "saved state could not be recorded" in status["message"], status
            assert "ends without touching the loop: its saved state is not recorded" in d.output()
            # The lock gone, the session's records land: ended untouched, with its code.
            def recorded() -> bool:  # the begin is in once the lock is gone and its retry comes round
                with sqlite3.connect(d.history) as db:
                    row = db.execute("SELECT state FROM sessions WHERE id = ?", (sid,)).fetchone()
                return row is not None and row[0] == "finished"

            wait_for(recorded, 150, "the session's end recorded")
            assert history_row(d.history, sid)["result"]["ite"] == int(Code.HISTORY_UNAVAILABLE)
    finally:
        plc.close()


class ThreadedPlc:
    """A simulated PLC behind a real Modbus TCP server, run in a thread of this process (its own event loop).

    ``freeze_after_gains``: once gains are written, every later request hangs — the daemon's next steps after the
    device write (its flags, the read-back, the record) cannot happen before the test kills it.
    """

    def __init__(self, speed: float = SPEED) -> None:
        self.plc = SimulatedPlc(parse_process(PLANT), ts=TS / 5)
        self.speed = speed
        self.gains_written = threading.Event()
        self.freeze_after_gains = False
        self._ready = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._halt: asyncio.Event | None = None
        self.server: ModbusPlcServer | None = None
        self._thread = threading.Thread(target=lambda: asyncio.run(self._main()), daemon=True)
        self._thread.start()
        assert self._ready.wait(30)

    async def _main(self) -> None:
        self._loop, self._halt = asyncio.get_running_loop(), asyncio.Event()
        self.server = server = await serve_modbus(self.plc, "127.0.0.1", 0, unit=1)
        set_gains = self.plc.set_gains

        def watched(gains):  # the server applies a gains write through it, in its event loop
            set_gains(gains)
            self.gains_written.set()
            if self.freeze_after_gains:
                server.hang(True)

        self.plc.set_gains = watched  # type: ignore[method-assign]
        self._ready.set()
        await run(self.plc, self.speed, self._halt)
        await server.close()

    def call(self, fn) -> None:
        """Run ``fn()`` in the PLC's thread (between two ticks)."""
        done = threading.Event()
        self._loop.call_soon_threadsafe(lambda: (fn(), done.set()))
        assert done.wait(30)

    def close(self) -> None:
        self._loop.call_soon_threadsafe(self._halt.set)
        self._thread.join(30)


def reconciled_at_start(plant: ThreadedPlc, config: Path, sid: str) -> dict:
    """The PLC answering again, start the daemon on ``config``: session ``sid``'s record once its open gains intent
    is reconciled with the device."""
    plant.call(lambda: plant.server.hang(False))
    plant.freeze_after_gains = False
    with Daemon(config) as restarted:
        def reconciled() -> bool:
            record = httpx.get(f"{restarted.base}/sessions/{sid}", headers=restarted.headers).json()
            return record["gains_intent"] is None and record["state"] != "running"

        restarted.wait_until(reconciled, 60, "the intent reconciled with the device")
        return httpx.get(f"{restarted.base}/sessions/{sid}", headers=restarted.headers).json()


def test_gains_written_then_sigkill_are_reconciled_with_the_device_at_the_next_start(tmp_path: Path):
    plant = ThreadedPlc(SLOW)
    try:
        db = tmp_path / "h.db"
        config = tmp_path / "daemon.yaml"
        config.write_text(yaml.safe_dump({"history": str(db), "loops": [
            {"id": "TIC", "link": f"modbus://127.0.0.1:{plant.server.port}/1?timeout=2", "ts": TS,
             "speed": SLOW, "tuning": {"amp": 5.0, "time_limit": 1000.0}}]}))
        before = plant.plc.gains
        plant.freeze_after_gains = True
        daemon = Daemon(config)
        with daemon:
            sid = httpx.post(f"{daemon.base}/loops/TIC/tune", json={"apply": True},
                             headers=daemon.headers).json()["session"]
            daemon.wait_until(lambda: plant.gains_written.is_set() or not status(daemon, "TIC")["tbsy"], 240,
                              "the gains written to the PLC")
            assert plant.gains_written.is_set(), status(daemon, "TIC")["message"]
            daemon.kill()  # the whole tuner, as a lost machine
        written = plant.plc.gains
        assert written != before
        row = sqlite3.connect(db).execute("SELECT state, gains_intent, applied_by FROM sessions WHERE id = ?",
                                          (sid,)).fetchone()
        assert row[0] == "running" and row[1] is not None and row[2] is None  # written, not recorded
        record = reconciled_at_start(plant, config, sid)
        # History and device agree: the gains the PLC runs are the session's, recorded as applied by its user.
        assert record["applied_by"] == "AUTOTUNER_TOKEN" and record["applied_at"] is not None
        assert plant.plc.gains == written
        assert record["gains_after"]["pk"] == pytest.approx(written.k, rel=1e-6)
        assert record["gains_after"]["pti"] == pytest.approx(written.ti, rel=1e-6)
    finally:
        plant.close()


def test_an_intent_whose_write_never_reached_the_device_is_recorded_as_not_applied(tmp_path: Path):
    from autotuner.engine.control.gains import Gains
    from autotuner.service.history import History

    plant = ThreadedPlc()
    try:
        db = tmp_path / "h.db"
        history = History(str(db))
        history.begin("s1", "TIC", "alice", {"apply": True})
        history.intend("s1", "alice", Gains(k=9.0, ti=3.0))  # the daemon died before the write
        history.close()
        config = tmp_path / "daemon.yaml"
        config.write_text(yaml.safe_dump({"history": str(db), "loops": [
            {"id": "TIC", "link": f"modbus://127.0.0.1:{plant.server.port}/1", "ts": TS, "speed": SPEED}]}))
        with Daemon(config) as daemon:
            def reconciled() -> bool:
                return httpx.get(f"{daemon.base}/sessions/s1", headers=daemon.headers).json()["gains_intent"] is None

            daemon.wait_until(reconciled, 60, "the intent reconciled")
            record = httpx.get(f"{daemon.base}/sessions/s1", headers=daemon.headers).json()
        assert record["applied_by"] is None and record["gains_after"]["pk"] == pytest.approx(plant.plc.gains.k, rel=1e-6)
        assert plant.plc.gains.k != 9.0
    finally:
        plant.close()


def tuned(daemon: Daemon, loop_id: str, body: dict) -> dict:
    """TUNE ``loop_id`` with ``body`` and wait for the session's end: its record."""
    r = httpx.post(f"{daemon.base}/loops/{loop_id}/tune", json=body, headers=daemon.headers, timeout=30)
    assert r.status_code == 202, r.text
    sid = r.json()["session"]

    def ended() -> bool:
        record = httpx.get(f"{daemon.base}/sessions/{sid}", headers=daemon.headers, timeout=30).json()
        return record.get("state") == "finished" and not status(daemon, loop_id)["tbsy"]

    daemon.wait_until(ended, 180, f"session {sid} to end")
    return httpx.get(f"{daemon.base}/sessions/{sid}", headers=daemon.headers, timeout=30).json()


def test_a_wall_clock_stepped_back_across_a_restart_leaves_the_new_session_the_newest(tmp_path: Path):
    """The issue's finding: with the clock stepped back an hour across a restart, the history sorted the new
    session below the old one, the status showed the old outcome and ``POST /apply`` without a body wrote the
    older session's gains. The order is now the database's: the new session is the newest whatever its times."""
    config = tmp_path / "daemon.yaml"
    config.write_text(yaml.safe_dump({"history": str(tmp_path / "h.db"), "loops": [
        {"id": "A", "sim": {"plant": PLANT}, "ts": TS, "speed": CALM, "monitor_period": 0.2,
         "tuning": {"amp": 5.0, "time_limit": 1000.0}, "limits": {"pv": [0, 100], "mv": [0, 100]}}]}))
    # The first run's wall clock an hour ahead, the second's the machine's: stepped back an hour across the
    # restart. (Not the second run's an hour behind: libfaketime 0.9.10 then fails Python's sleeps with EINVAL,
    # and with FAKETIME_DONT_FAKE_MONOTONIC its absolute monotonic sleeps too.)
    with Daemon(config, env={"LD_PRELOAD": libfaketime(), "FAKETIME": "+1h"}) as daemon:
        old = tuned(daemon, "A", {"ms": 1.2})
    with Daemon(config) as daemon:
        new = tuned(daemon, "A", {"ms": 2.0})
        assert old["outcome"] == new["outcome"] == "success", (old["message"], new["message"])
        assert new["started_at"] < old["started_at"]  # the daemon's clock really was an hour back
        assert new["seq"] > old["seq"]
        assert new["result"]["gains"]["pk"] != pytest.approx(old["result"]["gains"]["pk"], rel=1e-3)
        listed = httpx.get(f"{daemon.base}/loops/A/history", headers=daemon.headers, timeout=30).json()
        assert [r["id"] for r in listed] == [new["id"], old["id"]]
        now = status(daemon, "A")
        assert now["last_tuned_at"] == new["finished_at"] and now["pending_gains"] is True
        applied = httpx.post(f"{daemon.base}/loops/A/apply", headers=daemon.headers, timeout=30)
        assert applied.status_code == 200, applied.text
        assert applied.json()["session"] == new["id"]
        assert applied.json()["gains"]["pk"] == pytest.approx(new["result"]["gains"]["pk"], rel=1e-5)
        assert status(daemon, "A")["current_gains"]["pk"] == pytest.approx(new["result"]["gains"]["pk"], rel=1e-5)
        record = httpx.get(f"{daemon.base}/sessions/{old['id']}", headers=daemon.headers, timeout=30).json()
        assert record["applied_by"] is None  # the older session's gains were never written
    assert "Traceback" not in daemon.log()


class Disk:
    """A small tmpfs mounted at ``path`` (the tests run as root, as CI does), filled and freed on demand."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.filler = path / "filler"

    def fill(self) -> None:
        """Take every free byte (a file written until ENOSPC)."""
        fd = os.open(self.filler, os.O_WRONLY | os.O_CREAT | os.O_APPEND)
        try:
            while True:
                os.write(fd, b"\0" * 4096)
        except OSError as exc:
            assert exc.errno == errno.ENOSPC, exc
        finally:
            os.close(fd)
        assert os.statvfs(self.path).f_bavail == 0

    def free(self) -> None:
        self.filler.unlink()


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[Disk]:
    """A 4 MiB tmpfs of its own (``mount -t tmpfs``: root, or CAP_SYS_ADMIN), unmounted afterwards."""
    path = tmp_path / "disk"
    path.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(path)], capture_output=True,
                             text=True)
    if mounted.returncode != 0:
        pytest.fail("the full-disk tests mount a small tmpfs: run them as root (or with CAP_SYS_ADMIN): "
                    f"{mounted.stderr.strip()}", pytrace=False)
    try:
        yield Disk(path)
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def test_on_a_full_disk_a_guarded_record_is_dropped_at_its_deadline_and_a_session_is_kept_until_written(disk):
    """The history itself on a real full disk: an intent whose caller gave up is never written, even once space
    returns (it was written late before); a session's begin is retried until it is written (it was given up after
    120 s, and the session vanished). The outage is reported once, with the file."""
    from autotuner.engine.control.gains import Gains
    from autotuner.service.daemon.recorder import Recorder
    from autotuner.service.history import History

    path = disk.path / "h.db"
    history = History(str(path))
    errors: list[str | None] = []

    async def body() -> None:
        recorder = Recorder(history, RECORD_WAIT)
        recorder.on_health = lambda: errors.append(recorder.health.error)
        assert await recorder.durable(history.begin, "s1", "A", "alice", {}) == ""
        disk.fill()
        why = await recorder.guard(history.intend, "s1", "bob", Gains(k=9.0), wait=1.0)
        assert "never will" in why and "disk is full" in why, why
        begun = recorder.record(history.begin, "s2", "A", "alice", {})
        assert "not record it within 1 s" in await recorder.durable(history.get, "s2", wait=1.0)
        assert not begun.done()  # still retried
        disk.free()
        await asyncio.wait_for(begun, 60)
        await recorder.drain(60)
        recorder.close(wait=True)

    try:
        asyncio.run(body())
        assert history.get("s2") is not None  # kept: written once the disk had room
        assert history.get("s1")["gains_intent"] is None  # the intent refused to its caller: never written
        assert errors[0] is not None and str(path) in errors[0] and "full" in errors[0], errors
        assert errors[-1] is None and history.error is None and len(errors) == 2  # once at the start, once at the end
    finally:
        history.close()


def test_a_daemon_whose_history_disk_fills_loses_no_session_and_writes_no_late_intent(tmp_path: Path, disk: Disk):
    """The issue's finding with a real full disk: a session refused meanwhile vanished from the history, and
    ``POST /apply`` hung 96 s, answered 503, and its intent was written anyway once space returned (the next start
    then rewrote that session's gains_after). Now: apply answers 503 within its bound and nothing of it is ever
    written; the refused session is recorded once there is room; the status says why meanwhile."""
    db = disk.path / "h.db"
    config = tmp_path / "daemon.yaml"
    config.write_text(yaml.safe_dump({"history": str(db), "record_wait": RECORD_WAIT, "loops": [
        {"id": "A", "sim": {"plant": PLANT}, "ts": TS, "speed": CALM, "monitor_period": 0.2,
         "tuning": {"amp": 5.0, "time_limit": 1000.0}, "limits": {"pv": [0, 100], "mv": [0, 100]}}]}))
    with Daemon(config) as daemon:
        first = tuned(daemon, "A", {})
        assert first["outcome"] == "success", first["message"]
        gains_before = status(daemon, "A")["current_gains"]
        disk.fill()
        # Apply while the disk is full: the session is read, its intent cannot be written: refused, in bounds.
        for body in (None, {"session": first["id"]}):
            r = httpx.post(f"{daemon.base}/loops/A/apply", json=body, headers=daemon.headers, timeout=30)
            assert r.status_code == 503 and r.json()["code"] == "history_unavailable", r.text
            assert "disk is full" in r.json()["message"], r.text
        assert "dropped, never to be written" in daemon.log()
        now = status(daemon, "A")
        assert str(db) in now["history_error"] and "full" in now["history_error"], now["history_error"]
        assert now["current_gains"] == gains_before  # nothing written to the controller
        # A TUNE meanwhile: its record cannot be made durable, so it ends before it touches the loop.
        r = httpx.post(f"{daemon.base}/loops/A/tune", headers=daemon.headers, timeout=30)
        assert r.status_code == 202, r.text
        second = r.json()["session"]
        daemon.wait_until(lambda: not status(daemon, "A")["tbsy"], 120, "the refused session to end")
        now = status(daemon, "A")
        assert now["ite"] == Code.HISTORY_UNAVAILABLE and now["mode"] == "AUTO", now
        # Reads queued behind the session's retried begin: refused within the bound too.
        r = httpx.post(f"{daemon.base}/loops/A/apply", headers=daemon.headers, timeout=30)
        assert r.status_code == 503 and "did not answer within" in r.json()["message"], r.text
        assert daemon.log().count("every write is retrying until it succeeds") == 1  # logged once, with the path
        disk.free()
        daemon.wait_until(lambda: status(daemon, "A")["history_error"] is None, 120, "the history writing again")

        def recorded() -> bool:
            record = httpx.get(f"{daemon.base}/sessions/{second}", headers=daemon.headers, timeout=30).json()
            return record.get("state") == "finished"

        daemon.wait_until(recorded, 120, "the refused session recorded once the disk had room")
        record = httpx.get(f"{daemon.base}/sessions/{second}", headers=daemon.headers, timeout=30).json()
        assert record["code"] == Code.HISTORY_UNAVAILABLE and record["saved"] is None  # never touched the loop
        assert "writes succeed again" in daemon.log()
        assert "Traceback" not in daemon.log()
    with Daemon(config) as daemon:  # restarted: no open intent to reconcile, the session's gains after kept
        record = httpx.get(f"{daemon.base}/sessions/{first['id']}", headers=daemon.headers, timeout=30).json()
        assert record["gains_intent"] is None and record["applied_by"] is None
        assert record["gains_after"] == first["gains_after"]
        assert "was interrupted" not in daemon.log()


def test_a_stop_while_the_disk_is_full_gives_the_retried_writes_up_and_says_so(disk, caplog):
    """Writes are retried until written — but not past the daemon's stop, which would then never end."""
    from autotuner.service.daemon.recorder import Recorder
    from autotuner.service.history import History

    history = History(str(disk.path / "h.db"))

    async def body() -> None:
        recorder = Recorder(history, RECORD_WAIT)
        disk.fill()
        begun = recorder.record(history.begin, "s1", "A", "alice", {})
        await recorder.drain(1.0)
        assert not begun.done()  # retried
        await asyncio.wait_for(asyncio.to_thread(recorder.close, True), 60)  # ends: given up at its next failure
        with pytest.raises(sqlalchemy.exc.OperationalError, match="full"):
            await asyncio.wait_for(begun, 30)

    try:
        with caplog.at_level("WARNING"):
            asyncio.run(body())
        assert "1 write(s) not done yet at the stop" in caplog.text and "NOT RECORDED" in caplog.text
    finally:
        history.close()
