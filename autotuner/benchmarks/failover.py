"""Failover benchmark of a fleet: K daemons on one PostgreSQL share N loops; one is killed while it tunes some.

Everything runs as real processes on this machine: a PostgreSQL server (the
given database, or one of its own: :mod:`autotuner.benchmarks.postgres`),
the plant (``autotuner sim --loops``, 247 loops per process, loop k of a
process on unit id k), and K ``autotuner serve`` daemons with the same N
loops, the same history and a lease of ``lease`` seconds.

Once the loops are split evenly, ``tuning`` loops of the first daemon are
tuned through its API; every answer is kept (a 409 ``overloaded`` is a
result, not a hang). Once each accepted tuning has been seen at its relay
(or has ended already: not all at once), or after ``relay_wait`` seconds
whatever they do, that daemon — its process group: the daemon and its
sampler — gets SIGKILL; how many were running, and how many at their
relay, is reported. Measured from then, through the survivors' ``GET
/fleet`` (polled every 0.2 s): when each of its loops has a live owner
again (p50, p99, max, seconds), how many never did within ``lease + 120``
s; and, from the shared history, how each accepted session is recorded
(state, code, and how the new owner dealt with its loop: restored, found
back, …) once every record is final (or after two minutes, as it is).

Every process the run starts is stopped when it ends, however it ends: a
result, an error, SIGTERM or SIGINT (the daemons and the plant by their
process groups, SIGTERM then SIGKILL; the PostgreSQL server by ``pg_ctl
stop``). Every wait is bounded and names what it waited for.
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
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

import httpx
import numpy as np

from autotuner.benchmarks.postgres import new_database, temporary_postgres
from autotuner.service.remote_tuning import PLANT_TICKS_PER_SAMPLE

TOKEN = "failover-benchmark-operator-token"
UNITS = 247  # loops per plant process (Modbus unit ids)
LOOP_TS = 0.3  # the loops' experiment sample time, plant seconds
START_WAIT = 180.0  # s: a plant serving, the loops split
STOP_WAIT = 20.0  # s: a child stopping on SIGTERM before it gets SIGKILL
POLL = 0.2  # s between two looks at the fleet
RECORD_WAIT = 120.0  # s after the takeovers for the interrupted sessions' records to be final


@dataclass(frozen=True)
class FailoverSpec:
    """``daemons`` sharing ``loops`` with a ``lease`` (s); ``tuning`` loops of the victim asked to tune before it is
    killed, ``relay_wait`` (s) the longest wait for them to run; the plants at ``speed`` plant seconds per wall
    second; each daemon with ``samplers`` sampler processes and its loops' ``monitor_period`` (wall s);
    ``database``: a PostgreSQL URL (None: a server of the benchmark's own)."""

    daemons: int = 3
    loops: int = 300
    tuning: int = 20
    lease: float = 10.0
    speed: float = 10.0
    samplers: int = 1
    monitor_period: float = 1.0
    relay_wait: float = 60.0
    database: str | None = None


@dataclass(frozen=True)
class FailoverResult:
    """What a run measured: the victim's loops; the answers to its TUNEs (``"202"``, ``"409 overloaded"``, … →
    count); its sessions running (TBSY) and at their relay at the kill, ``waited`` s after the TUNEs; each of its
    loops' time to a new owner (s, those owned again); how its accepted sessions are recorded in the history
    (``"interrupted, code 1: loop restored to AUTO"`` … → count)."""

    spec: FailoverSpec
    victim_loops: int
    answers: dict[str, int]
    running: int
    at_relay: int
    waited: float
    times: tuple[float, ...]
    records: dict[str, int]

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile of the takeover times, s (NaN if no loop was owned again)."""
        return float(np.percentile(self.times, q)) if self.times else math.nan

    @property
    def unowned(self) -> int:
        """The victim's loops with no live owner at the end of the wait."""
        return self.victim_loops - len(self.times)

    @property
    def interrupted(self) -> int:
        """The accepted sessions the kill interrupted (not recorded as finished by the victim itself)."""
        return sum(n for key, n in self.records.items() if not key.startswith("finished"))

    @property
    def dealt_with(self) -> int:
        """The interrupted sessions whose loops their new owner has dealt with (the record final: ``interrupted``)."""
        return sum(n for key, n in self.records.items() if key.startswith("interrupted"))


class _Signals:
    """While active, SIGTERM and SIGINT raise SystemExit(128 + signal) in the main thread, once: later ones are
    ignored, so the clean-up they start runs to its end. While :meth:`held` the exit waits for the block's end: a
    child process started and not yet listed, or a clean-up half done, would leave processes behind."""

    def __init__(self) -> None:
        self._held, self._pending = 0, 0
        self._previous: dict[int, Any] = {}

    def _handler(self, signum: int, frame: FrameType | None) -> None:
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, signal.SIG_IGN)
        if self._held:
            self._pending = signum
            return
        raise SystemExit(128 + signum)

    @contextmanager
    def active(self) -> Iterator[None]:
        """Turn the signals into an exit for the block (where this is not the main thread: left as they are)."""
        with suppress(ValueError):  # not the main thread
            self._previous = {sig: signal.signal(sig, self._handler) for sig in (signal.SIGTERM, signal.SIGINT)}
        try:
            yield
        finally:
            for sig, handler in self._previous.items():
                signal.signal(sig, handler)

    @contextmanager
    def held(self) -> Iterator[None]:
        """A block no signal interrupts: the exit a signal asks meanwhile happens at its end."""
        self._held += 1
        try:
            yield
        finally:
            self._held -= 1
            if not self._held and self._pending:
                raise SystemExit(128 + self._pending)

    @contextmanager
    def cleaned_up(self) -> Iterator[ExitStack]:
        """An ExitStack closed at the block's end, however it ends, its clean-up held (no signal interrupts it)."""
        stack = ExitStack()
        try:
            yield stack
        finally:
            with self.held():
                stack.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Processes:
    """Child processes started for the run (each in a process group of its own), stopped at its end."""

    def __init__(self, folder: Path, signals: _Signals) -> None:
        self.folder, self.signals = folder, signals
        self.started: dict[str, subprocess.Popen[bytes]] = {}
        self.killed: set[str] = set()

    def start(self, name: str, args: list[str], env: dict[str, str] | None = None) -> subprocess.Popen[bytes]:
        """Start ``autotuner ARGS`` as ``name`` (its output in ``name.log``)."""
        with self.signals.held(), open(self.folder / f"{name}.log", "w") as out:
            proc = subprocess.Popen([sys.executable, "-m", "autotuner.cli", *args], stdout=out, stderr=out,
                                    env={**os.environ, **(env or {})}, start_new_session=True)
            self.started[name] = proc
        return proc

    def kill(self, name: str) -> None:
        """SIGKILL of ``name``'s process group (the process and what it started)."""
        self.killed.add(name)
        with suppress(ProcessLookupError):
            os.killpg(self.started[name].pid, signal.SIGKILL)

    def log(self, name: str) -> str:
        """What ``name`` wrote so far."""
        return (self.folder / f"{name}.log").read_text(errors="replace")

    def check(self) -> None:
        """RuntimeError naming the first child (not killed on purpose) that has exited, with its last words."""
        for name, proc in self.started.items():
            if name not in self.killed and proc.poll() is not None:
                tail = "\n".join(self.log(name).strip().splitlines()[-8:])
                raise RuntimeError(f"{name} exited with code {proc.returncode}:\n{tail}")

    def stop(self) -> None:
        """SIGTERM to every child (a daemon stops its samplers itself: SIGTERM to them too, it would start them
        again), SIGKILL to the groups of those still there after STOP_WAIT s and to what remains of each group."""
        for proc in self.started.values():
            if proc.poll() is None:
                proc.terminate()
        deadline = time.monotonic() + STOP_WAIT
        for proc in self.started.values():
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
            with suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


