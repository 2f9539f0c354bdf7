"""Load benchmark of the daemon: N simulated loops tuned at once over Modbus TCP on localhost.

The plants are N :class:`~drivers.simplc.SimulatedPlc`, each behind its own
Modbus TCP server (:func:`drivers.modbus_server.serve_modbus`, an ephemeral
port), all in a child process — the field devices, kept off the daemon's
event loop and its CPU account. The daemon side is a
:class:`~autotuner.service.daemon.LoopManager` with N loops whose links are
``modbus://127.0.0.1:PORT/1``; the benchmark starts all N tunings at once and
waits for them to end.

Measured from outside the session: each loop's link is wrapped so every
``read_pv`` is time-stamped (``time.monotonic()``). A session samples on a
deadline schedule (:func:`autotuner.service.link_session.deadlines`: sample k is due at
``start + k·ts/speed``, one PV read per sample, the first one due at once), so
the k-th read of a session is due at its first read + k·ts/speed. Lateness is
when the read *completed* behind that due time (the Modbus round trip
included) — what the experiment sees as jitter. CPU is the daemon's CPU
time (user + system: its process and the worker processes of the design) over
the wall time, in percent of one core; the plant process's is reported beside it.

With ``opcua`` the daemon also runs its OPC UA server (:mod:`api.opcua`, a
process of its own fed by the daemon) and a client in another child process
— a SCADA — subscribes to every variable of every loop at the monitor's rate
for the whole run; the number of data changes it received is reported
(``opcua_changes``), and the CPU of the server's process (``cpu_opcua``, % of
a core), which the daemon's CPU does not include.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import secrets
import socket
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.simplc import SimulatedPlc, run

from autotuner.service.config import DaemonConfig, TuneRequest
from autotuner.service.daemon import Loop, LoopManager
from autotuner.engine.plant.expression import parse_process
from autotuner.service.history import History
from autotuner.service.remote_tuning import PLANT_TICKS_PER_SAMPLE
from autotuner.service.link_session import design_cpu

# A fast plant: one tuning is about a minute of plant time (ts 0.1 s: about 60 samples per period).
DEFAULT_PLANT = "exp(-0.5*s)/(s+1)"
DEFAULT_TS = 0.1
DEFAULT_SPEED = 1.0


@dataclass(frozen=True)
class LoadResult:
    """One run: N loops, how many tunings succeeded, wall time, sampling lateness (ms) and CPU (% of a core)."""

    loops: int
    succeeded: int
    wall: float
    samples: int
    late_p50: float
    late_p99: float
    late_max: float
    cpu_daemon: float
    cpu_plants: float
    failures: dict[str, str]
    opcua_changes: int | None = None
    cpu_opcua: float | None = None


class TimedLink:
    """A link whose ``read_pv`` calls are time-stamped (start and completion); everything else forwarded.

    The daemon also monitors idle loops through links of its own (reads, no
    MV): only a link that writes an MV is a session's.
    """

    def __init__(self, link: Any) -> None:
        self._link = link
        self.starts: list[float] = []
        self.done: list[float] = []
        self.session = False

    async def read_pv(self) -> float:
        start = time.monotonic()
        pv = await self._link.read_pv()
        self.starts.append(start)
        self.done.append(time.monotonic())
        return pv

    async def write_mv(self, mv: float) -> None:
        self.session = True
        await self._link.write_mv(mv)

    @property
    def pv_age(self) -> float | None:
        return self._link.pv_age

    def __getattr__(self, name: str) -> Any:
        return getattr(self._link, name)


def stamp_reads(loop: Loop, links: list[TimedLink]) -> None:
    """Make every link ``loop`` opens from now on a :class:`TimedLink`, appended to ``links``."""
    connect = loop.connect

    def timed() -> TimedLink:
        links.append(TimedLink(connect()))
        return links[-1]

    loop.connect = timed


def lateness(starts: list[float], done: list[float], period: float) -> np.ndarray:
    """Seconds each read completed after its due time: read k is due when the first read began + k·period."""
    if not done:
        return np.zeros(0)
    t = np.asarray(done)
    return t - (starts[0] + period * np.arange(len(t)))


def _receive(conn: Any, child: Any, what: str = "plant") -> Any:
    """The ``what`` process's next message; RuntimeError if it dies first (it never answers then)."""
    while not conn.poll(0.2):
        if not child.is_alive():
            raise RuntimeError(f"the {what} process ended (exit code {child.exitcode}) before it answered")
    return conn.recv()


def _plants_main(n: int, plant: str, ts: float, speed: float, conn: Any) -> None:
    """Child process: N simulated PLCs behind N Modbus servers; sends the ports, runs until told, sends CPU."""
    from drivers.modbus_server import serve_modbus

    async def main() -> None:
        halt = asyncio.Event()
        plcs = [SimulatedPlc(parse_process(plant), ts=ts / PLANT_TICKS_PER_SAMPLE) for _ in range(n)]
        tasks = [asyncio.create_task(run(plc, speed, halt)) for plc in plcs]
        servers = [await serve_modbus(plc, "127.0.0.1", 0) for plc in plcs]
        conn.send([s.port for s in servers])
        cpu0, wall0 = time.process_time(), time.monotonic()
        await asyncio.get_running_loop().run_in_executor(None, conn.recv)  # "stop"
        cpu = 100.0 * (time.process_time() - cpu0) / (time.monotonic() - wall0)
        for server in servers:
            await server.close()
        halt.set()
        await asyncio.gather(*tasks)
        conn.send(cpu)

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


