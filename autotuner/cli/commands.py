"""Command line interface: ``autotuner tune``, ``autotuner design``, ``autotuner bench``, ``autotuner version``.

The contract (options, JSON shape, exit codes) is in docs/design.md. This
module only parses options, builds the engine's objects, shows progress and
prints results; all the work is done by :mod:`autotuner.engine.simulated_tuning` and
:mod:`autotuner.benchmarks.design_bench`.

Exit codes: 0 success, 1 the experiment or the design failed, 2 bad input.
"""

from __future__ import annotations

import asyncio
import contextlib
import cmath
import json
import math
import signal
import time
from collections.abc import Callable, Coroutine
from enum import Enum
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
from pydantic import ValidationError
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn
from rich.table import Table

from drivers.simplc import SimulatedPlc
from drivers.simplc import run as run_plc

from autotuner import __version__
from autotuner.benchmarks.design_bench import default_batch, format_table, load_batch, run_batch
from autotuner.engine.design.closed_loop import check_gains
from autotuner.benchmarks.rule_comparison import METHOD_NOTE, Row, compare
from autotuner.service.config import ConfigError, LoopConfig, TuneRequest, load_config
from autotuner.service.configured_loop import find_loop, tune_configured
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.design.process_data import ProcessData, from_fopdt, from_plant, from_point
from autotuner.engine.control.gains import FormError, Gains, to_parallel, to_series
from autotuner.engine.plant.process import Process
from autotuner.engine.design.robustness import log_grid
from autotuner.engine.experiment.relay import Point, RelayConfig, Status
from autotuner.engine.design.rules import RULES, Options, RuleError, Tuning, tune as tune_rule
from autotuner.service.remote_tuning import PLANT_TICKS_PER_SAMPLE, measure_jitter, tune_url, tune_via
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import TuneResult, default_sample_time, phase_frequency, tune

DEMO_PLANT = "1.5*exp(-0.7*s)/(4*s+1)^2"
# Time limit of a simulated experiment: this many expected periods of the
# oscillation, or this many samples when the plant never reaches the phase.
LIMIT_PERIODS = 200
LIMIT_SAMPLES = 20000
LINK_TIME_LIMIT = 7200.0

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


class Transport(str, Enum):
    MODBUS = "modbus"
    CAN = "can"


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
    stderr.print(f"[bold red]error:[/] {escape(message)}", highlight=False, markup=True, soft_wrap=True)
    raise typer.Exit(EXIT_BAD_INPUT)


def _time_limit(process: Process, phase: float, ts: float) -> float:
    """``LIMIT_PERIODS`` expected periods at the requested phase, else ``LIMIT_SAMPLES`` samples."""
    w = phase_frequency(process, phase)
    return LIMIT_PERIODS * 2.0 * math.pi / w if w is not None else LIMIT_SAMPLES * ts


def _config(amp: float, hysteresis: float | None, phase: float, time_limit: float) -> RelayConfig:
    try:
        return RelayConfig(amp=amp, phase_deg=phase, hysteresis=hysteresis, time_limit=time_limit)
    except ValueError as exc:
        _bad_input(str(exc))


def _prepare(
    plant: str, ts: float | None, amp: float, hysteresis: float | None, phase: float, noise: float, seed: int,
    time_limit: float | None = None,
) -> tuple[PlantSim, RelayConfig]:
    """The simulated plant and the experiment settings; bad input exits with code 2."""
    try:
        process = parse_process(plant)
    except ValueError as exc:  # ExpressionError names the token and its position
        _bad_input(f"bad --plant expression\n{exc}")
    try:
        sample_time = default_sample_time(process, phase) if ts is None else ts
        sim = PlantSim(process, sample_time, noise_std=noise, seed=seed)
    except ValueError as exc:
        _bad_input(str(exc))
    return sim, _config(amp, hysteresis, phase, time_limit or _time_limit(process, phase, sim.ts))


def _describe(status: Status) -> str:
    text = f"{status.stage.value:<5}  {status.periods:>2} periods"
    if status.code is None:
        text += f"  ≈ {status.ite:,.0f} s left"
    return text