class _Api:
    """The daemons' APIs, by port."""

    def __init__(self) -> None:
        self.client = httpx.Client(headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10.0)

    def get(self, port: int, path: str) -> Any:
        """``GET /api/v1{path}`` of the daemon at ``port`` (JSON); httpx.HTTPError if it does not answer."""
        response = self.client.get(f"http://127.0.0.1:{port}/api/v1{path}")
        response.raise_for_status()
        return response.json()

    def tune(self, port: int, loop_id: str) -> tuple[str, str | None]:
        """Ask for a TUNE of ``loop_id``: (the answer, e.g. ``"202"`` or ``"409 overloaded"``, the session id)."""
        try:
            response = self.client.post(f"http://127.0.0.1:{port}/api/v1/loops/{loop_id}/tune", json={})
        except httpx.HTTPError as exc:
            return f"no answer ({type(exc).__name__})", None
        try:
            body = response.json()
        except ValueError:
            body = {}
        if response.status_code == 202:
            return "202", body.get("session")
        return f"{response.status_code} {body.get('code', '')}".strip(), None


def _wait(predicate: Callable[[], Any], timeout: float, what: str, procs: _Processes) -> Any:
    """``predicate()`` once it is true (an HTTP error counts as not yet), within ``timeout`` s; RuntimeError naming
    ``what`` (and the last HTTP error) if not, or at once if a child has exited."""
    deadline, error = time.monotonic() + timeout, ""
    while True:
        procs.check()
        try:
            if value := predicate():
                return value
        except httpx.HTTPError as exc:
            error = f" (last answer: {type(exc).__name__}: {exc})"
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out after {timeout:g} s waiting for {what}{error}")
        time.sleep(POLL)


