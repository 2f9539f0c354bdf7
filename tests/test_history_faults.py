"""The history under faults, with real processes: a daemon (``autotuner serve``) whose SQLite file another process
locks; a gains write interrupted by SIGKILL between the device write and its record, reconciled at the next start
with the gains read back from a real Modbus server."""

from __future__ import annotations

import asyncio
import signal
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
import yaml

from autotuner.engine.outcome import Code
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.simulated_tuning import default_sample_time
from drivers.modbus_server import ModbusPlcServer, serve_modbus
from drivers.simplc import SimulatedPlc, run
from helpers import Daemon
from test_handback import Plc, daemon as handback_daemon, history_row, wait_for

PLANT = "exp(-s)/(2*s+1)"
SPEED = 10.0
# The experiment whose gains are written runs slower: a PLC served in a thread of the test jitters more.
SLOW = 4.0
TS = default_sample_time(parse_process(PLANT)) * 100 / 40

# A separate process holding an exclusive lock on an SQLite file until its stdin closes.
LOCKER = """
import sqlite3, sys
db = sqlite3.connect(sys.argv[1], isolation_level=None)
db.execute("BEGIN EXCLUSIVE")
print("locked", flush=True)
sys.stdin.read()
db.execute("ROLLBACK")
"""


@contextmanager
def locked(path: Path) -> Iterator[None]:
    """While inside: another process holds an exclusive lock on the SQLite file ``path``."""
    proc = subprocess.Popen([sys.executable, "-c", LOCKER, str(path)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)
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
    config.write_text(yaml.safe_dump({"history": str(db), "loops": [{"id": "A", **loop}, {"id": "B", **loop}]}))
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


def test_a_saved_state_that_cannot_be_recorded_ends_the_session_before_it_touches_the_loop(tmp_path: Path):
    """TUNE while another process locks the history: the session must not take the loop over without its saved
    state on record (a crash would leave nothing to restore it from), so it ends untouched. An external simulated
    PLC, read by a separate Modbus client from the TUNE to the end of the session."""
    plc = Plc(tmp_path)
    try:
        with handback_daemon(tmp_path, plc) as d:
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
        set_plc = server._set_plc

        def watched(plc: SimulatedPlc, written: dict[str, float]):
            answer = set_plc(plc, written)
            if "k" in written and answer is None:
                self.gains_written.set()
                if self.freeze_after_gains:
                    server.hang(True)
            return answer

        server._set_plc = watched  # type: ignore[method-assign]
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