def _run(
    start: Callable[[Callable[[Status], None] | None], Coroutine[Any, Any, TuneResult]], show_progress: bool
) -> TuneResult:
    """Run a tuning coroutine; with a progress bar on stderr (stdout stays clean) unless ``show_progress`` is off.

    SIGTERM cancels it like Ctrl-C does, so a field session restores its loop before the process exits.
    """

    async def main(on_status: Callable[[Status], None] | None) -> TuneResult:
        task = asyncio.current_task()
        loop = asyncio.get_running_loop()
        with contextlib.suppress(NotImplementedError, RuntimeError):  # no signals outside the main thread
            loop.add_signal_handler(signal.SIGTERM, task.cancel)
        return await start(on_status)

    if not show_progress:
        return asyncio.run(main(None))
    columns = (TextColumn("{task.description}"), BarColumn(), TaskProgressColumn(), TimeElapsedColumn())
    with Progress(*columns, console=stderr, transient=True) as progress:
        bar = progress.add_task("starting", total=1.0)

        def on_status(status: Status) -> None:
            progress.update(bar, completed=status.progress, description=_describe(status))

        return asyncio.run(main(on_status))


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


def _plant_ms(process: Process, gains: Gains, w_ref: float) -> str:
    """Ms of the designed loop on the simulated plant itself (inf: unstable)."""
    check = check_gains(process, gains, log_grid(w_ref))
    return "unstable" if math.isinf(check.ms) else f"{check.ms:.3f}"