def run_failover(spec: FailoverSpec, progress: Callable[[str], None] = lambda text: None) -> FailoverResult:
    """Run ``spec`` (module docstring), telling ``progress`` each step; RuntimeError if a step does not happen in
    time, SystemExit(128 + signal) on SIGTERM or SIGINT — every process it started stopped first."""
    signals = _Signals()
    with signals.active(), signals.cleaned_up() as stack:
        database = spec.database
        if database is None:
            with signals.held():
                server = stack.enter_context(temporary_postgres())
            progress(f"PostgreSQL server of its own: {server}")
            database = new_database(server)
        folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="autotuner-failover-")))
        procs = _Processes(folder, signals)
        stack.callback(procs.stop)
        api = _Api()
        stack.callback(api.client.close)
        return _run(spec, database, procs, api, progress)


def _run(spec: FailoverSpec, database: str, procs: _Processes, api: _Api,
         progress: Callable[[str], None]) -> FailoverResult:
    ports = _start(spec, database, procs, progress)
    start = time.monotonic()
    share = math.ceil(spec.loops / spec.daemons)
    seen = _wait(lambda: _split(api, ports[-1], share, spec.loops), START_WAIT, "the loops split evenly", procs)
    progress(f"the loops split evenly {time.monotonic() - start:.1f} s after the daemons started")
    mine = sorted(loop for loop, owner in seen["loops"].items() if owner["name"] == "d0")
    answers = {loop_id: api.tune(ports[0], loop_id) for loop_id in mine[:spec.tuning]}
    sessions = {loop_id: sid for loop_id, (_, sid) in answers.items() if sid}
    counts = dict(Counter(answer for answer, _ in answers.values()))
    progress(f"TUNE of {len(answers)} loops of d0: {counts}")
    running, at_relay, waited = _await_running(api, ports[0], sessions, spec.relay_wait, procs)
    procs.kill("d0")  # d0 and its sampler: its machine lost
    killed = time.monotonic()
    progress(f"SIGKILL of d0 {waited:.1f} s after the TUNEs: {running} session(s) running, {at_relay} at the relay; "
             f"load average {os.getloadavg()[0]:.2f}")
    times = _takeovers(api, ports[1:], mine, killed, spec.lease + 120.0, procs)
    progress(f"{len(times)}/{len(mine)} loops of d0 owned again, the last {max(times.values(), default=0):.1f} s "
             f"after the kill")
    records = _recorded(api, ports[1], sessions, procs)
    progress(f"sessions recorded: {records}; load average {os.getloadavg()[0]:.2f}")
    return FailoverResult(spec, len(mine), counts, running, at_relay, waited, tuple(sorted(times.values())), records)


