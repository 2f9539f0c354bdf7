"""A fleet of daemons on one PostgreSQL (docs/fleet.md): real processes, a real PostgreSQL server, the plant read by a
separate Modbus client.

The plant is `autotuner sim --loops 6` (loop k on unit id k); the daemons are `autotuner serve --config` with one
PostgreSQL history and a 4-second lease. What must hold: the loops split between the daemons, each with exactly
one owner shown in every daemon's status; a TUNE asked of the wrong daemon is redirected to the owner and two at
once run one experiment; a daemon killed has its loops taken over within the lease (plus a round), its session
recorded and its loop restored by the survivor; a daemon frozen past its lease writes nothing more once it runs.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import sqlalchemy as sa
from pymodbus.client import ModbusTcpClient

from api.auth import token_hash
from autotuner.benchmarks.postgres import new_database
from drivers.modbus_map import DEFAULT_MAP
from helpers import Daemon, free_port
from test_history_db import postgres  # noqa: F401 - the module's PostgreSQL server fixture

TOKEN = "fleet-operator-token-0123456789"
ADMIN = "fleet-admin-token-0123456789"
LOOPS = 6
LEASE = 4.0
SAVED_MV = 50.0  # the simulated PLCs start steady in AUTO at MV 50
WAIT = 60.0


def wait_for(predicate: Any, timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while not (value := predicate()):
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.1)
    return value


class Plant:
    """`autotuner sim --loops 6` and a Modbus client of our own reading each loop's unit."""

    def __init__(self, tmp: Path) -> None:
        self.port = free_port()
        self.log = tmp / "plant.log"
        with open(self.log, "w") as out:
            self.proc = subprocess.Popen([sys.executable, "-m", "autotuner.cli", "sim", "--loops", str(LOOPS),
                                          "--modbus", f"127.0.0.1:{self.port}", "--speed", "10"], stdout=out,
                                         stderr=subprocess.STDOUT)
        self.client = ModbusTcpClient("127.0.0.1", port=self.port, timeout=2.0, retries=1)
        wait_for(lambda: "serving" in self.log.read_text() or self.proc.poll() is not None, WAIT, "the plant")
        assert self.proc.poll() is None and self.client.connect(), self.log.read_text()

    def url(self, k: int) -> str:
        return f"modbus://127.0.0.1:{self.port}/{k}?timeout=0.5"

    def read(self, k: int) -> dict[str, Any]:
        """Mode, manual MV (hv), TBSY, TE and ite of loop k, read now."""
        mode = self.client.read_holding_registers(DEFAULT_MAP["mode"].address, count=1, device_id=k)
        hv = self.client.read_holding_registers(DEFAULT_MAP["hv"].address, count=2, device_id=k)
        ite = self.client.read_holding_registers(DEFAULT_MAP["ite"].address, count=2, device_id=k)
        coils = self.client.read_coils(DEFAULT_MAP["tune"].address, count=4, device_id=k)
        assert not (mode.isError() or hv.isError() or ite.isError() or coils.isError())
        return {"mode": "AUTO" if mode.registers[0] == 1 else "MAN", "hv": DEFAULT_MAP.decode("hv", hv.registers),
                "ite": DEFAULT_MAP.decode("ite", ite.registers), "tbsy": coils.bits[2], "te": coils.bits[3]}

    def epoch(self, k: int) -> int:
        """The newest lease epoch written to loop k's device (its ``epoch`` register), read now."""
        reg = DEFAULT_MAP["epoch"]
        r = self.client.read_holding_registers(reg.address, count=reg.size, device_id=k)
        assert not r.isError(), r
        return int(DEFAULT_MAP.decode("epoch", r.registers))

    def close(self) -> None:
        self.client.close()
        self.proc.kill()
        self.proc.wait()


@pytest.fixture
def database(postgres) -> str:  # noqa: F811 - the imported fixture
    """A fresh PostgreSQL database for one fleet's history."""
    return new_database(postgres)


@pytest.fixture
def plant(tmp_path) -> Iterator[Plant]:
    p = Plant(tmp_path)
    try:
        yield p
    finally:
        p.close()