def _result_table(result: TuneResult, ts: float, plant: Process | None = None) -> Table:
    table = Table(title=f"{result.controller} tuning", show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    outcome = "ok" if result.ok else f"[red]failed[/] (ite = {int(result.code)}): {escape(result.message)}"
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
        if plant is not None:
            table.add_row("Ms on the plant", _plant_ms(plant, des.gains, p.omega))
    return table


def _print_json(result: TuneResult) -> None:
    print(json.dumps(result.as_json(), allow_nan=False))


@app.command("tune")
def tune_command(
    ctx: typer.Context,
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
    link: Annotated[str | None, typer.Option(help="Tune a real loop in real time instead: modbus://HOST:PORT[/UNIT] "
                                             "or can://INTERFACE/CHANNEL (needs --ts).")] = None,
    map_file: Annotated[Path | None, typer.Option("--map", help="Modbus register map (YAML) for --link.")] = None,
    dbc: Annotated[Path | None, typer.Option(help="CAN database (DBC) for --link.")] = None,
    apply: Annotated[bool, typer.Option(help="Write the new gains to the controller on success.")] = False,
    via: Annotated[Transport | None, typer.Option(case_sensitive=False, help="Serve the simulated --plant over a "
                                                  "real Modbus TCP server or CAN virtual bus and tune it through "
                                                  "that link (self-test).")] = None,
    speed: Annotated[float | None, typer.Option(min=0.1, max=1000.0, help="With --via: plant seconds per wall "
                                                "second. Default: as fast as keeps 10 ms of wall time per "
                                                "sample, at most 20.")] = None,
    time_limit: Annotated[float | None, typer.Option(help="Longest experiment, s. Default: 200 expected periods "
                                                     "(simulation), 7200 s (--link).")] = None,
    config_file: Annotated[Path | None, typer.Option("--config", help="Daemon config (YAML, docs/daemon.md): tune "
                                                     "its loop --loop with the loop's link, sample time, limits "
                                                     "and defaults; options given here override the defaults.")]
    = None,
    loop_id: Annotated[str | None, typer.Option("--loop", help="Loop id in --config.")] = None,
) -> None:
    """Run a relay experiment and print the gains: on a simulated plant (default, faster than real time),
    through a field link to a real loop (--link, or a loop of a daemon config with --config/--loop), or on a
    simulated plant behind a real protocol stack (--via).

    Exit codes: 0 success, 1 the experiment or design failed, 2 bad input.
    """
    if (config_file is None) != (loop_id is None):
        _bad_input("--config and --loop go together")
    if config_file is not None:
        loop = _configured_loop(ctx, config_file, loop_id)
        request = _explicit_request(ctx, controller.value, amp, hysteresis, phase, ms, apply)
        sample_time = loop.ts

        def start(on_status: Callable[[Status], None] | None) -> Coroutine[Any, Any, TuneResult]:
            return tune_configured(loop, request, on_status)
    elif link is not None:
        if ts is None:
            _bad_input("--link needs --ts, the loop's sample time in seconds")
        config = _config(amp, hysteresis, phase, time_limit or LINK_TIME_LIMIT)
        sample_time = ts

        def start(on_status: Callable[[Status], None] | None) -> Coroutine[Any, Any, TuneResult]:
            return tune_url(link, config, ts, controller.value, ms, apply,
                            None if map_file is None else str(map_file), None if dbc is None else str(dbc), on_status)
    elif via is not None:
        sim, config = _prepare(plant, ts, amp, hysteresis, phase, noise, seed, time_limit)
        sample_time = sim.ts

        # A sample every 10 ms of wall time is what an asyncio loop keeps without much jitter.
        via_speed = speed or min(20.0, sim.ts / 0.01)

        def start(on_status: Callable[[Status], None] | None) -> Coroutine[Any, Any, TuneResult]:
            return tune_via(sim.process, via.value, config, sim.ts, controller.value, ms, via_speed, noise, seed,
                            on_status)
    else:
        sim, config = _prepare(plant, ts, amp, hysteresis, phase, noise, seed, time_limit)
        sample_time = sim.ts

        async def start(on_status: Callable[[Status], None] | None) -> TuneResult:
            return tune(sim, config, controller.value, ms, on_status=on_status)
    try:
        result = _run(start, show_progress=not as_json)
    except (ValueError, OSError) as exc:  # bad URL, map or DBC file, unreachable device
        _bad_input(str(exc))
    if as_json:
        _print_json(result)
    else:
        simulated = link is None and config_file is None
        stdout.print(_result_table(result, sample_time, sim.process if simulated else None))
    raise typer.Exit(EXIT_OK if result.ok else EXIT_FAILED)


# Options that choose another target than the config's loop.
_TARGET_OPTIONS = ("plant", "link", "via", "ts", "map_file", "dbc", "speed", "noise", "seed", "time_limit")


def _given(ctx: typer.Context, name: str) -> bool:
    # By name: typer vendors its own click, whose ParameterSource is not click's.
    source = ctx.get_parameter_source(name)
    return source is not None and source.name != "DEFAULT"


def _configured_loop(ctx: typer.Context, path: Path, loop_id: str) -> LoopConfig:
    """The loop ``loop_id`` of the daemon config ``path``; bad input (exit 2) for a bad file, id or option mix."""
    clash = [name for name in _TARGET_OPTIONS if _given(ctx, name)]
    if clash:
        options = ", ".join("--" + name.replace("_file", "").replace("_", "-") for name in clash)
        _bad_input(f"--config/--loop take the loop's own settings; drop {options}")
    try:
        return find_loop(load_config(path), loop_id)
    except (ConfigError, ValueError) as exc:
        _bad_input(str(exc))


def _explicit_request(ctx: typer.Context, controller: str, amp: float, hysteresis: float | None, phase: float,
                      ms: float, apply: bool) -> TuneRequest:
    """The tuning options given on the command line, as a TUNE request over the loop's defaults."""
    values = {"controller": controller, "amp": amp, "hysteresis": hysteresis, "phase": phase, "ms": ms,
              "apply": apply}
    try:
        return TuneRequest(**{name: value for name, value in values.items() if _given(ctx, name)})
    except ValidationError as exc:
        _bad_input("; ".join(f"--{error['loc'][0]}: {error['msg']}" for error in exc.errors()))


# -- sim --------------------------------------------------------------------


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        _bad_input(f"--modbus must be HOST:PORT, got {text!r}")
    return host, int(port)


@app.command("sim")
def sim_command(
    plant: Annotated[str, typer.Option(help="Process transfer function in s.")] = DEMO_PLANT,
    modbus: Annotated[str | None, typer.Option(help="Serve over Modbus TCP at HOST:PORT (default map, docs/modbus.md).")]
    = None,
    can: Annotated[str | None, typer.Option(help="Serve over CAN on this channel (default DBC, docs/can.md).")] = None,
    interface: Annotated[str, typer.Option(help="python-can interface for --can (socketcan, pcan, virtual, ...).")]
    = "socketcan",
    speed: Annotated[float, typer.Option(min=0.01, max=1000.0, help="Plant seconds per wall second.")] = 1.0,
    ts: Annotated[float | None, typer.Option(help="Plant sample time, s. Default: ~500 per period at 135°.")] = None,
    noise: Annotated[float, typer.Option(help="Standard deviation of measurement noise, PV units.")] = 0.0,
    seed: Annotated[int, typer.Option(help="Seed of the noise.")] = 0,
    duration: Annotated[float | None, typer.Option(help="Stop after this many wall seconds (default: run until "
                                                   "Ctrl-C or SIGTERM).")] = None,
) -> None:
    """Serve a simulated plant under a PID unit (a simulated PLC) over Modbus TCP and/or CAN."""
    if modbus is None and can is None:
        _bad_input("give --modbus HOST:PORT and/or --can CHANNEL")
    try:
        process = parse_process(plant)
    except ValueError as exc:
        _bad_input(f"bad --plant expression\n{exc}")
    address = None if modbus is None else _host_port(modbus)
    try:
        plc = SimulatedPlc(process, ts=(ts or default_sample_time(process) / PLANT_TICKS_PER_SAMPLE),
                           noise_std=noise, seed=seed)
    except ValueError as exc:
        _bad_input(str(exc))

    async def serve() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.add_signal_handler(sig, stop.set)
        if duration is not None:
            loop.call_later(duration, stop.set)
        servers = []
        try:
            if address is not None:
                from drivers.modbus_server import serve_modbus

                server = await serve_modbus(plc, address[0], address[1])
                servers.append(server)
                print(f"serving modbus://{address[0]}:{server.port}/1", flush=True)
            if can is not None:
                from drivers.can_node import serve_can

                servers.append(await serve_can(plc, interface, can, period=plc.ts / speed))
                print(f"serving can://{interface}/{can}", flush=True)
            print(f"plant {plant}, ts {plc.ts:.4g} s, {speed:g}× real time; Ctrl-C stops", flush=True)
            await run_plc(plc, speed, stop)
        finally:
            for server in servers:
                await server.close()

    try:
        asyncio.run(serve())
    except OSError as exc:  # port in use, no such CAN interface
        _bad_input(str(exc))


@app.command("jitter")
def jitter_command(
    via: Annotated[Transport, typer.Option(case_sensitive=False, help="Transport to the simulated plant.")]
    = Transport.MODBUS,
    rate: Annotated[float, typer.Option(min=1.0, max=1000.0, help="Sample rate, Hz.")] = 50.0,
    seconds: Annotated[float, typer.Option(min=1.0, max=3600.0, help="Length of the measurement, s.")] = 10.0,
    plant: Annotated[str, typer.Option(help="Process transfer function in s.")] = DEMO_PLANT,
) -> None:
    """Benchmark: sample a simulated plant over a real link as a tuning session does; print the timing."""
    try:
        process = parse_process(plant)
    except ValueError as exc:
        _bad_input(f"bad --plant expression\n{exc}")
    j = asyncio.run(measure_jitter(process, via.value, rate, seconds))
    table = Table(title=f"{j.samples} samples at {rate:g} Hz over {via.value} (localhost)", title_justify="left")
    for name in ("PV read done after due, p50", "p99", "max", "sample interval, p1", "p99"):
        table.add_column(name, justify="right")
    table.add_row(*(f"{x:.2f} ms" for x in (j.late_p50, j.late_p99, j.late_max, j.interval_p1, j.interval_p99)))
    stdout.print(table)


# -- serve ------------------------------------------------------------------


@app.command("serve")
def serve_command(
    config: Annotated[Path | None, typer.Option(help="Daemon config (YAML, docs/daemon.md). Default: a built-in "
                                                "demo of 3 simulated loops, 20× real time.")] = None,
    host: Annotated[str, typer.Option(help="Address to listen on.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(min=1, max=65535, help="TCP port.")] = 8000,
    ssl_certfile: Annotated[Path | None, typer.Option(help="TLS certificate (PEM); with --ssl-keyfile serves "
                                                      "HTTPS.")] = None,
    ssl_keyfile: Annotated[Path | None, typer.Option(help="TLS private key (PEM).")] = None,
) -> None:
    """Run the daemon: the REST API of design.md under /api/v1 over the configured loops.

    Tokens come from the config (hashed) and from $AUTOTUNER_TOKEN (an operator). The demo without
    --config generates an operator token and prints it once when $AUTOTUNER_TOKEN is unset.
    SIGTERM/SIGINT abort running experiments and restore their loops before the daemon exits.
    """
    import os

    import uvicorn

    from api.app import PREFIX, create_app
    from api.auth import new_token

    from autotuner.service.demo import demo_config
    from autotuner.service.history import History

    if (ssl_certfile is None) != (ssl_keyfile is None):
        _bad_input("--ssl-certfile and --ssl-keyfile go together")
    try:
        daemon_config = demo_config() if config is None else load_config(config)
    except ConfigError as exc:
        _bad_input(str(exc))
    try:  # a database that cannot be opened is a clear error now, not a failed start inside uvicorn
        History(daemon_config.history).close()
    except ValueError as exc:
        _bad_input(str(exc))
    token = os.environ.get("AUTOTUNER_TOKEN") or None
    if config is None and token is None:
        token = new_token()
        print(f"operator token (shown once; or set AUTOTUNER_TOKEN): {token}", flush=True)
    elif not daemon_config.tokens and token is None:
        stderr.print("warning: no tokens in the config and AUTOTUNER_TOKEN unset: every request except "
                     f"{PREFIX}/health will be refused", highlight=False)
    scheme = "http" if ssl_certfile is None else "https"
    print(f"autotuner API at {scheme}://{host}:{port}{PREFIX}  (OpenAPI: {PREFIX}/docs; operator page: "
          f"{scheme}://{host}:{port}/); {len(daemon_config.loops)} loops: "
          f"{', '.join(loop.id for loop in daemon_config.loops)}", flush=True)
    uvicorn.run(create_app(daemon_config, env_token=token or ""), host=host, port=port, log_level="info",
                ssl_certfile=None if ssl_certfile is None else str(ssl_certfile),
                ssl_keyfile=None if ssl_keyfile is None else str(ssl_keyfile))


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


# -- design -----------------------------------------------------------------


class RuleController(str, Enum):
    P = "P"
    PI = "PI"
    PID = "PID"


class StepKind(str, Enum):
    LOAD = "load"
    SETPOINT = "setpoint"


def _key_values(text: str, option: str, keys: tuple[str, ...]) -> dict[str, float]:
    """Parse ``k1=v1,k2=v2`` with exactly the given keys; bad input exits with code 2."""
    values: dict[str, float] = {}
    for part in text.split(","):
        key, sep, value = part.partition("=")
        key = key.strip()
        if not sep or key not in keys or key in values:
            _bad_input(f"bad {option} {text!r}: expected {','.join(k + '=..' for k in keys)}")
        try:
            values[key] = float(value)
        except ValueError:
            _bad_input(f"bad {option} {text!r}: {value.strip()!r} is not a number")
    if set(values) != set(keys):
        _bad_input(f"bad {option} {text!r}: expected {','.join(k + '=..' for k in keys)}")
    return values


def _design_data(fopdt: str | None, plant: str | None, point: str | None, static_gain: float | None) -> ProcessData:
    """The process data from exactly one of --fopdt, --plant, --point; bad input exits with code 2."""
    if sum(x is not None for x in (fopdt, plant, point)) != 1:
        _bad_input("give exactly one of --fopdt K=..,T=..,L=.., --plant EXPR, --point omega=..,gain=..,phase=..")
    if static_gain is not None and point is None:
        _bad_input("--static-gain goes with --point only (a model or plant has its own)")
    try:
        if fopdt is not None:
            v = _key_values(fopdt, "--fopdt", ("K", "T", "L"))
            return from_fopdt(v["K"], v["T"], v["L"])
        if plant is not None:
            return from_plant(parse_process(plant))
        v = _key_values(point, "--point", ("omega", "gain", "phase"))
        if not (v["omega"] > 0 and v["gain"] > 0 and -360.0 < v["phase"] <= 0.0):
            _bad_input("--point needs omega > 0 rad/s, gain > 0 and phase = arg F in degrees, "
                       "negative for lag (e.g. phase=-135)")
        value = v["gain"] * cmath.exp(1j * math.radians(v["phase"]))
        return from_point(Point(v["omega"], value), static_gain)
    except ValueError as exc:  # DataError, ExpressionError (names the token and its position)
        _bad_input(str(exc))


def _number(x: float | None) -> float | None:
    """JSON number, None for absent or infinite values."""
    return None if x is None or math.isinf(x) else float(x)


def _forms_json(gains: Gains) -> dict[str, Any]:
    """Series and parallel forms; the series form is null with the reason when Ti < 4·Td."""
    p = to_parallel(gains)
    out: dict[str, Any] = {"parallel": {"kp": p.kp, "ki": p.ki, "kd": p.kd}}
    try:
        ser = to_series(gains)
        out["series"] = {"k": ser.k, "ti": _number(ser.ti), "td": ser.td}
    except FormError as exc:
        out["series"] = None
        out["series_reason"] = str(exc)
    return out


def _tuning_json(tuning: Tuning) -> dict[str, Any]:
    return {"rule": tuning.rule, "controller": tuning.controller, "gains": tuning.gains.as_json(),
            **_forms_json(tuning.gains), **tuning.extra}


def _extra_rows(tuning: Tuning) -> list[tuple[str, str]]:
    rows = []
    for key, value in tuning.extra.items():
        if key == "two_controller":
            rows += [(name.replace("_", " "), json.dumps(value)) for name, value in value.items()]
        else:
            rows.append((key, ", ".join(f"{k} = {_fmt(v) if isinstance(v, float) else v}" for k, v in value.items())))
    return rows


def _tuning_table(tuning: Tuning) -> Table:
    table = Table(title=f"{tuning.rule}: {tuning.controller}", show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    for name, text in _gains_rows(tuning.gains) + _extra_rows(tuning):
        table.add_row(name, text)
    return table


def _compare_table(rows: list[Row], controller: str) -> Table:
    table = Table(title=f"{controller} rules compared on the plant", title_justify="left", caption=METHOD_NOTE,
                  caption_justify="left")
    table.add_column("rule", no_wrap=True)
    for col in ("k", "ti", "td", "b", "Ms", "GM", "PM °", "IAE load"):
        table.add_column(col, justify="right")
    for r in rows:
        g = r.tuning.gains
        metrics = ((_fmt(r.ms), _fmt(r.gain_margin), _fmt(r.phase_margin_deg), _fmt(r.iae)) if r.stable
                   else ("unstable", "—", "—", "—"))
        table.add_row(r.tuning.rule, _fmt(g.k), _fmt(g.ti), _fmt(g.td), _fmt(g.b), *metrics)
    return table


def _skipped_text(skipped: dict[str, str]) -> str:
    return "\n".join(f"not applicable: {name}: {reason}" for name, reason in skipped.items())


def _compare_json(rows: list[Row], skipped: dict[str, str], controller: str) -> dict[str, Any]:
    return {"controller": controller, "method": METHOD_NOTE, "skipped": skipped, "rules": [
        {**_tuning_json(r.tuning), "stable": r.stable, "ms": _number(r.ms), "gain_margin": _number(r.gain_margin),
         "phase_margin_deg": _number(r.phase_margin_deg), "iae_load": _number(r.iae)} for r in rows]}


def _rule_list() -> Table:
    table = Table(title="tuning rules (autotuner design --rule NAME)", title_justify="left")
    for col in ("rule", "controllers", "when to use it", "source"):
        table.add_column(col)
    for rule in RULES.values():
        table.add_row(rule.name, "/".join(rule.controllers), rule.when, rule.source)
    return table


@app.command("design")
def design_command(
    rule: Annotated[str | None, typer.Option(help="Rule name (see --list).")] = None,
    list_rules: Annotated[bool, typer.Option("--list", help="List the rules with when to use each.")] = False,
    compare_rules: Annotated[bool, typer.Option("--compare", help="All applicable rules in one table with Ms, "
                                                "margins and load-step IAE on the plant.")] = False,
    fopdt: Annotated[str | None, typer.Option(help="FOPDT model K·e^(−Ls)/(Ts+1): K=..,T=..,L=.. (s).")] = None,
    plant: Annotated[str | None, typer.Option(help="Process transfer function in s with optional dead time.")] = None,
    point: Annotated[str | None, typer.Option(help="Measured point F(jω): omega=..(rad/s),gain=..,phase=..(deg, "
                                              "negative for lag).")] = None,
    static_gain: Annotated[float | None, typer.Option(help="Static gain with --point (inf: integrating).")] = None,
    controller: Annotated[RuleController | None, typer.Option(case_sensitive=False, help="Controller type. "
                                                              "Default: PI (PID for direct-synthesis-unstable).")] = None,
    ts: Annotated[float | None, typer.Option(help="Sample time, s (takahashi).")] = None,
    ms: Annotated[float | None, typer.Option(min=1.05, max=10.0, help="Ms target: robust and itae-optimal "
                                             "(default 1.4), direct-synthesis-unstable (default 3).")] = None,
    rb: Annotated[float, typer.Option(help="astrom-hagglund: radius r_b of the target point (0–1).")] = 0.5,
    phib: Annotated[float, typer.Option(help="astrom-hagglund: angle φ_b of the target point, degrees.")] = 45.0,
    step: Annotated[StepKind, typer.Option(help="itae-optimal: the step whose ITAE is minimised.")] = StepKind.LOAD,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object to stdout.")] = False,
) -> None:
    """Classical tuning rules from a model, a plant or a measured point (methods.md §4).

    Exit codes: 0 success, 2 bad input or a rule that does not apply.
    """
    if list_rules:
        stdout.print(_rule_list())
        return
    if (rule is None) == (not compare_rules):
        _bad_input("give --rule NAME or --compare (or --list)")
    data = _design_data(fopdt, plant, point, static_gain)
    options = Options(ts=ts, ms=ms, rb=rb, phib_deg=phib, step=step.value)
    kind = controller.value if controller else None
    try:
        if compare_rules:
            rows, skipped = compare(data, kind or "PI", options)
        else:
            tuning = tune_rule(rule, data, kind, options)
    except RuleError as exc:
        _bad_input(str(exc))
    if compare_rules:
        if as_json:
            print(json.dumps(_compare_json(rows, skipped, kind or "PI"), allow_nan=False))
        else:
            stdout.print(_compare_table(rows, kind or "PI"))
            stdout.print(_skipped_text(skipped), highlight=False, markup=False)
    elif as_json:
        print(json.dumps(_tuning_json(tuning), allow_nan=False))
    else:
        stdout.print(_tuning_table(tuning))


# -- loadbench --------------------------------------------------------------


@app.command("loadbench")
def loadbench_command(
    loops: Annotated[list[int] | None, typer.Option("--loops", min=1, max=500, help="Loops tuned at once; "
                                                    "repeat for several runs. Default: 1, 10, 25, 50.")] = None,
    speed: Annotated[float, typer.Option(min=0.1, max=100.0, help="Plant seconds per wall second.")] = 1.0,
    ts: Annotated[float, typer.Option(min=0.001, help="Sample time, plant seconds.")] = 0.1,
    plant: Annotated[str, typer.Option(help="Process transfer function in s.")] = "exp(-0.5*s)/(s+1)",
    as_markdown: Annotated[bool, typer.Option("--markdown", help="Print a markdown table.")] = False,
) -> None:
    """Benchmark: N simulated loops tuned at once over Modbus TCP (localhost); sampling lateness and CPU.

    Not a test: it takes about a minute per run at the defaults (docs/daemon.md, "Load benchmark").
    """
    from autotuner.benchmarks.load import HEADERS, markdown, run_load, table_rows

    try:
        parse_process(plant)
    except ValueError as exc:
        _bad_input(f"bad --plant expression\n{exc}")
    results = []
    for n in loops or [1, 10, 25, 50]:
        result = asyncio.run(run_load(n, speed, ts, plant))
        results.append(result)
        for loop_id, message in result.failures.items():
            stderr.print(f"{n} loops: {loop_id} failed: {message}", highlight=False, markup=False)
    title = (f"tunings at once over Modbus TCP (localhost): ts {ts:g} s, {speed:g}× real time, one sample every "
             f"{1e3 * ts / speed:g} ms per loop; lateness of the PV read behind its due time")
    if as_markdown:
        print(f"{title}\n\n{markdown(results)}")
    else:
        table = Table(title=title, title_justify="left")
        for name in HEADERS:
            table.add_column(name, justify="right")
        for row in table_rows(results):
            table.add_row(*row)
        stdout.print(table)
    if any(r.succeeded < r.loops for r in results):
        raise typer.Exit(EXIT_FAILED)


def main() -> Any:
    """Console-script entry point."""
    return app()

