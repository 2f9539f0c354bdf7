"""Benchmarks (tables, not tests): ``autotuner bench`` (the experiment and the design over a batch of
processes) and ``autotuner loadbench`` (many loops tuned at once over Modbus TCP)."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from autotuner.cli.app import EXIT_FAILED, app, bad_input, parse_loads, parse_plant, stderr, stdout


@app.command()
def bench(
    batch: Annotated[Path | None, typer.Option(help="Batch CSV (id, family, params, expr, ...). "
                                               "Default: the Åström–Hägglund batch shipped with the package.")] = None,
    workers: Annotated[int | None, typer.Option(min=1, help="Worker processes. Default: all cores.")] = None,
    output: Annotated[Path | None, typer.Option(help="Also write the table (markdown) to this file.")] = None,
    design_only: Annotated[bool, typer.Option("--design-only", help="Only the design rule, from the exact "
                                              "135° point and static gain (no experiment).")] = False,
    field: Annotated[bool, typer.Option("--field", help="Field conditions: every process under load steps, "
                                        "drift, noise, quantisation and a non-steady start "
                                        "(docs/field-benchmark.md).")] = False,
    health: Annotated[bool, typer.Option("--health", help="The loop-health monitor instead: simulated loops with "
                                         "and without faults, detection and false-alarm rates per flag "
                                         "(docs/health.md).")] = False,
    repeats: Annotated[int, typer.Option(min=1, max=100, help="With --health: loops per fault, severity and "
                                         "process (healthy ones 3× as many).")] = 5,
) -> None:
    """Benchmark the experiment and the design on every process of a batch against the usual relay tuners."""
    if field and design_only:
        bad_input("--field and --design-only exclude each other")
    if health:
        if field or design_only or batch is not None:
            bad_input("--health takes no batch, --field or --design-only")
        _health_bench(repeats, workers, output)
        return
    from autotuner.benchmarks.design_bench import cpu_summary, default_batch, format_table, load_batch, run_batch
    from autotuner.engine.plant.expression import parse_process

    start = time.perf_counter()
    try:
        rows = load_batch(batch or default_batch())
        for row in rows:  # here, not in a worker: a bad expression gets a clear message
            parse_process(row["expr"])
    except KeyError as exc:
        bad_input(f"bad batch {batch}: missing column {exc}")
    except (OSError, ValueError) as exc:  # unreadable file, bad expression
        bad_input(f"bad batch {batch}: {exc}")
    if field:
        from autotuner.benchmarks import field_bench

        results = field_bench.run_field(rows, workers)
        table, line = field_bench.summary(results)
        cpu = f"experiment CPU (process time per call):\n\n{field_bench.cpu_summary(results)}"
        unstable = field_bench.unstable_table(field_bench.run_unstable(workers)) if batch is None else ""
        print(f"{table}\n\n{line}\n\n{cpu}" + (f"\n\nunstable processes:\n\n{unstable}" if unstable else ""))
        if output is not None:
            output.write_text(f"{table}\n\n{line}\n\n{cpu}\n\n"
                              + (f"## Unstable processes\n\n{unstable}\n\n" if unstable else "")
                              + f"## Per scenario\n\n{field_bench.per_scenario_tables(results)}")
        stderr.print(f"{len(rows)} processes in {time.perf_counter() - start:.1f} s wall time", highlight=False)
        return
    results = run_batch(rows, workers, design_only)
    table = format_table(results)
    if not design_only:
        table += f"\n\nexperiment CPU (process time per call, PI runs):\n\n{cpu_summary(results)}"
    print(table)
    if output is not None:
        output.write_text(table + "\n")
    stderr.print(f"{len(rows)} processes in {time.perf_counter() - start:.1f} s wall time", highlight=False)


def _health_bench(repeats: int, workers: int | None, output: Path | None) -> None:
    from autotuner.benchmarks.health_bench import run, table

    start = time.perf_counter()
    outcomes = run(repeats, workers)
    text = table(outcomes)
    print(text)
    if output is not None:
        output.write_text(text + "\n")
    stderr.print(f"{len(outcomes)} loops in {time.perf_counter() - start:.1f} s wall time", highlight=False)


@app.command("loadbench")
def loadbench_command(
    loops: Annotated[list[int] | None, typer.Option("--loops", min=1, max=1000, help="Loops tuned at once; "
                                                    "repeat for several runs. Default: 1, 10, 25, 50.")] = None,
    idle: Annotated[int, typer.Option(min=0, max=5000, help="Loops monitored besides, not tuned.")] = 0,
    clients: Annotated[int, typer.Option(min=0, max=5000, help="Viewer event streams held open over the tuned "
                                         "loops for the whole run, half of them never read.")] = 0,
    noise: Annotated[float, typer.Option(min=0.0, help="Measurement noise of every loop, σ in PV units.")] = 0.0,
    load: Annotated[list[str] | None, typer.Option("--load", help="Load step T:SIZE at the process input of every "
                                                   "loop (plant seconds after the tuner takes the loop : MV "
                                                   "units); repeat for several.")] = None,
    samplers: Annotated[int, typer.Option(min=0, max=64, help="The daemon's sampler processes (0: sampling in the "
                                          "API's process).")] = 1,
    analysis_workers: Annotated[int, typer.Option(min=0, max=64, help="Analysis worker processes per sampler "
                                                  "(AUTOTUNER_ANALYSIS_WORKERS; 0: threads, awaited).")] = 2,
    speed: Annotated[float, typer.Option(min=0.1, max=100.0, help="Plant seconds per wall second.")] = 1.0,
    ts: Annotated[float, typer.Option(min=0.001, help="Sample time, plant seconds.")] = 0.1,
    plant: Annotated[str, typer.Option(help="Process transfer function in s.")] = "exp(-0.5*s)/(s+1)",
    as_markdown: Annotated[bool, typer.Option("--markdown", help="Print a markdown table.")] = False,
    opcua: Annotated[bool, typer.Option("--opcua", help="Also publish the loops over OPC UA to a client subscribed "
                                        "to all their variables (docs/opcua.md). Needs the opcua extra.")] = False,
    monitor_period: Annotated[float, typer.Option(min=0.05, max=60.0, help="The loops' monitor period (and OPC UA "
                                                  "publishing interval), wall seconds.")] = 1.0,
    health_window: Annotated[float | None, typer.Option(min=60.0, max=86400.0, help="The loops' health window, "
                                                        "plant seconds (default: the config's, 3600).")] = None,
    health_every: Annotated[float | None, typer.Option(min=1.0, max=3600.0, help="How often each loop's health is "
                                                       "assessed, plant seconds (default: the config's, 60).")] = None,
) -> None:
    """Benchmark: N simulated loops tuned at once (and M monitored) over Modbus TCP on localhost, with clients
    watching; sampling lateness, analysis CPU, the daemon's CPU and memory.

    Not a test: it takes about a minute per run at the defaults (docs/daemon.md, "Load benchmark").
    """
    from autotuner.benchmarks.load import LoadSpec, headers, markdown, run_load, table_rows

    parse_plant(plant)
    steps = tuple(parse_loads(load, "when the tuner takes the loop over"))
    if opcua:
        from api.opcua import require

        try:
            require()
        except RuntimeError as exc:
            bad_input(str(exc))
    results = []
    for n in loops or [1, 10, 25, 50]:
        spec = LoadSpec(n, idle, clients, opcua, noise, steps, plant, ts, speed, samplers=samplers,
                        analysis_workers=analysis_workers, monitor_period=monitor_period,
                        health_window=health_window, health_every=health_every)
        result = asyncio.run(run_load(spec))
        results.append(result)
        for loop_id, message in result.failures.items():
            stderr.print(f"{n} loops: {loop_id} failed: {message}", highlight=False, markup=False)
    title = (f"tunings at once over Modbus TCP (localhost): ts {ts:g} s, {speed:g}× real time, one sample every "
             f"{1e3 * ts / speed:g} ms per loop; noise {noise:g}, loads {list(steps) or 'none'}; lateness of the PV "
             "read behind its due time; the plant at "
             + ("real-time priority (it stands for devices with CPUs of their own)"
                if all(r.plant_realtime for r in results) else "ordinary priority (real time not granted: its own "
                                                              "lateness counts in the figures)"))
    if as_markdown:
        print(f"{title}\n\n{markdown(results)}")
    else:
        table = Table(title=title, title_justify="left")
        for name in headers(results):
            table.add_column(name, justify="right")
        for row in table_rows(results):
            table.add_row(*row)
        stdout.print(table)
    if any(r.tuned < r.spec.loops for r in results):
        raise typer.Exit(EXIT_FAILED)


@app.command("failover")
def failover_command(
    daemons: Annotated[int, typer.Option(min=2, max=16, help="Daemons in the fleet.")] = 3,
    loops: Annotated[int, typer.Option(min=2, max=2000, help="Loops they share.")] = 300,
    tuning: Annotated[int, typer.Option(min=0, max=500, help="Loops of the killed daemon tuning when it dies.")] = 20,
    lease: Annotated[float, typer.Option(min=2.0, max=600.0, help="Lease time, seconds.")] = 10.0,
    database: Annotated[str | None, typer.Option(help="PostgreSQL URL (postgresql+psycopg://…) of an empty database. "
                                                 "Default: a server of the benchmark's own (the distribution's "
                                                 "PostgreSQL programs).")] = None,
    as_markdown: Annotated[bool, typer.Option("--markdown", help="Print a markdown table.")] = False,
) -> None:
    """Benchmark: a fleet of daemons on one PostgreSQL, one killed while it tunes; how soon its loops have an owner
    again and its sessions are recovered (docs/fleet.md). Real processes on this machine; a few minutes."""
    from autotuner.benchmarks.failover import HEADERS, FailoverSpec, markdown, run_failover, table_rows

    if tuning > loops // daemons:
        bad_input(f"--tuning {tuning} is more than the killed daemon's share of the loops ({loops // daemons})")
    try:
        result = run_failover(FailoverSpec(daemons, loops, tuning, lease, database=database))
    except FileNotFoundError as exc:
        bad_input(str(exc))
    title = f"failover: {daemons} daemons, {loops} loops, lease {lease:g} s; one daemon killed (SIGKILL)"
    if as_markdown:
        print(f"{title}\n\n{markdown([result])}")
        return
    table = Table(title=title, title_justify="left")
    for name in HEADERS:
        table.add_column(name, justify="right")
    for row in table_rows([result]):
        table.add_row(*row)
    stdout.print(table)
