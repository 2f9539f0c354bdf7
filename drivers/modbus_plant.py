"""A simulated plant of many loops in one process: N simulated PLCs behind Modbus TCP, one unit id each.

Loop k (1 ≤ k ≤ N) is a :class:`~drivers.simplc.SimulatedPlc` of the same
process, sample time, noise level and load steps, served with the default
map (docs/modbus.md). Up to :data:`UNITS_PER_SERVER` (247, the Modbus unit
ids 1..247) loops share one TCP server: loop k answers on unit id k. Beyond
that, loop k is on server ``(k − 1) // 247`` at unit id ``(k − 1) % 247 + 1``;
the servers listen on ``port``, ``port + 1``, … (or each on an ephemeral port
when ``port`` is 0). Loop k's noise is seeded with ``seed + k − 1``, so the
loops differ and loop 1 is the PLC a single ``autotuner sim`` serves.

It is cheap: one asyncio task ticks every loop (:func:`drivers.simplc.run_many`,
one timer whatever N), and the servers compute a register only when a request
asks for it. This is what ``autotuner sim --loops N`` runs, and what a load
benchmark or a test calls in-process (:func:`serve_plant`).
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass

from autotuner.engine.plant.process import Process

from .modbus_server import ModbusPlcServer, serve_units
from .simplc import SimulatedPlc, run_many

__all__ = ["UNITS_PER_SERVER", "ModbusPlant", "serve_plant"]

#: Loops per TCP server: the Modbus unit ids 1..247 (0 is broadcast, 248..255 reserved).
UNITS_PER_SERVER = 247


@dataclass
class ModbusPlant:
    """A running plant: ``plcs[k − 1]`` is loop k, ``servers`` the Modbus servers in front of them; use
    :func:`serve_plant` to start one and :meth:`close` to stop it."""

    plcs: list[SimulatedPlc]
    servers: list[ModbusPlcServer]
    host: str
    _halt: asyncio.Event
    _ticking: asyncio.Task[None]

    @property
    def port(self) -> int:
        """The port of the first server (the only one up to 247 loops)."""
        return self.servers[0].port

    def address(self, k: int) -> tuple[int, int]:
        """(port, unit id) of loop ``k`` (1-based); IndexError outside 1..N."""
        if not 1 <= k <= len(self.plcs):
            raise IndexError(f"loop {k} is not in this plant of {len(self.plcs)} loops (1..{len(self.plcs)})")
        server, unit = divmod(k - 1, UNITS_PER_SERVER)
        return self.servers[server].port, unit + 1

    def url(self, k: int) -> str:
        """The link URL of loop ``k`` (1-based), e.g. ``modbus://127.0.0.1:5020/3``."""
        port, unit = self.address(k)
        return f"modbus://{self.host}:{port}/{unit}"

    async def close(self) -> None:
        """Stop serving (clients are disconnected) and stop ticking; idempotent."""
        for server in self.servers:
            await server.close()
        self._halt.set()
        await self._ticking

    async def __aenter__(self) -> "ModbusPlant":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


async def serve_plant(n: int, process: Process, *, ts: float = 0.0, noise_std: float = 0.0, seed: int = 0,
                      loads: tuple[tuple[float, float], ...] = (), speed: float = 1.0, host: str = "127.0.0.1",
                      port: int = 0) -> ModbusPlant:
    """Serve ``n`` simulated loops of ``process`` over Modbus TCP at ``host:port`` (module docstring).

    ``ts``: the PLCs' sample time, plant seconds (0: :class:`~drivers.simplc.SimulatedPlc`'s default);
    ``noise_std``: measurement noise, PV units, loop k seeded ``seed + k − 1``; ``loads``: (T plant seconds after
    a tuner takes the loop over, SIZE MV units) load steps of every loop; ``speed``: plant seconds per wall
    second; ``port`` 0: ephemeral ports (``.port``, :meth:`ModbusPlant.address`). ValueError for ``n < 1`` or a
    bad load step; OSError if a port cannot be bound (nothing is left running then).
    """
    if n < 1:
        raise ValueError(f"a plant has at least one loop, got {n}")
    plcs = [SimulatedPlc(process, ts=ts, noise_std=noise_std, seed=seed + k, loads=loads) for k in range(n)]
    halt = asyncio.Event()
    plant = ModbusPlant(plcs, [], host, halt, asyncio.create_task(run_many(plcs, speed, halt)))
    try:
        for first in range(0, n, UNITS_PER_SERVER):
            units = {unit: plc for unit, plc in enumerate(plcs[first:first + UNITS_PER_SERVER], start=1)}
            plant.servers.append(await serve_units(units, host, port + first // UNITS_PER_SERVER if port else 0))
    except BaseException:
        await plant.close()
        raise
    return plant
