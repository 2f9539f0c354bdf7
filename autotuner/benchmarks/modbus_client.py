"""What a Modbus request costs the client: CPU of the process that runs the links, per request.

The plant (:func:`drivers.modbus_plant.serve_plant`, what ``autotuner sim --loops N`` runs) is a child process
of its own, so its CPU is not counted. This process opens one :class:`~drivers.modbus_link.ModbusLink` per loop
(``modbus://127.0.0.1:PORT/UNIT``, plus ``?pipeline=P`` when ``pipeline`` is given) and makes ``requests``
``read_pv`` calls in two ways:

* **sequential** — one call at a time, the links in turn (a request's whole path, nothing overlapping);
* **concurrent** — every link calls at once, each link one call after the other (as many loops sampled
  together): the requests overlap and a shared connection pipelines them.

Figures per way: the client's CPU time (user + system, ``time.process_time``) per request in µs, and requests
per wall second. The loops idle in AUTO.

With ``--paced T:M``, the load the daemon's sampler is sized for instead: T links sampled every ``--ts`` wall
seconds (a PV read, then an MV write, on a deadline schedule, all in phase: sessions started together) and M
monitored every second (``read_sample``, the gains with ``read_state`` every 10th), for ``--seconds``; figures:
the lateness of each PV read's completion behind its due time (p50, p99, max, ms) and the client process's CPU
(% of one core, its own scheduling of the T + M tasks included).

Run: ``python -m autotuner.benchmarks.modbus_client [--loops 100] [--requests 20000] [--pipeline 1 16]`` or
``python -m autotuner.benchmarks.modbus_client --paced 100:400 [--ts 0.1] [--seconds 60] [--pipeline 1 16]``.
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing
import os
import time
from dataclasses import dataclass
from typing import Any

DEFAULT_PLANT = "exp(-0.5*s)/(s+1)"


@dataclass(frozen=True)
class ClientCpu:
    """One measurement: ``loops`` links, ``way`` sequential or concurrent, ``pipeline`` (None: not in the URL);
    the client's CPU per request (µs) and requests per wall second."""

    loops: int
    way: str
    pipeline: int | None
    us_per_request: float
    per_second: float


def _plant_main(n: int, plant: str, conn: Any) -> None:
    """Child process: the plant; sends the loops' URLs, then serves until told to stop."""
    from drivers.modbus_plant import serve_plant

    from autotuner.engine.plant.expression import parse_process

    async def main() -> None:
        async with await serve_plant(n, parse_process(plant), ts=0.1) as served:
            conn.send([served.url(k) for k in range(1, n + 1)])
            await asyncio.get_running_loop().run_in_executor(None, conn.recv)  # "stop"

    asyncio.run(main())


async def _sequential(links: list[Any], requests: int) -> None:
    for i in range(requests):
        await links[i % len(links)].read_pv()


async def _concurrent(links: list[Any], requests: int) -> None:
    async def calls(link: Any, n: int) -> None:
        for _ in range(n):
            await link.read_pv()

    share, extra = divmod(requests, len(links))
    await asyncio.gather(*(calls(link, share + (k < extra)) for k, link in enumerate(links)))


async def _measure(urls: list[str], requests: int, pipeline: int | None) -> list[ClientCpu]:
    from drivers.modbus_link import ModbusLink

    suffix = "" if pipeline is None else f"?pipeline={pipeline}"
    links = [ModbusLink.from_url(url + suffix) for url in urls]
    rows = []
    try:
        for link in links:
            await link.open()
        await _concurrent(links, len(links))  # warm-up: every link connected, first answers in
        for way, run in (("sequential", _sequential), ("concurrent", _concurrent)):
            cpu0, wall0 = time.process_time(), time.monotonic()
            await run(links, requests)
            cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
            rows.append(ClientCpu(len(urls), way, pipeline, 1e6 * cpu / requests, requests / wall))
    finally:
        for link in links:
            await link.close()
    return rows


def measure(n: int, requests: int, pipeline: int | None = None, plant: str = DEFAULT_PLANT) -> list[ClientCpu]:
    """The client's CPU per ``read_pv`` of ``n`` links (one per loop of a plant of ``n`` loops of ``plant`` in a
    child process), ``requests`` calls made sequentially, then as many concurrently (module docstring);
    ``pipeline``: the URLs' ``?pipeline=`` (None: not given)."""
    ours, theirs = multiprocessing.Pipe()
    child = multiprocessing.get_context("spawn").Process(target=_plant_main, args=(n, plant, theirs), daemon=True)
    child.start()
    try:
        urls = ours.recv()
        return asyncio.run(_measure(urls, requests, pipeline))
    finally:
        ours.send("stop")
        child.join(30)
        if child.is_alive():
            child.kill()


@dataclass(frozen=True)
class Paced:
    """A paced run: ``tuned`` links sampled every ``ts`` s, ``idle`` monitored every second, ``pipeline``; the PV
    reads' lateness p50/p99/max (ms) over ``samples`` reads, the client's CPU (% of a core)."""

    tuned: int
    idle: int
    ts: float
    pipeline: int | None
    samples: int
    p50: float
    p99: float
    worst: float
    cpu: float


