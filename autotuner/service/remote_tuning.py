"""Tuning through a field link: a device at a URL, or a simulated plant behind a real protocol stack.

``modbus://HOST:PORT[/UNIT]`` and ``can://INTERFACE/CHANNEL`` name a loop;
:func:`open_link` makes its link, :func:`tune_opened` opens it and runs a session
on it (:func:`~autotuner.service.link_session.tune_link`). :func:`tune_via` serves a simulated
plant (a process under a PID unit) over a real in-process Modbus TCP server
on an ephemeral localhost port or on a python-can virtual bus, and tunes it
through the same link code — the self-test of an installation.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from drivers.link import Link, LinkError
from drivers.simplc import SimulatedPlc, run

from autotuner.engine.plant.process import Process
from autotuner.engine.outcome import MESSAGES, Code
from autotuner.engine.experiment.relay import RelayConfig, Status
from autotuner.service.link_session import SessionHooks, SessionPlan, deadlines, tune_link
from autotuner.engine.result import TuneResult

# Sampling a PLC through a link scatters the per-period estimates by about
# ±0.5°, ±0.4 % and ±0.03 in |F|/K0 (the PLC's clock and the session's are
# independent): acceptance tolerances for field experiments.
FIELD_PHASE_TOL = 1.0
FIELD_GAIN_TOL = 0.01
FIELD_STATIC_TOL = 0.05
# Scattered estimates are averaged over more periods before they settle.
FIELD_MAX_PERIODS = 40
# The simulated plant behind a link ticks this many times per session sample,
# so its own sampling adds little delay to what the session sees.
PLANT_TICKS_PER_SAMPLE = 5
# Longest experiment on a real loop, s, unless asked otherwise.
LINK_TIME_LIMIT = 7200.0
# A sample every this many wall seconds is what an asyncio loop keeps without much jitter.
VIA_WALL_PER_SAMPLE = 0.01
VIA_MAX_SPEED = 20.0


def default_via_speed(ts: float) -> float:
    """Plant seconds per wall second for a simulated plant behind a link sampled every ``ts`` plant seconds:
    ``VIA_WALL_PER_SAMPLE`` of wall time per sample, at most ``VIA_MAX_SPEED``."""
    return min(VIA_MAX_SPEED, ts / VIA_WALL_PER_SAMPLE)


def field_config(config: RelayConfig) -> RelayConfig:
    """``config`` with the field tolerances (unless it is already looser)."""
    return replace(
        config,
        phase_tol_deg=max(config.phase_tol_deg, FIELD_PHASE_TOL),
        gain_tol=max(config.gain_tol, FIELD_GAIN_TOL),
        static_tol=max(config.static_tol, FIELD_STATIC_TOL),
        max_periods=max(config.max_periods, FIELD_MAX_PERIODS),
    )


def open_link(url: str, map_path: str | None = None, dbc_path: str | None = None) -> Link:
    """The link for ``url`` (``modbus://…`` or ``can://…``); ValueError for anything else."""
    if url.startswith(("modbus://", "modbus+tcp://", "modbus+rtu://")):
        from drivers.modbus_link import ModbusLink

        return ModbusLink.from_url(url, map_path=map_path)
    if url.startswith("can://"):
        from drivers.can_link import CanLink

        return CanLink.from_url(url, dbc=dbc_path)
    raise ValueError(
        f"unknown link {url!r}: use modbus://HOST:PORT[/UNIT], modbus+rtu:///dev/ttyUSB0?baudrate=… "
        "or can://INTERFACE/CHANNEL"
    )


async def tune_opened(link: Link, controller: str, session: Callable[[Link], Awaitable[TuneResult]]) -> TuneResult:
    """Open ``link``, run ``session`` on it (a :func:`~autotuner.service.link_session.tune_link` call), close it;
    code 7 naming why if it cannot open (``controller``: the one the failed result names)."""
    try:
        await link.open()
    except LinkError as exc:
        return TuneResult.failed(Code.LINK_FAULT, f"{MESSAGES[Code.LINK_FAULT]}: {exc}", controller)
    try:
        return await session(link)
    finally:
        await link.close()


@contextlib.asynccontextmanager
async def serving(
    plc: SimulatedPlc, speed: float, modbus: tuple[str, int] | None = None, can: tuple[str, str] | None = None,
    can_options: dict[str, int] | None = None,
) -> AsyncIterator[list[tuple[str, Any]]]:
    """Run ``plc`` (``speed`` × real time) behind a Modbus TCP server at ``modbus`` (HOST, PORT; port 0: any free
    one) and/or a CAN node on ``can`` (INTERFACE, CHANNEL; ``can_options``: python-can bus options a CAN link URL
    carries too, e.g. ``port`` and ``hop_limit`` of ``udp_multicast``); yields the URL of a link to each (with
    those options) and its server.

    The one way to serve a simulated PLC: ``autotuner sim``, ``tune --via``, the jitter benchmark and the tests.
    """
    halt = asyncio.Event()
    plant = asyncio.create_task(run(plc, speed, halt))
    servers: list[tuple[str, Any]] = []
    try:
        if modbus is not None:
            from drivers.modbus_server import serve_modbus

            server = await serve_modbus(plc, modbus[0], modbus[1])
            servers.append((f"modbus://{modbus[0]}:{server.port}/1", server))
        if can is not None:
            from drivers.can_node import serve_can

            options = can_options or {}
            server = await serve_can(plc, can[0], can[1], period=plc.ts / speed, **options)
            query = "&".join(f"{k}={v}" for k, v in options.items())
            servers.append((f"can://{can[0]}/{can[1]}" + (f"?{query}" if query else ""), server))
        yield servers
    finally:
        for _, server in servers:
            await server.close()
        halt.set()
        await plant


@contextlib.asynccontextmanager
async def served(plc: SimulatedPlc, transport: str, speed: float) -> AsyncIterator[tuple[str, Any]]:
    """Run ``plc`` (``speed`` × real time) behind a server on this machine only (a free localhost port, or a
    fresh CAN virtual channel); yields the URL of the link to it and the server."""
    if transport == "modbus":
        where: dict[str, Any] = {"modbus": ("127.0.0.1", 0)}
    elif transport == "can":
        where = {"can": ("virtual", f"autotuner-{os.getpid()}-{id(plc)}")}
    else:
        raise ValueError(f"unknown transport {transport!r}: modbus or can")
    async with serving(plc, speed, **where) as servers:
        yield servers[0]


async def tune_via(
    process: Process,
    transport: str,
    config: RelayConfig,
    ts: float,
    controller: str = "PI",
    ms: float = 1.4,
    speed: float = 20.0,
    noise: float = 0.0,
    seed: int = 0,
    on_status: Callable[[Status], None] | None = None,
    loads: Sequence[tuple[float, float]] = (),
) -> TuneResult:
    """Serve ``process`` over ``transport`` ("modbus" or "can") and tune it through the real link.

    ``loads``: (T, SIZE) load steps at the process input (plant seconds after the session takes the loop,
    MV units), made by the simulated PLC.
    """
    plc = SimulatedPlc(process, ts=ts / PLANT_TICKS_PER_SAMPLE, noise_std=noise, seed=seed, loads=tuple(loads))
    async with served(plc, transport, speed) as (url, _):
        plan = SessionPlan(field_config(config), ts, controller, ms, speed=speed)
        return await tune_opened(open_link(url), controller,
                                 lambda link: tune_link(link, plan, SessionHooks(on_status=on_status)))


@dataclass(frozen=True)
class Jitter:
    """Lateness of the samples behind their due times, and the sample intervals, in milliseconds."""

    samples: int
    late_p50: float
    late_p99: float
    late_max: float
    interval_p1: float
    interval_p99: float


async def measure_jitter(process: Process, transport: str, rate: float = 50.0, seconds: float = 10.0) -> Jitter:
    """Sample a simulated plant over ``transport`` at ``rate`` Hz as a tuning session does (read PV, write MV).

    The plant runs in real time behind a real server in this process; what is
    measured is when each PV read completed against its due time.
    """
    plc = SimulatedPlc(process, ts=1.0 / rate / PLANT_TICKS_PER_SAMPLE)
    done: list[float] = []
    late: list[float] = []
    async with served(plc, transport, 1.0) as (url, _):
        link = open_link(url)
        await link.open()
        try:
            async for due in deadlines(1.0 / rate):
                await link.read_pv()
                now = time.monotonic()
                await link.write_mv(plc.mv0)
                late.append(now - due)
                done.append(now)
                if len(done) >= rate * seconds:
                    break
        finally:
            await link.close()
    lateness = 1e3 * np.asarray(late)
    intervals = 1e3 * np.diff(done)
    return Jitter(len(done), *np.percentile(lateness, [50, 99]), float(lateness.max()),
                  *np.percentile(intervals, [1, 99]))