def fleet_config(tmp: Path, name: str, database: str, plant: Plant, lease: float = LEASE,
                 renew: float | None = None) -> Path:
    loops = [{"id": f"L{k}", "link": plant.url(k), "ts": 0.3, "speed": 10, "monitor_period": 0.5,
              "tuning": {"amp": 5.0}} for k in range(1, LOOPS + 1)]
    path = tmp / f"{name}.yaml"
    timing = {"lease": lease} if renew is None else {"lease": lease, "renew": renew}
    path.write_text(json.dumps({
        "history": database, "loops": loops, "fleet": {"name": name, **timing},
        "handback": {"watchdog": 0.0, "shutdown": 8.0},
        "tokens": [{"name": "root", "role": "admin", "sha256": token_hash(ADMIN)}]}))
    return path


def fleet(d: Daemon) -> dict[str, Any]:
    return httpx.get(f"{d.base}/fleet", headers=d.headers, timeout=10).json()


def owned(d: Daemon, name: str) -> set[str]:
    return {loop for loop, owner in fleet(d)["loops"].items() if owner and owner["name"] == name}


def split(a: Daemon, b: Daemon) -> dict[str, Any] | None:
    """The fleet as ``a`` sees it once every loop has an owner and both daemons hold their share (3 each)."""
    seen = fleet(a)
    owners = [o["name"] if o else "" for o in seen["loops"].values()]
    return seen if sorted(owners) == ["a"] * 3 + ["b"] * 3 else None


def test_two_daemons_split_the_loops_and_every_status_names_the_owner(tmp_path, database, plant):
    with Daemon(fleet_config(tmp_path, "a", database, plant), TOKEN) as a, \
            Daemon(fleet_config(tmp_path, "b", database, plant), TOKEN) as b:
        seen = wait_for(lambda: split(a, b), WAIT, "the loops split 3/3")
        assert {m["name"] for m in seen["members"]} == {"a", "b"}
        assert fleet(b)["loops"] == seen["loops"]  # both daemons agree on every owner
        for loop_id, owner in seen["loops"].items():
            for d in (a, b):
                status = httpx.get(f"{d.base}/loops/{loop_id}", headers=d.headers, timeout=10).json()
                assert status["owner"] == owner, (d.port, loop_id)
        assert owner["url"] in (f"http://127.0.0.1:{a.port}", f"http://127.0.0.1:{b.port}")


