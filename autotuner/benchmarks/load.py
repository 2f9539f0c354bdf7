"""Load benchmark of the daemon: N loops tuned at once and M monitored, over Modbus TCP, with C clients watching.

The plant is a child process (:func:`drivers.modbus_plant.serve_plant`: one
task ticks every loop, 247 loops per Modbus server, loop k on unit id k) —
the field devices, kept off the daemon's CPU account, and at real-time
priority where the machine allows it (:data:`PLANT_RT_PRIORITY`): devices
have CPUs of their own, and a plant waiting for the same two cores as the
daemon and its clients would answer late and make its lateness the daemon's. The daemon is the real
one: the app of ``autotuner serve`` (its loop manager, its sampler
process(es), its design workers) served by uvicorn in this process, with N +
M loops (``modbus://127.0.0.1:PORT/UNIT``, ``apply: true``). With
``clients`` C, a second child opens C viewer event streams over the tuned
loops (``GET /loops/{id}/events``) for the whole run, half of them read and
half never read (a dashboard left open on many screens, some of them
asleep); with ``opcua`` a third subscribes to every variable of every loop
over OPC UA. All N TUNEs are asked at once, through the same call as REST's
(the fresh read of the loop first; a refusal is counted by its code).

Figures: how many tunings succeeded and the codes of the rest; the sessions'
sampling lateness — when each PV read completed behind its due time, as the
sessions themselves measure it (``SessionHooks.on_timing``; the link's round
trip included: what the experiment sees as jitter), p50/p99/max; the analysis
CPU per period (p50/p99/max); the daemon's CPU (its process, its samplers and
design workers, the samplers' analysis workers; % of one core) and peak RSS
(its process, its samplers and theirs), the
plant's CPU and the clients'.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import resource
import secrets
import socket
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from autotuner.engine.plant.expression import parse_process
from autotuner.service.channel import descendants, tree_cpu_seconds
from autotuner.service.config import DaemonConfig, TuneRequest
from autotuner.service.daemon.analyses import DEFAULT_WORKERS, WORKERS_ENV
from autotuner.service.design_pool import design_cpu

# A fast plant: one tuning is about a minute of plant time (ts 0.1 s: about 27 samples per period).
DEFAULT_PLANT = "exp(-0.5*s)/(s+1)"
DEFAULT_TS = 0.1
DEFAULT_SPEED = 1.0
VIEWER_NAME = "dashboard"
# Requests in flight on each plant server's connection (the loops' URLs' ?pipeline=).
PIPELINE = 16
# The plant process's real-time priority (SCHED_RR), above the samplers' (docs/daemon.md): it stands for devices.
PLANT_RT_PRIORITY = 30


@dataclass(frozen=True)
class LoadSpec:
    """One run: ``loops`` tuned at once, ``idle`` monitored only, ``clients`` viewer event streams (half never
    read), ``opcua`` a subscribed OPC UA client; the plant (``plant``, sample time ``ts`` plant seconds,
    ``speed`` plant seconds per wall second, measurement ``noise`` σ in PV units, ``loads`` (T, SIZE) steps at
    the process input T plant seconds after a tuner takes the loop, MV units); the relay ``amp`` (MV units),
    the experiments' ``time_limit`` (plant seconds), the loops' ``monitor_period`` (wall seconds), the
    daemon's ``samplers`` (0: in its own process) and each sampler's ``analysis_workers`` (0: threads); the
    loops' ``health_window`` and ``health_every`` (plant seconds; None: the config's defaults)."""

    loops: int
    idle: int = 0
    clients: int = 0
    opcua: bool = False
    noise: float = 0.0
    loads: tuple[tuple[float, float], ...] = ()
    plant: str = DEFAULT_PLANT
    ts: float = DEFAULT_TS
    speed: float = DEFAULT_SPEED
    amp: float = 5.0
    time_limit: float = 600.0
    monitor_period: float = 1.0
    samplers: int = 1
    analysis_workers: int = DEFAULT_WORKERS
    health_window: float | None = None
    health_every: float | None = None


@dataclass(frozen=True)
class LoadResult:
    """What one run measured (module docstring): times in ms, CPU in % of one core, RSS in MB."""

    spec: LoadSpec
    tuned: int
    codes: dict[str, int]
    failures: dict[str, str]
    wall: float
    samples: int
    late_p50: float
    late_p99: float
    late_max: float
    analysis_p50: float
    analysis_p99: float
    analysis_max: float
    cpu_daemon: float
    rss_daemon: float
    cpu_plant: float
    plant_realtime: bool = False
    cpu_clients: float | None = None
    events: int | None = None
    opcua_changes: int | None = None
    cpu_opcua: float | None = None
    assessed: int = 0  # health assessments made during the run
    health_cpu: float = 0.0  # their CPU in the workers, s (counted in cpu_daemon)


def _receive(conn: Any, child: Any, what: str) -> Any:
    """The ``what`` process's next message; RuntimeError if it dies first (it never answers then)."""
    while not conn.poll(0.2):
        if not child.is_alive():
            raise RuntimeError(f"the {what} process ended (exit code {child.exitcode}) before it answered")
    return conn.recv()


