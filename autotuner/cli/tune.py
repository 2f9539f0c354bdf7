"""``autotuner tune``: a relay experiment on a simulated plant, a field link, a configured loop or a
simulated plant behind a real protocol stack; prints the gains (table or the JSON of docs/design.md).

Exit codes: 0 success, 1 the experiment or the design failed, 2 bad input.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import signal
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.markup import escape
from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn
from rich.table import Table

from autotuner.cli.app import (
    DEMO_PLANT, EXIT_FAILED, EXIT_OK, Controller, Transport, app, bad_input, gains_rows, parse_loads, parse_plant,
    stderr, stdout,
)

if TYPE_CHECKING:
    from autotuner.engine.control.gains import Gains
    from autotuner.engine.experiment.relay import RelayConfig, Status
    from autotuner.engine.plant.process import Process
    from autotuner.engine.plant.simulation import PlantSim
    from autotuner.engine.result import TuneResult
    from autotuner.service.config import DaemonConfig, LoopConfig, TuneRequest


def _config(amp: float, hysteresis: float | None, phase: float, time_limit: float,
            mv_limits: tuple[float, float] = (-math.inf, math.inf)) -> RelayConfig:
    from autotuner.engine.experiment.relay import RelayConfig

    try:
        return RelayConfig(amp=amp, phase_deg=phase, hysteresis=hysteresis, time_limit=time_limit,
                           mv_limits=mv_limits)
    except ValueError as exc:
        bad_input(str(exc))


def _check_plant(process: Process, text: str) -> None:
    """Refuse plants no relay experiment can tune (exit 2): zero gain, or no dynamics at all."""
    if process.num == (0.0,):
        bad_input(f"--plant {text!r} is zero: the MV has no effect on the PV, there is nothing to tune")
    if process.order == 0 and process.delay == 0.0:
        bad_input(f"--plant {text!r} has no dynamics (a pure gain): the PV follows the MV at once, so a relay "
                  "experiment identifies no frequency-response point; give a transfer function in s, "
                  "e.g. 2*exp(-s)/(3*s+1)")


def _mv_limits(text: str | None) -> tuple[float, float]:
    """``--mv-limits LO:HI`` as (LO, HI), MV units; none given: unbounded."""
    if text is None:
        return -math.inf, math.inf
    low, sep, high = text.partition(":")
    try:
        limits = float(low), float(high)
    except ValueError:
        limits = (math.nan, math.nan)
    if not sep or not all(math.isfinite(x) for x in limits) or not limits[0] < limits[1]:
        bad_input(f"--mv-limits must be LO:HI with finite numbers LO < HI (MV units), got {text!r}")
    return limits


def _prepare(
    plant: str, ts: float | None, amp: float, hysteresis: float | None, phase: float, noise: float, seed: int,
    time_limit: float | None = None, loads: list[tuple[float, float]] | None = None, drift: float = 0.0,
    quantum: float = 0.0, mv_limits: tuple[float, float] = (-math.inf, math.inf),
) -> tuple[PlantSim, RelayConfig]:
    """The simulated plant (with its load steps, drift and PV resolution) and the experiment settings.

    Bad input exits with code 2.
    """
    from autotuner.engine.plant.simulation import PlantSim
    from autotuner.engine.simulated_tuning import default_sample_time, default_time_limit, ramp_loads

    process = parse_plant(plant)
    _check_plant(process, plant)
    if not math.isfinite(drift):
        bad_input(f"--drift must be a finite number of MV units per second, got {drift}")
    try:
        sample_time = default_sample_time(process, phase) if ts is None else ts
        limit = time_limit or default_time_limit(process, phase, sample_time)
        steps = list(loads or ()) + ramp_loads(drift, sample_time, limit)
        sim = PlantSim(process, sample_time, noise_std=noise, seed=seed, quantum=quantum, loads=steps)
    except ValueError as exc:
        bad_input(str(exc))
    return sim, _config(amp, hysteresis, phase, time_limit or default_time_limit(process, phase, sim.ts), mv_limits)


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


def _plant_ms(process: Process, gains: Gains, w_ref: float) -> str:
    """Ms of the designed loop on the simulated plant itself (inf: unstable)."""
    from autotuner.engine.design.closed_loop import check_gains
    from autotuner.engine.design.robustness import log_grid

    check = check_gains(process, gains, log_grid(w_ref))
    return "unstable" if math.isinf(check.ms) else f"{check.ms:.3f}"


def _result_table(result: TuneResult, ts: float, plant: Process | None = None) -> Table:
    table = Table(title=f"{result.controller} tuning", show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    if not result.ok:
        outcome = f"[red]failed[/] (ite = {int(result.code)}): {escape(result.message)}"
    elif int(result.code) == 0:
        outcome = "ok"
    else:  # a warning: gains usable, but the message names what was missed
        # (The message opens with "warning: " itself.)
        outcome = f"[yellow]warning[/] (ite = {int(result.code)}): {escape(result.message.removeprefix('warning: '))}"
    table.add_row("result", outcome)
    ident, des = result.identification, result.design
    if ident is None:
        exp = result.as_json()["experiment"]
        table.add_row("experiment", f"{exp['duration']:.4g} s, {exp['samples']} samples (ts = {ts:.4g} s)")
        return table
    p = ident.point
    table.add_row("point", f"ω = {p.omega:.4g} rad/s, |F| = {p.gain:.4g}, phase = {p.phase_deg:.2f}°")
    if ident.phase_moved:
        table.add_row("phase target", f"{ident.phase_target_deg:.1f}° of lag (moved from the requested one: out of "
                      "reach of this unstable process)")
    table.add_row("static gain", "integrating (∞)" if math.isinf(ident.static_gain) else f"{ident.static_gain:.4g}")
    table.add_row("experiment", f"{ident.duration:.4g} s, {ident.periods:.1f} periods, {ident.samples} samples "
                  f"(ts = {ts:.4g} s, hysteresis = {ident.hysteresis:.3g})")
    if ident.disturbance:
        table.add_row("disturbance", f"a load change of {ident.load_estimate:+.4g} MV units at the process input "
                      "(or a PV still settling at the start) was detected and the static gain estimated through it"
                      + (f"; {ident.periods_discarded} periods before it left out" if ident.periods_discarded else ""))
    if des is not None:
        for name, text in gains_rows(des.gains):
            table.add_row(name, text)
        real = all(abs(pole.imag) == 0.0 for pole in des.model.poles)  # a resonance has no time-constant form
        table.add_row("model", f"{des.model.text}: {des.model.time_constant_text() if real else des.model}")
        table.add_row("Ms on model", f"{des.model_ms:.3f} (target {des.ms_target:.3g})")
        table.add_row("noise gain", f"{des.noise_gain:.4g} (MV noise per PV noise)")
        for note in des.notes:
            table.add_row("design note", escape(note))
        if plant is not None:
            table.add_row("Ms on the plant", _plant_ms(plant, des.gains, p.omega))
    return table


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
    load: Annotated[list[str] | None, typer.Option("--load", help="Load step T:SIZE at the process input (plant "
                                                   "seconds from the start of the experiment : MV units); "
                                                   "repeat for several. With --via the simulated PLC makes "
                                                   "it, T from when the session takes the loop over.")] = None,
    drift: Annotated[float, typer.Option(help="Load ramp at the process input from the start, MV units per "
                                         "second.")] = 0.0,
    quantum: Annotated[float, typer.Option(min=0.0, help="PV resolution (the sensor rounds to multiples of it), "
                                           "PV units; 0: none.")] = 0.0,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object (docs/design.md) to stdout.")] = False,
    link: Annotated[str | None, typer.Option(help="Tune a real loop in real time instead: "
                                             f"{escape('modbus://HOST:PORT[/UNIT]')} "
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
    mv_limits: Annotated[str | None, typer.Option(help="MV limits of the experiment, LO:HI (MV units); with "
                                                  "--link, --amp may not exceed HI-LO (without them: 100).")]
    = None,
) -> None:
    """Run a relay experiment and print the gains: on a simulated plant (default, faster than real time),
    through a field link to a real loop (--link, or a loop of a daemon config with --config/--loop), or on a
    simulated plant behind a real protocol stack (--via).

    Exit codes: 0 success, 1 the experiment or design failed, 2 bad input.
    """
    if (config_file is None) != (loop_id is None):
        bad_input("--config and --loop go together")
    field = [name for name, given in (("--load", bool(load)), ("--drift", drift != 0.0), ("--quantum", quantum != 0.0))
             if given]
    if field and (config_file is not None or link is not None):
        bad_input(f"{', '.join(field)} simulate field conditions on a simulated --plant only "
                  "(not with --config or --link)")
    if via is not None and (drift != 0.0 or quantum != 0.0):
        bad_input("--drift and --quantum simulate field conditions on the in-process --plant only (with --via: "
                  "--load, the PLC's load steps from when the tuner takes the loop)")
    steps = parse_loads(load, "the start of the experiment")
    if config_file is not None:
        from autotuner.service.configured_loop import cli_user, tune_configured
        from autotuner.service.history import History

        daemon_config, loop = _configured_loop(ctx, config_file, loop_id)
        request = _explicit_request(ctx, controller.value, amp, hysteresis, phase, ms, apply)
        sample_time = loop.ts

        async def start(on_status: Callable[[Status], None] | None) -> TuneResult:
            # The loop's history, as the daemon keeps it (a damaged or unreachable one: ValueError, bad input).
            # Writes are retried for as long as the session waits for them, so the command ends soon after.
            history = History(daemon_config.history, retry_for=daemon_config.record_wait)
            try:
                return await tune_configured(loop, request, on_status, daemon_config.handback.session(), history,
                                             cli_user(), daemon_config.record_wait)
            finally:
                history.close()
    elif link is not None:
        from autotuner.service.link_session import SessionHooks, SessionPlan, tune_link
        from autotuner.service.remote_tuning import LINK_TIME_LIMIT, field_config, open_link, tune_opened

        if ts is None:
            bad_input("--link needs --ts, the loop's sample time in seconds")
        from autotuner.service.config import amp_bound

        limits = _mv_limits(mv_limits)
        if amp > amp_bound(limits):
            bad_input(f"--amp {amp:g} is above the largest relay amplitude {amp_bound(limits):g} MV units "
                      "(HI-LO of --mv-limits, else the default bound): it would be written to a live controller")
        config = _config(amp, hysteresis, phase, time_limit or LINK_TIME_LIMIT, limits)
        sample_time = ts

        async def start(on_status: Callable[[Status], None] | None) -> TuneResult:
            opened = open_link(link, None if map_file is None else str(map_file), None if dbc is None else str(dbc))
            plan = SessionPlan(field_config(config), ts, controller.value, ms, apply)
            return await tune_opened(opened, controller.value,
                                     lambda on: tune_link(on, plan, SessionHooks(on_status=on_status)))
    elif via is not None:
        from autotuner.service.remote_tuning import default_via_speed, tune_via

        sim, config = _prepare(plant, ts, amp, hysteresis, phase, noise, seed, time_limit,
                               mv_limits=_mv_limits(mv_limits))
        sample_time = sim.ts
        via_speed = speed or default_via_speed(sim.ts)

        def start(on_status: Callable[[Status], None] | None) -> Coroutine[Any, Any, TuneResult]:
            return tune_via(sim.process, via.value, config, sim.ts, controller.value, ms, via_speed, noise, seed,
                            on_status, loads=steps)
    else:
        from autotuner.engine.simulated_tuning import tune

        sim, config = _prepare(plant, ts, amp, hysteresis, phase, noise, seed, time_limit, steps, drift, quantum,
                               _mv_limits(mv_limits))
        sample_time = sim.ts

        async def start(on_status: Callable[[Status], None] | None) -> TuneResult:
            return tune(sim, config, controller.value, ms, on_status=on_status)
    try:
        result = _run(start, show_progress=not as_json)
    except (ValueError, OSError) as exc:  # bad URL, map or DBC file, unreachable device
        bad_input(str(exc))
    if as_json:
        print(json.dumps(result.as_json(), allow_nan=False))
    else:
        simulated = link is None and config_file is None
        stdout.print(_result_table(result, sample_time, sim.process if simulated else None))
    raise typer.Exit(EXIT_OK if result.ok else EXIT_FAILED)


# Options that choose another target than the config's loop.
_TARGET_OPTIONS = ("plant", "link", "via", "ts", "map_file", "dbc", "speed", "noise", "seed", "time_limit",
                   "mv_limits")


def _given(ctx: typer.Context, name: str) -> bool:
    # By name: typer vendors its own click, whose ParameterSource is not click's.
    source = ctx.get_parameter_source(name)
    return source is not None and source.name != "DEFAULT"


def _configured_loop(ctx: typer.Context, path: Path, loop_id: str) -> tuple[DaemonConfig, LoopConfig]:
    """The daemon config ``path`` and its loop ``loop_id``; bad input (exit 2) for a bad file, id or option mix."""
    from autotuner.service.config import ConfigError, load_config
    from autotuner.service.configured_loop import find_loop

    clash = [name for name in _TARGET_OPTIONS if _given(ctx, name)]
    if clash:
        options = ", ".join("--" + name.replace("_file", "").replace("_", "-") for name in clash)
        bad_input(f"--config/--loop take the loop's own settings; drop {options}")
    try:
        config = load_config(path)
        return config, find_loop(config, loop_id)
    except (ConfigError, ValueError) as exc:
        bad_input(str(exc))


def _explicit_request(ctx: typer.Context, controller: str, amp: float, hysteresis: float | None, phase: float,
                      ms: float, apply: bool) -> TuneRequest:
    """The tuning options given on the command line, as a TUNE request over the loop's defaults."""
    from pydantic import ValidationError

    from autotuner.service.config import TuneRequest

    values = {"controller": controller, "amp": amp, "hysteresis": hysteresis, "phase": phase, "ms": ms,
              "apply": apply}
    try:
        return TuneRequest(**{name: value for name, value in values.items() if _given(ctx, name)})
    except ValidationError as exc:
        bad_input("; ".join(f"--{error['loc'][0]}: {error['msg']}" for error in exc.errors()))