async def run_load(n: int, speed: float = DEFAULT_SPEED, ts: float = DEFAULT_TS, plant: str = DEFAULT_PLANT,
                   amp: float = 5.0, time_limit: float = 600.0, opcua: bool = False,
                   monitor_period: float = 1.0) -> LoadResult:
    """Tune ``n`` simulated loops at once over Modbus TCP; the result with the sampling lateness and CPU.

    ``opcua``: also publish them over OPC UA to a subscribed client (module
    docstring); ``monitor_period``: the loops' monitor period, wall seconds
    (also the OPC UA publishing rate).
    """
    parse_process(plant)  # a bad expression fails here, not in the child
    ours, theirs = multiprocessing.Pipe()
    child = multiprocessing.get_context("spawn").Process(target=_plants_main, args=(n, plant, ts, speed, theirs),
                                                         daemon=True)
    child.start()
    loop = asyncio.get_running_loop()
    try:
        ports = await loop.run_in_executor(None, _receive, ours, child)
        config = DaemonConfig.model_validate({"history": ":memory:", "loops": [
            {"id": f"L{i:03d}", "link": f"modbus://127.0.0.1:{port}/1", "ts": ts, "speed": speed, "apply": True,
             "monitor_period": monitor_period, "tuning": {"amp": amp, "time_limit": time_limit}}
            for i, port in enumerate(ports)], "opcua": {"port": _free_port()} if opcua else None})
        history = History(config.history)
        manager = LoopManager(config, history)
        links: list[TimedLink] = []
        for item in manager.loops.values():
            stamp_reads(item, links)
        await manager.start()
        server = scada = None
        try:
            if opcua:
                from api.opcua import start_opcua

                password = secrets.token_urlsafe(16)
                server = await start_opcua(manager, config, password, "127.0.0.1")
                scada_conn, scada_end = multiprocessing.Pipe()
                scada = multiprocessing.get_context("spawn").Process(
                    target=_scada_main, args=(server.url, password, list(manager.loops), monitor_period, scada_end),
                    daemon=True)
                scada.start()
                await loop.run_in_executor(None, _receive, scada_conn, scada, "OPC UA client")  # subscribed
            cpu0, wall0 = time.process_time() + design_cpu(), time.monotonic()
            opcua0 = None if server is None else server.cpu_time()
            for loop_id in manager.loops:
                manager.tune(loop_id, TuneRequest(), "loadbench")
            await asyncio.gather(*(manager.wait(loop_id) for loop_id in manager.loops))
            wall = time.monotonic() - wall0
            cpu = 100.0 * (time.process_time() + design_cpu() - cpu0) / wall
            opcua1 = None if server is None else server.cpu_time()
            cpu_opcua = None if opcua0 is None or opcua1 is None else 100.0 * (opcua1 - opcua0) / wall
            if scada is not None:
                scada_conn.send("stop")
                changes = await loop.run_in_executor(None, _receive, scada_conn, scada, "OPC UA client")
        finally:
            if scada is not None:
                scada.join(10)
                if scada.is_alive():
                    scada.kill()
            if server is not None:
                await server.stop()
            await manager.stop()
            history.close()
        ours.send("stop")
        cpu_plants = await loop.run_in_executor(None, _receive, ours, child)
    finally:
        child.join(10)
        if child.is_alive():
            child.kill()
    failures = {loop_id: "no result" if item.result is None else item.result.message
                for loop_id, item in manager.loops.items() if item.result is None or item.result.ite != 0}
    late = 1e3 * np.concatenate([lateness(link.starts, link.done, ts / speed) for link in links if link.session]
                                + [np.zeros(0)])
    p50, p99 = np.percentile(late, [50, 99]) if late.size else (float("nan"),) * 2
    return LoadResult(n, n - len(failures), wall, int(late.size), float(p50), float(p99),
                      float(late.max()) if late.size else float("nan"), cpu, cpu_plants, failures,
                      changes if opcua else None, cpu_opcua if opcua else None)


def table_rows(results: list[LoadResult]) -> list[list[str]]:
    """Rows of the markdown table of the docs (and of the command's table); the OPC UA column when measured."""
    opcua = any(r.opcua_changes is not None for r in results)
    return [[str(r.loops), f"{r.succeeded}/{r.loops}", f"{r.wall:.1f}", str(r.samples), f"{r.late_p50:.2f}",
             f"{r.late_p99:.2f}", f"{r.late_max:.1f}", f"{r.cpu_daemon:.0f}", f"{r.cpu_plants:.0f}"]
            + ([str(r.opcua_changes if r.opcua_changes is not None else "-"),
                "-" if r.cpu_opcua is None else f"{r.cpu_opcua:.1f}"] if opcua else [])
            for r in results]


HEADERS = ["loops", "ok", "wall s", "samples", "p50 ms", "p99 ms", "max ms", "CPU daemon %", "CPU plants %"]
OPCUA_HEADERS = ["OPC UA changes", "CPU OPC UA %"]


def headers(results: list[LoadResult]) -> list[str]:
    """The table's column names (with :data:`OPCUA_HEADERS` when OPC UA was measured)."""
    return HEADERS + (OPCUA_HEADERS if any(r.opcua_changes is not None for r in results) else [])


def markdown(results: list[LoadResult]) -> str:
    """The results as a markdown table."""
    names = headers(results)
    lines = ["| " + " | ".join(names) + " |", "|" + "---:|" * len(names)]
    lines += ["| " + " | ".join(row) + " |" for row in table_rows(results)]
    return "\n".join(lines)