def _start(spec: FailoverSpec, database: str, procs: _Processes, progress: Callable[[str], None]) -> list[int]:
    """Start the plants, then the daemons; their API ports."""
    urls = _plants(spec, procs)
    progress(f"plant of {spec.loops} loops serving")
    ports = [_free_port() for _ in range(spec.daemons)]
    loops = [{"id": f"L{k:03d}", "link": url, "ts": LOOP_TS, "speed": spec.speed,
              "monitor_period": spec.monitor_period, "tuning": {"amp": 5.0}} for k, url in enumerate(urls, 1)]
    for i, port in enumerate(ports):
        config = procs.folder / f"d{i}.yaml"
        config.write_text(json.dumps({"history": database, "loops": loops, "handback": {"watchdog": 0.0},
                                      "samplers": spec.samplers, "fleet": {"name": f"d{i}", "lease": spec.lease}}))
        procs.start(f"d{i}", ["serve", "--config", str(config), "--port", str(port), "--log-level", "warning"],
                    {"AUTOTUNER_TOKEN": TOKEN})
    progress(f"{spec.daemons} daemons started")
    return ports


def _plants(spec: FailoverSpec, procs: _Processes) -> list[str]:
    """Start the plant processes; the link URL of every loop."""
    urls = []
    for first in range(0, spec.loops, UNITS):
        count, port = min(UNITS, spec.loops - first), _free_port()
        # 5 plant ticks per sample of the loops (as `autotuner sim` makes for a plant's own sample time): a finer
        # plant costs the plant process CPU the daemons need (300 loops ticked at 3 ms: most of a core).
        procs.start(f"plant{first}", ["sim", "--loops", str(count), "--modbus", f"127.0.0.1:{port}", "--speed",
                                      str(spec.speed), "--ts", f"{LOOP_TS / PLANT_TICKS_PER_SAMPLE:g}"])
        # 16 requests in flight on each daemon's connection to a plant (as loadbench's): one at a time, a
        # daemon's monitor of 150 loops behind one connection waited for a plant busy with 247.
        urls += [f"modbus://127.0.0.1:{port}/{k}?timeout=0.5&pipeline=16" for k in range(1, count + 1)]
        _wait(lambda name=f"plant{first}": "serving" in procs.log(name), START_WAIT, f"plant{first} to serve", procs)
    return urls


def _split(api: _Api, port: int, share: int, loops: int) -> dict[str, Any] | None:
    """The fleet as the daemon at ``port`` sees it once every loop has an owner and none holds more than ``share``."""
    seen = api.get(port, "/fleet")
    names = [owner["name"] for owner in seen["loops"].values() if owner]
    counts = Counter(names)
    return seen if len(names) == loops and max(counts.values()) <= share and len(counts) > 1 else None


def _await_running(api: _Api, port: int, sessions: dict[str, str], limit: float,
                   procs: _Processes) -> tuple[int, int, float]:
    """Wait until every session of ``sessions`` (loop → id) has been seen at its relay (the loop taken over) or has
    ended — not all at once: a short experiment may end before another starts —, or ``limit`` s have passed: (how
    many run (TBSY) and how many are at their relay at the last look, the seconds waited)."""
    start = time.monotonic()
    running, at_relay, seen = 0, 0, set()
    while len(seen) < len(sessions) and time.monotonic() - start <= limit:
        procs.check()
        with suppress(httpx.HTTPError):
            status = [s for s in api.get(port, "/loops") if s["session"] == sessions.get(s["id"], "")]
            running = sum(s["tbsy"] for s in status)
            at_relay = sum(s["tbsy"] and s["stage"] == "relay" for s in status)
            seen |= {s["id"] for s in status if s["stage"] in ("relay", "done")}
        time.sleep(2.5 * POLL)  # (every loop's status: not too often, the daemon has its tunings to run)
    return running, at_relay, time.monotonic() - start