def _plant_main(spec: LoadSpec, conn: Any) -> None:
    """Child process: the plant of ``loops + idle`` loops; sends the loops' URLs, runs until told, sends its CPU."""
    from drivers.modbus_plant import serve_plant
    from autotuner.service.remote_tuning import PLANT_TICKS_PER_SAMPLE

    async def main() -> None:
        realtime = _plant_priority()
        plant = await serve_plant(spec.loops + spec.idle, parse_process(spec.plant),
                                  ts=spec.ts / PLANT_TICKS_PER_SAMPLE, noise_std=spec.noise, loads=spec.loads,
                                  speed=spec.speed)
        # The loops of one plant server share one connection; 16 requests in flight on it (the plant answers
        # pipelined requests: docs/modbus.md), as a PLC that takes them would be configured.
        conn.send(([plant.url(k, PIPELINE) for k in range(1, spec.loops + spec.idle + 1)], realtime))
        cpu0, wall0 = time.process_time(), time.monotonic()
        await asyncio.get_running_loop().run_in_executor(None, conn.recv)  # "stop"
        cpu = 100.0 * (time.process_time() - cpu0) / (time.monotonic() - wall0)
        await plant.close()
        conn.send(cpu)

    asyncio.run(main())


def _plant_priority() -> bool:
    """In the plant's process: real-time round-robin scheduling above the daemon's samplers; whether granted."""
    try:
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(PLANT_RT_PRIORITY))
    except (PermissionError, OSError):
        return False
    return True