def test_a_tune_asked_of_both_daemons_at_once_runs_one_experiment(tmp_path, database, plant):
    with Daemon(fleet_config(tmp_path, "a", database, plant), TOKEN) as a, \
            Daemon(fleet_config(tmp_path, "b", database, plant), TOKEN) as b:
        seen = wait_for(lambda: split(a, b), WAIT, "the loops split 3/3")
        loop_id = next(loop for loop, owner in seen["loops"].items() if owner["name"] == "b")
        answers: list[httpx.Response] = []

        def ask(d: Daemon) -> None:
            answers.append(httpx.post(f"{d.base}/loops/{loop_id}/tune", headers=d.headers, json={}, timeout=10))

        threads = [threading.Thread(target=ask, args=(d,)) for d in (a, b)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        codes = sorted(r.status_code for r in answers)
        assert codes == [202, 307], [r.text for r in answers]
        moved = next(r for r in answers if r.status_code == 307)
        assert moved.headers["location"] == f"{b.base}/loops/{loop_id}/tune" and moved.json()["code"] == "not_owner"
        # Following the redirect finds the owner busy with the one experiment.
        again = httpx.post(moved.headers["location"], headers=b.headers, json={}, timeout=10)
        assert again.status_code == 409 and again.json()["code"] == "busy", again.text
        engine = sa.create_engine(database)
        with engine.connect() as db:
            sessions = db.execute(sa.text("SELECT count(*) FROM sessions WHERE loop = :l"), {"l": loop_id}).scalar()
        engine.dispose()
        assert sessions == 1


def test_a_killed_daemons_loop_is_taken_over_within_the_lease_and_restored(tmp_path, database, plant):
    with Daemon(fleet_config(tmp_path, "a", database, plant), TOKEN) as a, \
            Daemon(fleet_config(tmp_path, "b", database, plant), TOKEN) as b:
        seen = wait_for(lambda: split(a, b), WAIT, "the loops split 3/3")
        loop_id = next(loop for loop, owner in seen["loops"].items() if owner["name"] == "b")
        k = int(loop_id[1:])
        sid = httpx.post(f"{b.base}/loops/{loop_id}/tune", headers=b.headers, json={}, timeout=10).json()["session"]
        wait_for(lambda: (r := plant.read(k))["mode"] == "MAN" and abs(r["hv"] - SAVED_MV) > 2.0, WAIT,
                 "the relay to hold the loop")
        b.kill()  # the whole tuner: its machine lost
        killed = time.monotonic()
        wait_for(lambda: loop_id in owned(a, "a"), LEASE + 10.0, "the survivor to take the loop over")
        taken = time.monotonic() - killed
        status = wait_for(lambda: (s := httpx.get(f"{a.base}/loops/{loop_id}", headers=a.headers,
                                                  timeout=10).json())["restore"] is None and "restored" in
                          s["message"] and s, WAIT, "the session recovered and the loop restored")
        now = plant.read(k)
        assert now["mode"] == "AUTO" and not now["tbsy"], now  # (in AUTO the manual MV tracks the PID's output)
        assert status["session"] == sid and "loop restored to AUTO with MV 50" in status["message"]
        assert len(owned(a, "a")) == LOOPS  # every loop of the dead daemon
    assert taken <= LEASE + 10.0


def test_a_daemon_frozen_past_its_lease_writes_nothing_once_it_runs_again(tmp_path, database, plant):
    with Daemon(fleet_config(tmp_path, "a", database, plant), TOKEN) as a, \
            Daemon(fleet_config(tmp_path, "b", database, plant), TOKEN) as b:
        seen = wait_for(lambda: split(a, b), WAIT, "the loops split 3/3")
        loop_id = next(loop for loop, owner in seen["loops"].items() if owner["name"] == "b")
        k = int(loop_id[1:])
        httpx.post(f"{b.base}/loops/{loop_id}/tune", headers=b.headers, json={}, timeout=10)
        wait_for(lambda: (r := plant.read(k))["mode"] == "MAN" and abs(r["hv"] - SAVED_MV) > 2.0, WAIT,
                 "the relay to hold the loop")
        os.killpg(b.proc.pid, signal.SIGSTOP)  # the whole tuner frozen (a stalled machine)
        try:
            wait_for(lambda: loop_id in owned(a, "a"), LEASE + 10.0, "the survivor to take the loop over")
            wait_for(lambda: plant.read(k)["mode"] == "AUTO", WAIT, "the survivor to restore the loop")
            restored = plant.read(k)
        finally:
            os.killpg(b.proc.pid, signal.SIGCONT)
        readings = []
        end = time.monotonic() + 5.0  # the frozen one runs again: its session's next writes would come now
        while time.monotonic() < end:
            readings.append(plant.read(k))
            time.sleep(0.05)
        # What a session writes — MAN and relay levels, TBSY and the seconds left in ite every 0.5 s — never comes:
        # the loop stays as the survivor restored it (TE set, ite its code). (In AUTO the manual MV tracks the
        # PID's output: not a sign of anything.)
        for now in readings:
            assert now["mode"] == "AUTO" and not now["tbsy"] and now["te"] and now["ite"] == restored["ite"], now
        b.wait_until(lambda: f"loop {loop_id}: its lease (epoch" in b.log() and "ended after this daemon lost the "
                     "loop's lease" in b.log(), WAIT, "the frozen daemon to say it lost the loop")
        assert owned(a, "a") | owned(a, "b") == {f"L{k}" for k in range(1, LOOPS + 1)}  # every loop owned again


def test_a_daemon_superseded_on_the_device_stops_writing_at_once_and_the_next_owner_restores(tmp_path, database,
                                                                                               plant):
    """The device-side fence: b tunes a loop, its lease's epoch on the device; a newer epoch reaches the device while
    b's own clock and the database still say b holds the lease (the test's own client writes it, as the next owner's
    first write would: a daemon restores within a sample time, faster than b would write again, so a takeover alone
    seldom meets one of b's writes). b's next relay level is refused by the device: b logs it naming both epochs, writes
    nothing more, gives the lease up and records nothing; the next owner takes the lease with that epoch, its writes
    pass the fence, and it restores the loop."""
    with Daemon(fleet_config(tmp_path, "a", database, plant), TOKEN) as a, \
            Daemon(fleet_config(tmp_path, "b", database, plant), TOKEN) as b:
        seen = wait_for(lambda: split(a, b), WAIT, "the loops split 3/3")
        loop_id = next(loop for loop, owner in seen["loops"].items() if owner["name"] == "b")
        k, old = int(loop_id[1:]), seen["loops"][loop_id]["epoch"]
        httpx.post(f"{b.base}/loops/{loop_id}/tune", headers=b.headers, json={}, timeout=10)
        wait_for(lambda: (r := plant.read(k))["mode"] == "MAN" and abs(r["hv"] - SAVED_MV) > 2.0, WAIT,
                 "the relay to hold the loop")
        assert plant.epoch(k) == old  # b's epoch went to the device with its first write
        reg = DEFAULT_MAP["epoch"]
        written = plant.client.write_registers(reg.address, DEFAULT_MAP.encode("epoch", old + 1), device_id=k)
        assert not written.isError(), written
        try:
            b.wait_until(lambda: f"loop {loop_id}: its device refused this daemon's write under lease epoch {old}"
                         in b.log(), WAIT, "b to be fenced by the device")
        except AssertionError as exc:
            raise AssertionError(f"{exc}\nthe plant's log:\n{plant.log.read_text()}") from None
        assert f"lease epoch {old + 1}, newer than this daemon's epoch {old}" in b.log()
        wait_for(lambda: f"unit {k}: refused the writes of" in plant.log.read_text(), WAIT, "the plant's log")
        assert f"its lease epoch {old} is older than the unit's {old + 1}" in plant.log.read_text()
        frozen = plant.read(k)
        readings = []
        end = time.monotonic() + 1.0
        while time.monotonic() < end and (now := plant.read(k))["mode"] == "MAN":
            readings.append(now)
            time.sleep(0.05)
        # b's relay levels (every 0.03 s) and its countdown in ite (every 0.5 s) stop at once: until the next owner
        # restores the loop, it holds the last level b wrote.
        assert readings and all(r == frozen for r in readings), (frozen, readings)
        b.wait_until(lambda: "ended after this daemon lost the loop's lease" in b.log(), WAIT,
                     "b to end its session without a record")
        wait_for(lambda: plant.read(k)["mode"] == "AUTO", WAIT, "the next owner to restore the loop")
        owner = wait_for(lambda: (o := fleet(a)["loops"][loop_id]) and o["epoch"] == old + 1 and o, WAIT,
                         "the next owner's lease")
        assert plant.epoch(k) == owner["epoch"] == old + 1
        assert plant.log.read_text().count("refused the writes of") == 1  # nobody else was refused


def test_a_drained_daemon_hands_its_idle_loops_to_the_others(tmp_path, database, plant):
    with Daemon(fleet_config(tmp_path, "a", database, plant), TOKEN) as a, \
            Daemon(fleet_config(tmp_path, "b", database, plant), TOKEN) as b:
        wait_for(lambda: split(a, b), WAIT, "the loops split 3/3")
        r = httpx.post(f"{a.base}/fleet/drain", headers={"Authorization": f"Bearer {ADMIN}"},
                       json={"drain": True}, timeout=10)
        assert r.status_code == 200 and r.json()["draining"] is True, r.text
        forbidden = httpx.post(f"{a.base}/fleet/drain", headers=a.headers, json={"drain": False}, timeout=10)
        assert forbidden.status_code == 403  # an operator may not
        wait_for(lambda: len(owned(b, "b")) == LOOPS, 3 * LEASE, "every loop on the other daemon")
        assert owned(a, "a") == set()