async def _sampled(link: Any, ts: float, until: float, late: list[float]) -> None:
    start = time.monotonic()
    k = 0
    while (due := start + k * ts) < until:
        await asyncio.sleep(max(due - time.monotonic(), 0.0))
        await link.read_pv()
        late.append(time.monotonic() - due)
        await link.write_mv(50.0)  # the loops are in AUTO: the manual MV is not applied
        k += 1


async def _monitored(link: Any, until: float) -> None:
    start = time.monotonic()
    k = 0
    while (due := start + k) < until:
        await asyncio.sleep(max(due - time.monotonic(), 0.0))
        await link.read_sample()
        if k % 10 == 0:
            await link.read_state()
        k += 1


async def _measure_paced(urls: list[str], tuned: int, ts: float, seconds: float, pipeline: int | None) -> Paced:
    from drivers.modbus_link import ModbusLink

    suffix = "" if pipeline is None else f"?pipeline={pipeline}"
    links = [ModbusLink.from_url(url + suffix) for url in urls]
    late: list[float] = []
    try:
        for link in links:
            await link.open()
        cpu0, wall0 = time.process_time(), time.monotonic()
        until = wall0 + seconds
        await asyncio.gather(*(_sampled(link, ts, until, late) for link in links[:tuned]),
                             *(_monitored(link, until) for link in links[tuned:]))
        cpu = 100.0 * (time.process_time() - cpu0) / (time.monotonic() - wall0)
    finally:
        for link in links:
            await link.close()
    late.sort()
    return Paced(tuned, len(urls) - tuned, ts, pipeline, len(late), 1e3 * late[len(late) // 2],
                 1e3 * late[int(0.99 * (len(late) - 1))], 1e3 * late[-1], cpu)


def measure_paced(tuned: int, idle: int, ts: float, seconds: float, pipeline: int | None = None,
                  plant: str = DEFAULT_PLANT) -> Paced:
    """``tuned`` links sampled every ``ts`` wall seconds and ``idle`` monitored every second for ``seconds``
    against a plant of ``tuned + idle`` loops of ``plant`` in a child process (module docstring)."""
    ours, theirs = multiprocessing.Pipe()
    child = multiprocessing.get_context("spawn").Process(target=_plant_main, args=(tuned + idle, plant, theirs),
                                                         daemon=True)
    child.start()
    try:
        return asyncio.run(_measure_paced(ours.recv(), tuned, ts, seconds, pipeline))
    finally:
        ours.send("stop")
        child.join(30)
        if child.is_alive():
            child.kill()


def paced_markdown(rows: list[Paced]) -> str:
    """Paced runs as a markdown table."""
    lines = ["| tuned | ts, s | monitored | pipeline | PV reads | late p50 ms | p99 ms | max ms | client CPU % |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        pipeline = "–" if r.pipeline is None else str(r.pipeline)
        lines.append(f"| {r.tuned} | {r.ts:g} | {r.idle} | {pipeline} | {r.samples} | {r.p50:.2f} | {r.p99:.2f} | "
                     f"{r.worst:.1f} | {r.cpu:.0f} |")
    return "\n".join(lines)


def markdown(rows: list[ClientCpu]) -> str:
    """The measurements as a markdown table."""
    lines = ["| loops | calls | pipeline | client CPU, µs per request | requests/s |", "|---:|---|---:|---:|---:|"]
    for r in rows:
        pipeline = "–" if r.pipeline is None else str(r.pipeline)
        lines.append(f"| {r.loops} | {r.way} | {pipeline} | {r.us_per_request:.0f} | {r.per_second:.0f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--loops", type=int, nargs="+", default=[100])
    parser.add_argument("--requests", type=int, default=20000, help="read_pv calls per way")
    parser.add_argument("--pipeline", type=int, nargs="*", default=[], help="?pipeline= values (none: not given)")
    parser.add_argument("--plant", default=DEFAULT_PLANT)
    parser.add_argument("--paced", metavar="T:M", help="T links sampled every --ts, M monitored every second")
    parser.add_argument("--ts", type=float, default=0.1, help="sample time of the paced links, wall seconds")
    parser.add_argument("--seconds", type=float, default=60.0, help="length of a paced run, wall seconds")
    args = parser.parse_args()
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    if args.paced:
        try:
            tuned, idle = (int(x) for x in args.paced.split(":"))
        except ValueError:
            parser.error(f"--paced takes T:M (two whole numbers), got {args.paced!r}")
        paced = []
        for pipeline in args.pipeline or [None]:
            paced.append(measure_paced(tuned, idle, args.ts, args.seconds, pipeline, args.plant))
            print(paced_markdown(paced[-1:]).splitlines()[-1], flush=True)
        print(paced_markdown(paced))
        print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        return
    rows: list[ClientCpu] = []
    for n in args.loops:
        for pipeline in args.pipeline or [None]:
            rows += measure(n, args.requests, pipeline, args.plant)
            print("\n".join(markdown(rows[-2:]).splitlines()[2:]), flush=True)
    print(markdown(rows))
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
