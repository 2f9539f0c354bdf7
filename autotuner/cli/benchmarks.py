"""Benchmarks (tables, not tests): ``autotuner bench`` (the experiment and the design over a batch of
processes) and ``autotuner loadbench`` (many loops tuned at once over Modbus TCP)."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from autotuner.cli.app import EXIT_FAILED, app, bad_input, parse_plant, stderr, stdout


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
) -> None:
    """Benchmark the experiment and the design on every process of a batch against the usual relay tuners."""
    if field and design_only:
        bad_input("--field and --design-only exclude each other")
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


@app.command("loadbench")
def loadbench_command(
    loops: Annotated[list[int] | None, typer.Option("--loops", min=1, max=500, help="Loops tuned at once; "
                                                    "repeat for several runs. Default: 1, 10, 25, 50.")] = None,
    speed: Annotated[float, typer.Option(min=0.1, max=100.0, help="Plant seconds per wall second.")] = 1.0,
    ts: Annotated[float, typer.Option(min=0.001, help="Sample time, plant seconds.")] = 0.1,
    plant: Annotated[str, typer.Option(help="Process transfer function in s.")] = "exp(-0.5*s)/(s+1)",
    as_markdown: Annotated[bool, typer.Option("--markdown", help="Print a markdown table.")] = False,
    opcua: Annotated[bool, typer.Option("--opcua", help="Also publish the loops over OPC UA to a client subscribed "
                                        "to all their variables (docs/opcua.md). Needs the opcua extra.")] = False,
    monitor_period: Annotated[float, typer.Option(min=0.05, max=60.0, help="The loops' monitor period (and OPC UA "
                                                  "publishing interval), wall seconds.")] = 1.0,
) -> None:
    """Benchmark: N simulated loops tuned at once over Modbus TCP (localhost); sampling lateness and CPU.

    Not a test: it takes about a minute per run at the defaults (docs/daemon.md, "Load benchmark").
    """
    from autotuner.benchmarks.load import headers, markdown, run_load, table_rows

    parse_plant(plant)
    if opcua:
        from api.opcua import require

        try:
            require()
        except RuntimeError as exc:
            bad_input(str(exc))
    results = []
    for n in loops or [1, 10, 25, 50]:
        result = asyncio.run(run_load(n, speed, ts, plant, opcua=opcua, monitor_period=monitor_period))
        results.append(result)
        for loop_id, message in result.failures.items():
            stderr.print(f"{n} loops: {loop_id} failed: {message}", highlight=False, markup=False)
    title = (f"tunings at once over Modbus TCP (localhost): ts {ts:g} s, {speed:g}× real time, one sample every "
             f"{1e3 * ts / speed:g} ms per loop; lateness of the PV read behind its due time")
    if as_markdown:
        print(f"{title}\n\n{markdown(results)}")
    else:
        table = Table(title=title, title_justify="left")
        for name in headers(results):
            table.add_column(name, justify="right")
        for row in table_rows(results):
            table.add_row(*row)
        stdout.print(table)
    if any(r.succeeded < r.loops for r in results):
        raise typer.Exit(EXIT_FAILED)