def _takeovers(api: _Api, ports: list[int], mine: list[str], killed: float, limit: float,
               procs: _Processes) -> dict[str, float]:
    """Seconds from ``killed`` (monotonic) until each loop of ``mine`` had a live owner other than d0, as the
    survivors' ``/fleet`` shows it (asked in turn), within ``limit`` s."""
    taken: dict[str, float] = {}
    turn = 0
    while len(taken) < len(mine) and time.monotonic() < killed + limit:
        procs.check()
        turn += 1
        with suppress(httpx.HTTPError):
            seen = api.get(ports[turn % len(ports)], "/fleet")["loops"]
            now = time.monotonic() - killed
            for loop_id in mine:
                owner = seen.get(loop_id)
                if loop_id not in taken and owner and owner["name"] != "d0":
                    taken[loop_id] = now
        time.sleep(POLL)
    return taken


def _recorded(api: _Api, port: int, sessions: dict[str, str], procs: _Processes) -> dict[str, int]:
    """How the sessions (loop → id) are recorded in the history, read through the daemon at ``port`` (state, code
    and how the loop was dealt with → count), once every record is final — finished, or interrupted and its loop
    handed back, found back or left as an operator set it (the new owner appends how) — or as they are after
    RECORD_WAIT s (``not_restored``: its loop not handed back yet)."""
    deadline = time.monotonic() + RECORD_WAIT
    while True:
        procs.check()
        try:
            records = [_record(api, port, loop_id, sid) for loop_id, sid in sessions.items()]
            if all(r["state"] in ("finished", "interrupted") for r in records) or time.monotonic() > deadline:
                return dict(sorted(Counter(_how(r) for r in records).items()))
        except httpx.HTTPError:
            if time.monotonic() > deadline:
                raise RuntimeError(f"the survivors did not answer within {RECORD_WAIT:g} s") from None
        time.sleep(1.0)


def _how(record: dict[str, Any]) -> str:
    """A session's record in a few words: its state, code and what its message ends with, the MV left out
    (``interrupted, code 1: loop restored to AUTO``)."""
    last = (record.get("message") or "").rsplit("; ", 1)[-1]
    return f"{record['state']}, code {record['code']}: {last.split(' with MV')[0]}"


def _record(api: _Api, port: int, loop_id: str, sid: str) -> dict[str, Any]:
    """Session ``sid``'s record in loop ``loop_id``'s history, as the daemon at ``port`` reads it."""
    found = [r for r in api.get(port, f"/loops/{loop_id}/history") if r["id"] == sid]
    return found[0] if found else {"state": "missing", "code": None}


HEADERS = ["daemons", "loops", "lease s", "loops of the killed daemon", "TUNE answers", "running at the kill",
           "owned again p50 s", "p99 s", "max s", "not owned again", "sessions recorded",
           "interrupted, dealt with"]


def table_rows(results: list[FailoverResult]) -> list[list[str]]:
    """Rows of the table (markdown and the command's)."""
    return [[str(r.spec.daemons), str(r.spec.loops), f"{r.spec.lease:g}", str(r.victim_loops),
             ", ".join(f"{answer}: {n}" for answer, n in r.answers.items()),
             f"{r.running} ({r.at_relay} at the relay)", f"{r.percentile(50):.1f}", f"{r.percentile(99):.1f}",
             f"{r.percentile(100):.1f}", str(r.unowned), ", ".join(f"{key}: {n}" for key, n in r.records.items()),
             f"{r.dealt_with}/{r.interrupted}"] for r in results]


def markdown(results: list[FailoverResult]) -> str:
    """The results as a markdown table."""
    lines = ["| " + " | ".join(HEADERS) + " |", "|" + "---:|" * len(HEADERS)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in table_rows(results)])
