"""Field links without a plant of one's own: ``autotuner sim`` serves a simulated PLC over Modbus TCP
and/or CAN (or a plant of many, ``--loops``, over Modbus TCP); ``autotuner jitter`` measures the sampling timing
over a real link."""

from __future__ import annotations

import asyncio
import contextlib
import signal
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from autotuner.cli.app import DEMO_PLANT, Transport, app, bad_input, parse_loads, parse_plant, stdout

if TYPE_CHECKING:
    from drivers.link import Mode


# Loops of `sim --loops`: the unit ids 1..247 of one Modbus server (drivers.modbus_plant.UNITS_PER_SERVER; a
# constant here, since the CLI does not import the drivers to show its help).
MAX_LOOPS = 247


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        bad_input(f"--modbus must be HOST:PORT, got {text!r}")
    return host, int(port)


@app.command("sim")
def sim_command(
    plant: Annotated[str, typer.Option(help="Process transfer function in s.")] = DEMO_PLANT,
    modbus: Annotated[str | None, typer.Option(help="Serve over Modbus TCP at HOST:PORT (default map, docs/modbus.md).")]
    = None,
    can: Annotated[str | None, typer.Option(help="Serve over CAN on this channel (default DBC, docs/can.md).")] = None,
    interface: Annotated[str, typer.Option(help="python-can interface for --can (socketcan, pcan, virtual, "
                                           "udp_multicast, ...).")] = "socketcan",
    can_port: Annotated[int | None, typer.Option(min=1, max=65535, help="UDP port of --interface udp_multicast "
                                                 "(default: python-can's).")] = None,
    hop_limit: Annotated[int | None, typer.Option(min=0, max=255, help="Multicast hop limit of --interface "
                                                  "udp_multicast (0: the frames never leave this host).")] = None,
    speed: Annotated[float, typer.Option(min=0.01, max=1000.0, help="Plant seconds per wall second.")] = 1.0,
    ts: Annotated[float | None, typer.Option(help="Plant sample time, s. Default: ~500 per period at 135°.")] = None,
    noise: Annotated[float, typer.Option(help="Standard deviation of measurement noise, PV units.")] = 0.0,
    seed: Annotated[int, typer.Option(help="Seed of the noise (loop k of --loops: SEED + k − 1).")] = 0,
    duration: Annotated[float | None, typer.Option(help="Stop after this many wall seconds (default: run until "
                                                   "Ctrl-C or SIGTERM).")] = None,
    load: Annotated[list[str] | None, typer.Option("--load", help="Load step T:SIZE at the process input (plant "
                                                   "seconds from when a tuner first takes the loop over, i.e. "
                                                   "the PLC's first cycle in MAN : MV units); repeat for "
                                                   "several.")] = None,
    loops: Annotated[int | None, typer.Option(min=1, max=MAX_LOOPS, help="Serve a plant of this many loops behind "
                                              "the one --modbus server, loop k on unit id k (docs/modbus.md); "
                                              "--plant, --ts, --noise, --load, --speed apply to every loop.")]
    = None,
) -> None:
    """Serve a simulated plant under a PID unit (a simulated PLC) over Modbus TCP and/or CAN, or many over Modbus."""
    from drivers.modbus_plant import serve_plant
    from drivers.simplc import SimulatedPlc

    from autotuner.engine.simulated_tuning import default_sample_time
    from autotuner.service.remote_tuning import PLANT_TICKS_PER_SAMPLE, serving

    if modbus is None and can is None:
        bad_input("give --modbus HOST:PORT and/or --can CHANNEL")
    if loops is not None and (can is not None or modbus is None):
        bad_input("--loops serves its loops over Modbus TCP only: give --modbus HOST:PORT and no --can "
                  "(one CAN node per loop would need a frame layout per loop)")
    can_options = {k: v for k, v in (("port", can_port), ("hop_limit", hop_limit)) if v is not None}
    if can_options and (can is None or interface != "udp_multicast"):
        bad_input("--can-port and --hop-limit are options of --can with --interface udp_multicast")
    process = parse_plant(plant)
    steps = parse_loads(load, "when a tuner takes the loop over")
    address = None if modbus is None else _host_port(modbus)
    plant_ts = ts or default_sample_time(process) / PLANT_TICKS_PER_SAMPLE
    try:
        plc = SimulatedPlc(process, ts=plant_ts, noise_std=noise, seed=seed, loads=tuple(steps), on_mode=_said_mode)
    except ValueError as exc:
        bad_input(str(exc))
    about = f"plant {plant}, ts {plc.ts:.4g} s, {speed:g}× real time; Ctrl-C stops"

    async def serve_one() -> None:
        stop = _stop_event(duration)
        async with serving(plc, speed, address, None if can is None else (interface, can), can_options) as servers:
            for url, _ in servers:
                print(f"serving {url}", flush=True)
            print(about, flush=True)
            await stop.wait()

    async def serve_many(n: int, host: str, port: int) -> None:
        stop = _stop_event(duration)
        async with await serve_plant(n, process, ts=plc.ts, noise_std=noise, seed=seed, loads=plc.loads,
                                     speed=speed, host=host, port=port) as many:
            print(f"serving {many.url(1)}" + (f" … {many.url(n)}: {n} loops, loop k on unit id k" if n > 1 else ""),
                  flush=True)
            print(about, flush=True)
            await stop.wait()

    try:
        asyncio.run(serve_one() if loops is None or address is None else serve_many(loops, *address))
    except OSError as exc:  # port in use, no such CAN interface
        bad_input(str(exc))


def _said_mode(t: float, mode: Mode, mv: float) -> None:
    """A simulated PLC's change of mode, on stdout: the device's own record of a hand-over (docs/modbus.md)."""
    print(f"mode {mode.name} at plant t={t:.3f} s, MV {mv:.6g}", flush=True)


def _stop_event(duration: float | None) -> asyncio.Event:
    """An event set on SIGINT, SIGTERM or after ``duration`` wall seconds (None: never); call inside the loop."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    if duration is not None:
        loop.call_later(duration, stop.set)
    return stop


@app.command("jitter")
def jitter_command(
    via: Annotated[Transport, typer.Option(case_sensitive=False, help="Transport to the simulated plant.")]
    = Transport.MODBUS,
    rate: Annotated[float, typer.Option(min=1.0, max=1000.0, help="Sample rate, Hz.")] = 50.0,
    seconds: Annotated[float, typer.Option(min=1.0, max=3600.0, help="Length of the measurement, s.")] = 10.0,
    plant: Annotated[str, typer.Option(help="Process transfer function in s.")] = DEMO_PLANT,
) -> None:
    """Benchmark: sample a simulated plant over a real link as a tuning session does; print the timing."""
    from autotuner.service.remote_tuning import measure_jitter

    process = parse_plant(plant)
    j = asyncio.run(measure_jitter(process, via.value, rate, seconds))
    table = Table(title=f"{j.samples} samples at {rate:g} Hz over {via.value} (localhost)", title_justify="left")
    for name in ("PV read done after due, p50", "p99", "max", "sample interval, p1", "p99"):
        table.add_column(name, justify="right")
    table.add_row(*(f"{x:.2f} ms" for x in (j.late_p50, j.late_p99, j.late_max, j.interval_p1, j.interval_p99)))
    stdout.print(table)
