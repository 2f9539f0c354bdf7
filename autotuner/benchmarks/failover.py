"""Failover benchmark of a fleet: K daemons on one PostgreSQL share N loops; one is killed while it tunes some.

Everything runs as real processes on this machine: a PostgreSQL server (the
given database, or one of its own: :mod:`autotuner.benchmarks.postgres`),
the plant (``autotuner sim --loops``, 247 loops per process, loop k of a
process on unit id k), and K ``autotuner serve`` daemons with the same N
loops, the same history and a lease of ``lease`` seconds. Once the loops are
split evenly, ``tuning`` loops of the first daemon are tuned; once their
relays run, that daemon — its process group: the daemon and its sampler —
gets SIGKILL. Measured from then, through the survivors' ``GET /fleet``
(polled every 0.2 s): when each of its loops has a live owner again (p50,
p99, max, seconds), and how many of its interrupted sessions a survivor has
recovered and restored (their status's message says how) within
``lease + 60`` seconds.
"""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from autotuner.benchmarks.postgres import new_database, temporary_postgres

TOKEN = "failover-benchmark-operator-token"
UNITS = 247  # loops per plant process (Modbus unit ids)
START_WAIT = 180.0


@dataclass(frozen=True)
class FailoverSpec:
    """``daemons`` sharing ``loops`` with a ``lease`` (s); ``tuning`` loops of the victim tuned when it is killed;
    the plants at ``speed`` plant seconds per wall second; ``database``: a PostgreSQL URL (None: a server of the
    benchmark's own)."""

    daemons: int = 3
    loops: int = 300
    tuning: int = 20
    lease: float = 10.0
    speed: float = 10.0
    database: str | None = None


@dataclass(frozen=True)
class FailoverResult:
    """What a run measured: the victim's loops and sessions, the takeover times (s), the sessions restored."""

    spec: FailoverSpec
    victim_loops: int
    interrupted: int
    p50: float
    p99: float
    worst: float
    restored: int


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(predicate: Callable[[], Any], timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while not (value := predicate()):
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.2)
    return value


class _Processes:
    """Child processes started for the run, stopped (their process groups killed) at its end."""

    def __init__(self, folder: Path) -> None:
        self.folder, self.started = folder, []

    def start(self, name: str, args: list[str], env: dict[str, str] | None = None) -> subprocess.Popen[bytes]:
        with open(self.folder / f"{name}.log", "w") as out:
            proc = subprocess.Popen([sys.executable, "-m", "autotuner.cli", *args], stdout=out, stderr=out,
                                    env={**os.environ, **(env or {})}, start_new_session=True)
        self.started.append(proc)
        return proc

    def log(self, name: str) -> str:
        return (self.folder / f"{name}.log").read_text(errors="replace")

    def stop(self) -> None:
        for proc in self.started:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
        for proc in self.started:
            try:
                proc.wait(40)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()


def _get(port: int, path: str) -> Any:
    return httpx.get(f"http://127.0.0.1:{port}/api/v1{path}", headers={"Authorization": f"Bearer {TOKEN}"},
                     timeout=10).json()


def run_failover(spec: FailoverSpec) -> FailoverResult:
    """Run ``spec`` (module docstring)."""
    with ExitStack() as stack:
        database = spec.database or new_database(stack.enter_context(temporary_postgres()))
        folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="autotuner-failover-")))
        procs = _Processes(folder)
        stack.callback(procs.stop)
        result = _run(spec, database, folder, procs)
    return result