def clients_main(port: int, token: str, loop_ids: list[str], count: int, conn: Any) -> None:
    """Child process: ``count`` event streams over ``loop_ids`` (round robin), the even ones read, the odd ones
    never; "ready" once all are open, then on "stop" (events read, CPU % of a core)."""

    async def stream(loop_id: str, read: bool, events: list[int]) -> tuple[asyncio.StreamReader,
                                                                             asyncio.StreamWriter]:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(f"GET /api/v1/loops/{loop_id}/events HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                     f"Authorization: Bearer {token}\r\nAccept: text/event-stream\r\n\r\n".encode())
        await writer.drain()
        if read:
            async def drain() -> None:
                while data := await reader.read(65536):
                    events[0] += data.count(b"\nevent: ") + data.startswith(b"event: ")

            asyncio.create_task(drain())
        return reader, writer

    async def main() -> None:
        events = [0]
        opened = []
        for i in range(count):
            opened.append(await stream(loop_ids[i % len(loop_ids)], i % 2 == 0, events))
        conn.send("ready")
        cpu0, wall0 = time.process_time(), time.monotonic()
        await asyncio.get_running_loop().run_in_executor(None, conn.recv)  # "stop"
        cpu = 100.0 * (time.process_time() - cpu0) / (time.monotonic() - wall0)
        for _, writer in opened:
            writer.close()
        conn.send((events[0], cpu))

    asyncio.run(main())


def _scada_main(url: str, password: str, loop_ids: list[str], period: float, conn: Any) -> None:
    """Child process: an OPC UA client subscribed to every variable of every loop; "ready", then on "stop" the
    number of data changes received."""
    from asyncua import Client, ua

    from api.opcua import ENV_USER
    from api.opcua.address_space import NAMESPACE, VARIABLES

    class Count:
        changes = 0

        def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
            Count.changes += 1

    async def main() -> None:
        client = Client(url, timeout=30)
        client.set_user(ENV_USER)
        client.set_password(password)
        async with client:
            idx = await client.get_namespace_index(NAMESPACE)
            sub = await client.create_subscription(period * 1000.0, Count())
            for loop_id in loop_ids:
                await sub.subscribe_data_change([client.get_node(ua.NodeId(f"{loop_id}.{v.name}", idx))
                                                 for v in VARIABLES])
            conn.send("ready")
            await asyncio.get_running_loop().run_in_executor(None, conn.recv)  # "stop"
        conn.send(Count.changes)

    asyncio.run(main())


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _peak_rss_mb(pid: int) -> float:
    """Peak resident memory of process ``pid`` (VmHWM), MB (0 where /proc is missing)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


@dataclass
class _Children:
    """The run's child processes and their pipes (plant, clients, SCADA)."""

    started: list[tuple[Any, Any, str]] = field(default_factory=list)

    def start(self, target: Any, args: tuple[Any, ...], what: str) -> Any:
        ours, theirs = multiprocessing.Pipe()
        child = multiprocessing.get_context("spawn").Process(target=target, args=(*args, theirs), daemon=True)
        child.start()
        self.started.append((child, ours, what))
        return ours, child

    def stop(self) -> None:
        for child, _, _ in self.started:
            child.join(10)
            if child.is_alive():
                child.kill()


def config_of(spec: LoadSpec, urls: list[str], viewer: str) -> DaemonConfig:
    """The daemon's config for ``spec``: the tuned loops L000…, the idle ones I000…, a viewer token."""
    from api.auth import token_hash

    health = {key: value for key, value in (("window", spec.health_window), ("every", spec.health_every))
              if value is not None}
    loops = [{"id": f"L{i:03d}" if i < spec.loops else f"I{i - spec.loops:03d}", "link": url, "ts": spec.ts,
              "speed": spec.speed, "apply": True, "monitor_period": spec.monitor_period, "health": health,
              "tuning": {"amp": spec.amp, "time_limit": spec.time_limit}} for i, url in enumerate(urls)]
    return DaemonConfig.model_validate({"history": ":memory:", "loops": loops, "samplers": spec.samplers,
                                        "tokens": [{"name": VIEWER_NAME, "role": "viewer",
                                                    "sha256": token_hash(viewer)}],
                                        "opcua": {"port": _free_port()} if spec.opcua else None})


async def run_load(spec: LoadSpec) -> LoadResult:
    """Run ``spec`` (module docstring): the daemon tunes its loops under the clients' watch; the figures."""
    import uvicorn

    from api.app import create_app

    parse_process(spec.plant)  # a bad expression fails here, not in the child
    os.environ[WORKERS_ENV] = str(spec.analysis_workers)  # read by the daemon's samplers
    loop = asyncio.get_running_loop()
    children = _Children()
    try:
        plant_conn, plant = children.start(_plant_main, (spec,), "plant")
        urls, plant_realtime = await loop.run_in_executor(None, _receive, plant_conn, plant, "plant")
        viewer = secrets.token_urlsafe(24)
        operator = secrets.token_urlsafe(24)
        port = _free_port()
        app = create_app(config_of(spec, urls, viewer), env_token=operator)
        server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
        serving = asyncio.create_task(server.serve())
        while not server.started:
            if serving.done():
                await serving
                raise RuntimeError("the daemon did not start")
            await asyncio.sleep(0.05)
        try:
            result = await _measured(spec, app, port, viewer, operator, children)
        finally:
            server.should_exit = True
            await serving
        plant_conn.send("stop")
        cpu_plant = await loop.run_in_executor(None, _receive, plant_conn, plant, "plant")
    finally:
        children.stop()
    return LoadResult(**{**result, "cpu_plant": cpu_plant, "plant_realtime": plant_realtime})


async def _measured(spec: LoadSpec, app: Any, port: int, viewer: str, operator: str,
                    children: _Children) -> dict[str, Any]:
    """The run itself once the daemon serves: clients, every TUNE at once, the wait, the figures."""
    loop = asyncio.get_running_loop()
    manager = app.state.manager
    tuned = [loop_id for loop_id in manager.loops if loop_id.startswith("L")]
    clients = scada = None
    if spec.clients:
        clients = children.start(clients_main, (port, viewer, tuned, spec.clients), "clients")
        await loop.run_in_executor(None, _receive, *clients, "clients")
    if spec.opcua:
        scada = children.start(_scada_main, (app.state.opcua_url, operator, list(manager.loops),
                                             spec.monitor_period), "OPC UA client")
        await loop.run_in_executor(None, _receive, *scada, "OPC UA client")
    pids = getattr(manager.field, "pids", [])
    health0 = (manager.health_assessed, manager.health_cpu)
    cpu0 = time.process_time() + design_cpu() + manager.health_cpu + sum(tree_cpu_seconds(pid) or 0.0 for pid in pids)
    wall0 = time.monotonic()
    opcua = getattr(app.state, "opcua", None)
    opcua0 = None if opcua is None else opcua.cpu_time()
    answers = await asyncio.gather(*(manager.request_tune(loop_id, TuneRequest(), "loadbench") for loop_id in tuned),
                                   return_exceptions=True)
    await asyncio.gather(*(manager.wait(loop_id) for loop_id in tuned))
    wall = time.monotonic() - wall0
    cpu = 100.0 * (time.process_time() + design_cpu() + manager.health_cpu
                   + sum(tree_cpu_seconds(pid) or 0.0 for pid in pids) - cpu0) / wall
    assessed, health_cpu = manager.health_assessed - health0[0], manager.health_cpu - health0[1]
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0 + sum(_peak_rss_mb(p) for pid in pids for p in (pid, *descendants(pid)))
    out: dict[str, Any] = {}
    if opcua is not None and opcua0 is not None:
        out["cpu_opcua"] = 100.0 * ((opcua.cpu_time() or 0.0) - opcua0) / wall
    if clients is not None:
        clients[0].send("stop")
        out["events"], out["cpu_clients"] = await loop.run_in_executor(None, _receive, *clients, "clients")
    if scada is not None:
        scada[0].send("stop")
        out["opcua_changes"] = await loop.run_in_executor(None, _receive, *scada, "OPC UA client")
    codes: Counter[str] = Counter()
    failures: dict[str, str] = {}
    for loop_id, answer in zip(tuned, answers):
        record = manager.loops[loop_id].result
        if isinstance(answer, BaseException):
            codes[f"refused {getattr(answer, 'code', type(answer).__name__)}"] += 1
            failures[loop_id] = str(answer)
        elif record is None or record.te:
            codes[str(None if record is None else record.ite)] += 1
            failures[loop_id] = "no result" if record is None else record.message
    s = manager.sampling
    return {**out, "spec": spec, "tuned": len(tuned) - len(failures), "codes": dict(codes), "failures": failures,
            "wall": wall, "samples": s.late.count, "late_p50": 1e3 * s.late.quantile(0.5),
            "late_p99": 1e3 * s.late.quantile(0.99), "late_max": 1e3 * s.late.largest,
            "analysis_p50": 1e3 * s.analysis.quantile(0.5), "analysis_p99": 1e3 * s.analysis.quantile(0.99),
            "analysis_max": 1e3 * s.analysis.largest, "cpu_daemon": cpu, "rss_daemon": rss, "assessed": assessed,
            "health_cpu": health_cpu}


HEADERS = ["loops", "idle", "clients", "tuned", "codes of the rest", "wall s", "samples", "p50 ms", "p99 ms",
           "max ms", "analysis p50/p99/max ms", "CPU daemon %", "RSS MB", "CPU plant %", "health assessed",
           "health CPU ms each"]
CLIENT_HEADERS = ["events read", "CPU clients %"]
OPCUA_HEADERS = ["OPC UA changes", "CPU OPC UA %"]


def headers(results: list[LoadResult]) -> list[str]:
    """The table's column names (the clients' and OPC UA's columns when measured)."""
    return (HEADERS + (CLIENT_HEADERS if any(r.events is not None for r in results) else [])
            + (OPCUA_HEADERS if any(r.opcua_changes is not None for r in results) else []))


def table_rows(results: list[LoadResult]) -> list[list[str]]:
    """Rows of the table (markdown and the command's)."""
    clients = any(r.events is not None for r in results)
    opcua = any(r.opcua_changes is not None for r in results)
    rows = []
    for r in results:
        codes = ", ".join(f"{code}: {n}" for code, n in sorted(r.codes.items())) or "-"
        row = [str(r.spec.loops), str(r.spec.idle), str(r.spec.clients), f"{r.tuned}/{r.spec.loops}", codes,
               f"{r.wall:.1f}", str(r.samples), f"{r.late_p50:.2f}", f"{r.late_p99:.2f}", f"{r.late_max:.2f}",
               f"{r.analysis_p50:.2f} / {r.analysis_p99:.2f} / {r.analysis_max:.2f}", f"{r.cpu_daemon:.0f}",
               f"{r.rss_daemon:.0f}", f"{r.cpu_plant:.0f}", str(r.assessed),
               f"{1e3 * r.health_cpu / r.assessed:.2f}" if r.assessed else "-"]
        if clients:
            row += ["-" if r.events is None else str(r.events),
                    "-" if r.cpu_clients is None else f"{r.cpu_clients:.0f}"]
        if opcua:
            row += ["-" if r.opcua_changes is None else str(r.opcua_changes),
                    "-" if r.cpu_opcua is None else f"{r.cpu_opcua:.1f}"]
        rows.append(row)
    return rows


def markdown(results: list[LoadResult]) -> str:
    """The results as a markdown table."""
    names = headers(results)
    lines = ["| " + " | ".join(names) + " |", "|" + "---:|" * len(names)]
    lines += ["| " + " | ".join(row) + " |" for row in table_rows(results)]
    return "\n".join(lines)

