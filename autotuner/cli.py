"""Command line interface: ``autotuner tune``, ``autotuner bench``, ``autotuner version``.

The contract (options, JSON shape, exit codes) is in docs/design.md. This
module only parses options, builds the engine's objects, shows progress and
prints results; all the work is done by :mod:`autotuner.tuning` and
:mod:`autotuner.bench`.

Exit codes: 0 success, 1 the experiment or the design failed, 2 bad input.
"""

from __future__ import annotations

import json
import math
import time
from enum import Enum
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn
from rich.table import Table

from . import __version__
from .bench import default_batch, format_table, load_batch, run_batch
from .expr import parse_process
from .gains import FormError, Gains, to_parallel, to_series
from .process import Process
from .relay import RelayConfig, Status
from .simulate import PlantSim
from .tuning import TuneResult, default_sample_time, phase_frequency, tune

DEMO_PLANT = "1.5*exp(-0.7*s)/(4*s+1)^2"
# Time limit of a simulated experiment: this many expected periods of the
# oscillation, or this many samples when the plant never reaches the phase.
LIMIT_PERIODS = 200
LIMIT_SAMPLES = 20000

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2

stdout = Console()
stderr = Console(stderr=True)

app = typer.Typer(
    help="Relay-feedback PI/PID autotuner: identify one point of the process frequency "
    "response with a relay + adaptive phase filter, then compute robust gains.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


class Controller(str, Enum):
    PI = "PI"
    PID = "PID"


def _version_callback(value: bool) -> None:
    if value:
        print(__version__)
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool, typer.Option("--version", callback=_version_callback, is_eager=True, help="Print the version and exit.")
    ] = False,
) -> None:
    """Relay-feedback PI/PID autotuner."""


@app.command()
def version() -> None:
    """Print the version."""
    print(__version__)


# -- tune -------------------------------------------------------------------


def _bad_input(message: str) -> NoReturn:
    stderr.print(f"[bold red]error:[/] {message}", highlight=False, markup=True, soft_wrap=True)
    raise typer.Exit(EXIT_BAD_INPUT)


def _time_limit(process: Process, phase: float, ts: float) -> float:
    """``LIMIT_PERIODS`` expected periods at the requested phase, else ``LIMIT_SAMPLES`` samples."""
    w = phase_frequency(process, phase)
    return LIMIT_PERIODS * 2.0 * math.pi / w if w is not None else LIMIT_SAMPLES * ts


def _prepare(
    plant: str, ts: float | None, amp: float, hysteresis: float | None, phase: float, noise: float, seed: int
) -> tuple[PlantSim, RelayConfig]:
    """The simulated plant and the experiment settings; bad input exits with code 2."""
    try:
        process = parse_process(plant)
    except ValueError as exc:  # ExpressionError names the token and its position
        _bad_input(f"bad --plant expression\n{exc}")
    try:
        sample_time = default_sample_time(process, phase) if ts is None else ts
        sim = PlantSim(process, sample_time, noise_std=noise, seed=seed)
        limit = _time_limit(process, phase, sim.ts)
        config = RelayConfig(amp=amp, phase_deg=phase, hysteresis=hysteresis, time_limit=limit)
    except ValueError as exc:
        _bad_input(str(exc))
    return sim, config


def _describe(status: Status) -> str:
    text = f"{status.stage.value:<5}  {status.periods:>2} periods"
    if status.code is None:
        text += f"  ≈ {status.ite:,.0f} s left"
    return text


def _run_with_progress(sim: PlantSim, config: RelayConfig, controller: str, ms: float) -> TuneResult:
    """Tune while showing a progress bar on stderr (stdout stays clean)."""
    columns = (TextColumn("{task.description}"), BarColumn(), TaskProgressColumn(), TimeElapsedColumn())
    with Progress(*columns, console=stderr, transient=True) as progress:
        task = progress.add_task("starting", total=1.0)

        def on_status(status: Status) -> None:
            progress.update(task, completed=status.progress, description=_describe(status))

        return tune(sim, config, controller, ms, on_status=on_status)


def _fmt(x: float, unit: str = "") -> str:
    return "∞" if math.isinf(x) else f"{x:.4g}{unit}"


def _gains_rows(gains: Gains) -> list[tuple[str, str]]:
    rows = [
        ("standard (ISA)", f"k = {_fmt(gains.k)}, ti = {_fmt(gains.ti, ' s')}, td = {_fmt(gains.td, ' s')}, "
         f"nd = {_fmt(gains.nd)}, b = {_fmt(gains.b)}, c = {_fmt(gains.c)}"),
    ]
    try:
        s = to_series(gains)
        rows.append(("series", f"k' = {_fmt(s.k)}, ti' = {_fmt(s.ti, ' s')}, td' = {_fmt(s.td, ' s')}"))
    except FormError as exc:
        rows.append(("series", f"does not exist: {exc}"))
    p = to_parallel(gains)
    rows.append(("parallel", f"kp = {_fmt(p.kp)}, ki = {_fmt(p.ki, ' /s')}, kd = {_fmt(p.kd, ' s')}"))
    return rows