def _run(spec: FailoverSpec, database: str, folder: Path, procs: _Processes) -> FailoverResult:
    urls = _plants(spec, procs)
    ports = [_free_port() for _ in range(spec.daemons)]
    loops = [{"id": f"L{k:03d}", "link": url, "ts": 0.3, "speed": spec.speed, "monitor_period": 1.0,
              "tuning": {"amp": 5.0}} for k, url in enumerate(urls, 1)]
    daemons = []
    for i, port in enumerate(ports):
        config = folder / f"d{i}.yaml"
        config.write_text(json.dumps({"history": database, "loops": loops, "handback": {"watchdog": 0.0},
                                      "fleet": {"name": f"d{i}", "lease": spec.lease}}))
        daemons.append(procs.start(f"d{i}", ["serve", "--config", str(config), "--port", str(port), "--log-level",
                                             "warning"], {"AUTOTUNER_TOKEN": TOKEN}))
    share = math.ceil(spec.loops / spec.daemons)
    seen = _wait(lambda: _split(ports[-1], share, spec.loops), START_WAIT, "the loops split evenly")
    mine = sorted(loop for loop, owner in seen["loops"].items() if owner["name"] == "d0")
    victims = mine[:spec.tuning]
    for loop_id in victims:
        httpx.post(f"http://127.0.0.1:{ports[0]}/api/v1/loops/{loop_id}/tune", json={},
                   headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10)
    _wait(lambda: all(_get(ports[0], f"/loops/{loop_id}")["stage"] == "relay" for loop_id in victims), START_WAIT,
          "the victim's relays")
    os.killpg(daemons[0].pid, signal.SIGKILL)  # d0 and its sampler: its machine lost
    killed = time.monotonic()
    taken: dict[str, float] = {}
    while len(taken) < len(mine) and time.monotonic() < killed + spec.lease + 120.0:
        for loop_id, owner in _get(ports[-1], "/fleet")["loops"].items():
            if loop_id in mine and loop_id not in taken and owner and owner["name"] != "d0":
                taken[loop_id] = time.monotonic() - killed
        time.sleep(0.2)
    restored = _wait(lambda: _restored(ports, victims, seen), spec.lease + 60.0, "the sessions recovered")
    times = np.asarray(list(taken.values()) or [math.nan])
    return FailoverResult(spec, len(mine), len(victims), float(np.percentile(times, 50)),
                          float(np.percentile(times, 99)), float(times.max()), restored)


def _plants(spec: FailoverSpec, procs: _Processes) -> list[str]:
    """Start the plant processes; the link URL of every loop."""
    urls = []
    for first in range(0, spec.loops, UNITS):
        count, port = min(UNITS, spec.loops - first), _free_port()
        procs.start(f"plant{first}", ["sim", "--loops", str(count), "--modbus", f"127.0.0.1:{port}", "--speed",
                                      str(spec.speed)])
        # 16 requests in flight on each daemon's connection to a plant (as loadbench's): one at a time, a
        # daemon's monitor of 150 loops behind one connection waited for a plant busy with 247.
        urls += [f"modbus://127.0.0.1:{port}/{k}?timeout=0.5&pipeline=16" for k in range(1, count + 1)]
        _wait(lambda name=f"plant{first}": "serving" in procs.log(name), START_WAIT, "a plant")
    return urls


def _split(port: int, share: int, loops: int) -> dict[str, Any] | None:
    """The fleet as the daemon at ``port`` sees it once every loop has an owner and none holds more than
    ``share``."""
    try:
        seen = _get(port, "/fleet")
    except httpx.HTTPError:
        return None
    names = [owner["name"] for owner in seen["loops"].values() if owner]
    counts = {name: names.count(name) for name in set(names)}
    return seen if len(names) == loops and max(counts.values()) <= share and len(counts) > 1 else None


def _restored(ports: list[int], victims: list[str], seen: dict[str, Any]) -> int | None:
    """How many of the victim's sessions a survivor has recovered (its status names the session and how the loop
    was found or handed back); None until every one of them has."""
    done = 0
    for loop_id in victims:
        owner = _get(ports[-1], "/fleet")["loops"][loop_id]
        if owner is None or owner["name"] == "d0":
            return None
        status = _get(int(owner["url"].rsplit(":", 1)[1]), f"/loops/{loop_id}")
        done += status["restore"] is None and status["session"] is not None and (
            "restored" in status["message"] or "found back" in status["message"])
    return done if done == len(victims) else None


HEADERS = ["daemons", "loops", "lease s", "loops of the killed daemon", "sessions interrupted",
           "owned again p50 s", "p99 s", "max s", "sessions recovered"]


def table_rows(results: list[FailoverResult]) -> list[list[str]]:
    """Rows of the table (markdown and the command's)."""
    return [[str(r.spec.daemons), str(r.spec.loops), f"{r.spec.lease:g}", str(r.victim_loops), str(r.interrupted),
             f"{r.p50:.1f}", f"{r.p99:.1f}", f"{r.worst:.1f}", f"{r.restored}/{r.interrupted}"] for r in results]


def markdown(results: list[FailoverResult]) -> str:
    """The results as a markdown table."""
    lines = ["| " + " | ".join(HEADERS) + " |", "|" + "---:|" * len(HEADERS)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in table_rows(results)])
