"""What a simulated plant of many loops costs: the CPU of its process, idle and read by a client.

The plant (:func:`drivers.modbus_plant.serve_plant`, what ``autotuner sim --loops N`` runs) is started
in a child process of its own; after a warm-up its CPU time (user + system, ``time.process_time``) is
taken over a window of wall time, in percent of one core. With ``read_period`` a client in this process
reads every loop's PV and MV (input registers 0–3, one request per loop) once per period, the loops one
after the other on one connection per server, as a monitor would. The loops stay idle in AUTO.

Run: ``python -m autotuner.benchmarks.plant_cpu [--ts 0.1] [--seconds 30] [--loops 1 100 247 500]``.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing
import time
from dataclasses import dataclass
from typing import Any

DEFAULT_PLANT = "exp(-0.5*s)/(s+1)"
WARM_UP = 3.0  # wall seconds between the plant serving and the window (imports done, first ticks made)


@dataclass(frozen=True)
class PlantCpu:
    """One measurement: N loops at plant sample time ``ts``; CPU of the plant's process, % of a core; reads/s."""

    loops: int
    ts: float
    read_period: float | None
    cpu: float
    reads_per_s: float


def _plant_main(n: int, plant: str, ts: float, speed: float, conn: Any) -> None:
    """Child process: the plant; sends the servers' ports, then its CPU (% of a core) between "start" and "stop"."""
    from drivers.modbus_plant import serve_plant

    from autotuner.engine.plant.expression import parse_process

    async def main() -> None:
        async with await serve_plant(n, parse_process(plant), ts=ts, speed=speed) as served:
            conn.send([(*served.address(k), k) for k in range(1, n + 1)])
            loop = asyncio.get_running_loop()
            await loop.run_in_executor(None, conn.recv)  # "start"
            cpu0, wall0 = time.process_time(), time.monotonic()
            await loop.run_in_executor(None, conn.recv)  # "stop"
            conn.send(100.0 * (time.process_time() - cpu0) / (time.monotonic() - wall0))

    asyncio.run(main())


async def _read_every_loop(addresses: list[tuple[int, int, int]], period: float, stop: asyncio.Event) -> float:
    """Read PV and MV of every (port, unit, loop) once per ``period`` wall seconds until ``stop``; reads per second."""
    from pymodbus.client import AsyncModbusTcpClient

    clients = {port: AsyncModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0)
               for port in {port for port, _, _ in addresses}}
    reads = 0
    try:
        for client in clients.values():
            await client.connect()
        due = start = time.monotonic()
        while not stop.is_set():
            for port, unit, k in addresses:
                answer = await clients[port].read_input_registers(0, count=4, device_id=unit)
                if answer.isError():
                    raise RuntimeError(f"loop {k} (port {port}, unit {unit}) answered {answer}")
                reads += 1
            due += period
            try:
                await asyncio.wait_for(stop.wait(), max(due - time.monotonic(), 0.0))
            except asyncio.TimeoutError:
                pass
    finally:
        for client in clients.values():
            client.close()
    return reads / (time.monotonic() - start)


async def measure(n: int, ts: float, read_period: float | None = None, seconds: float = 30.0, speed: float = 1.0,
                  plant: str = DEFAULT_PLANT) -> PlantCpu:
    """The CPU of a plant of ``n`` loops of ``plant`` (sample time ``ts`` plant seconds, ``speed`` × real time)
    over ``seconds`` wall seconds, read once per ``read_period`` wall seconds (None: not read)."""
    ours, theirs = multiprocessing.Pipe()
    child = multiprocessing.get_context("spawn").Process(target=_plant_main, args=(n, plant, ts, speed, theirs),
                                                         daemon=True)
    child.start()
    loop = asyncio.get_running_loop()
    try:
        addresses = await loop.run_in_executor(None, ours.recv)
        stop = asyncio.Event()
        reader = None if read_period is None else asyncio.create_task(_read_every_loop(addresses, read_period, stop))
        await asyncio.sleep(WARM_UP)
        ours.send("start")
        await asyncio.sleep(seconds)
        stop.set()
        reads = 0.0 if reader is None else await reader
        ours.send("stop")
        cpu = await loop.run_in_executor(None, ours.recv)
    finally:
        child.join(30)
        if child.is_alive():
            child.kill()
    return PlantCpu(n, ts, read_period, cpu, reads)


def markdown(rows: list[PlantCpu]) -> str:
    """The measurements as a markdown table."""
    lines = ["| loops | plant ts, s | client | plant CPU, % of a core | reads/s |", "|---:|---:|---|---:|---:|"]
    for r in rows:
        client = "none (idle)" if r.read_period is None else f"every loop every {r.read_period:g} s"
        lines.append(f"| {r.loops} | {r.ts:g} | {client} | {r.cpu:.1f} | {r.reads_per_s:.0f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--loops", type=int, nargs="+", default=[1, 100, 247, 500])
    parser.add_argument("--ts", type=float, nargs="+", default=[0.1], help="plant sample times, s")
    parser.add_argument("--seconds", type=float, default=30.0, help="length of each window, wall seconds")
    parser.add_argument("--plant", default=DEFAULT_PLANT)
    args = parser.parse_args()
    rows = []
    for ts in args.ts:
        for n in args.loops:
            for period in (None, 1.0):
                rows.append(asyncio.run(measure(n, ts, period, args.seconds, plant=args.plant)))
                print(markdown(rows[-1:]).splitlines()[-1], flush=True)
    print(markdown(rows))


if __name__ == "__main__":
    main()