def _model_text(model: Process) -> str:
    """The model in time-constant form, e.g. ``1.5*exp(-2.5*s)/(8.8*s+1)``."""
    n = model.integrator_count
    gain = model.num[-1] / model.den[-1 - n]
    text = f"{gain:.4g}" + (f"*exp(-{model.delay:.4g}*s)" if model.delay else "")
    text += "/s" * n
    text += "".join(f"/({-1.0 / p.real:.4g}*s+1)" for p in model.poles if p != 0)
    return text


def _result_table(result: TuneResult, ts: float) -> Table:
    table = Table(title=f"{result.controller} tuning", show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    outcome = "ok" if result.ok else f"[red]failed[/] (ite = {int(result.code)}): {result.message}"
    table.add_row("result", outcome)
    ident, des = result.identification, result.design
    if ident is None:
        exp = result.as_json()["experiment"]
        table.add_row("experiment", f"{exp['duration']:.4g} s, {exp['samples']} samples (ts = {ts:.4g} s)")
        return table
    p = ident.point
    table.add_row("point", f"ω = {p.omega:.4g} rad/s, |F| = {p.gain:.4g}, phase = {p.phase_deg:.2f}°")
    table.add_row("static gain", "integrating (∞)" if math.isinf(ident.static_gain) else f"{ident.static_gain:.4g}")
    table.add_row("experiment", f"{ident.duration:.4g} s, {ident.periods:.1f} periods, {ident.samples} samples "
                  f"(ts = {ts:.4g} s, hysteresis = {ident.hysteresis:.3g})")
    if des is not None:
        for name, text in _gains_rows(des.gains):
            table.add_row(name, text)
        table.add_row("model", f"{des.model.text}: {_model_text(des.model)}")
        table.add_row("Ms on model", f"{des.model_ms:.3f}")
    return table


def _print_json(result: TuneResult) -> None:
    print(json.dumps(result.as_json(), allow_nan=False))


@app.command("tune")
def tune_command(
    plant: Annotated[
        str,
        typer.Option(help="Process transfer function in s with optional dead time. "
                     "Default: a built-in demo plant, so plain `autotuner tune` tunes a simulated loop."),
    ] = DEMO_PLANT,
    controller: Annotated[Controller, typer.Option(case_sensitive=False, help="Controller type.")] = Controller.PI,
    ts: Annotated[
        float | None, typer.Option(help="Sample time, s. Default: about 100 samples per period at --phase.")
    ] = None,
    amp: Annotated[float, typer.Option(help="Relay amplitude, MV units (> 0).")] = 1.0,
    hysteresis: Annotated[
        float | None, typer.Option(help="Relay hysteresis, PV units. Default: 3σ of the measured noise.")
    ] = None,
    phase: Annotated[float, typer.Option(help="Phase lag of the identified point, degrees (90–170).")] = 135.0,
    ms: Annotated[float, typer.Option(min=1.05, max=4.0, help="Maximum sensitivity of the design.")] = 1.4,
    noise: Annotated[float, typer.Option(help="Standard deviation of white measurement noise, PV units.")] = 0.0,
    seed: Annotated[int, typer.Option(help="Seed of the noise.")] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object (docs/design.md) to stdout.")] = False,
) -> None:
    """Run a relay experiment on a simulated plant (faster than real time) and print the gains.

    Exit codes: 0 success, 1 the experiment or design failed, 2 bad input.
    """
    sim, config = _prepare(plant, ts, amp, hysteresis, phase, noise, seed)
    if as_json:
        result = tune(sim, config, controller.value, ms)
    else:
        result = _run_with_progress(sim, config, controller.value, ms)
    if as_json:
        _print_json(result)
    else:
        stdout.print(_result_table(result, sim.ts))
    raise typer.Exit(EXIT_OK if result.ok else EXIT_FAILED)


# -- bench ------------------------------------------------------------------


@app.command()
def bench(
    batch: Annotated[Path | None, typer.Option(help="Batch CSV (id, family, params, expr, ...). "
                                               "Default: the Åström–Hägglund batch shipped with the package.")] = None,
    workers: Annotated[int | None, typer.Option(min=1, help="Worker processes. Default: all cores.")] = None,
    output: Annotated[Path | None, typer.Option(help="Also write the table (markdown) to this file.")] = None,
    design_only: Annotated[bool, typer.Option("--design-only", help="Only the design rule, from the exact "
                                              "135° point and static gain (no experiment).")] = False,
) -> None:
    """Benchmark the experiment and the design on every process of a batch against the usual relay tuners."""
    start = time.perf_counter()
    try:
        rows = load_batch(batch or default_batch())
        for row in rows:  # here, not in a worker: a bad expression gets a clear message
            parse_process(row["expr"])
    except KeyError as exc:
        _bad_input(f"bad batch {batch}: missing column {exc}")
    except (OSError, ValueError) as exc:  # unreadable file, bad expression
        _bad_input(f"bad batch {batch}: {exc}")
    table = format_table(run_batch(rows, workers, design_only))
    print(table)
    if output is not None:
        output.write_text(table + "\n")
    stderr.print(f"{len(rows)} processes in {time.perf_counter() - start:.1f} s wall time", highlight=False)


def main() -> Any:
    """Console-script entry point."""
    return app()


if __name__ == "__main__":
    main()
