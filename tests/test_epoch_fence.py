"""The device-side fence of a fleet (docs/fleet.md): the lease epoch a daemon writes to the device's ``epoch``
register, and the device refusing the writes of a connection whose epoch is older than the newest it was written.

Real parts: the simulated plant's Modbus TCP server (drivers.modbus_server, what ``autotuner sim --loops`` serves),
written by real pymodbus clients, each its own TCP connection, and by the project's own link (drivers.modbus_link).
"""

from __future__ import annotations

import asyncio

import pytest
from pymodbus.client import AsyncModbusTcpClient

from autotuner.engine.plant.expression import parse_process
from drivers.link import Fenced, LinkError, Mode, TuneFlags
from drivers.modbus_link import ModbusLink
from drivers.modbus_map import DEFAULT_MAP, ModbusMap
from drivers.modbus_plant import serve_plant

PLANT = "exp(-0.5*s)/(s+1)"
BOUND = 30.0  # no test may take longer than this, whatever happens
ILLEGAL_VALUE, DEVICE_FAILURE = 3, 4  # Modbus exception codes


def arun(coro):
    """Run ``coro`` with an overall bound (a hang is a failure, not a stuck suite)."""
    async def bounded():
        return await asyncio.wait_for(coro, BOUND)
    return asyncio.run(bounded())


async def client_of(port: int) -> AsyncModbusTcpClient:
    """A pymodbus client with a connection of its own."""
    client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=2, retries=0)
    assert await client.connect()
    return client


async def write(client: AsyncModbusTcpClient, unit: int, signal: str, value: float) -> int:
    """Write ``signal`` (a register signal) with FC 16; 0 when accepted, else the exception code."""
    reg = DEFAULT_MAP[signal]
    r = await client.write_registers(reg.address, DEFAULT_MAP.encode(signal, value), device_id=unit)
    return r.exception_code if r.isError() else 0


async def read(client: AsyncModbusTcpClient, unit: int, signal: str) -> float:
    reg = DEFAULT_MAP[signal]
    r = await client.read_holding_registers(reg.address, count=reg.size, device_id=unit)
    assert not r.isError(), (unit, signal, r)
    return DEFAULT_MAP.decode(signal, r.registers)


async def refusal(response_of: object) -> int:
    r = await response_of  # type: ignore[misc]
    return r.exception_code if r.isError() else 0


def test_a_connection_superseded_by_a_newer_epoch_writes_nothing_more():
    async def main():
        async with await serve_plant(2, parse_process(PLANT), ts=0.02) as plant:
            plc = plant.plcs[0]
            a, b, c = [await client_of(plant.port) for _ in range(3)]  # c: an HMI, never writes an epoch
            try:
                assert plc.epoch == 0 and await read(c, 1, "epoch") == 0.0  # nothing written since the start
                assert await write(a, 1, "epoch", 5) == 0
                assert await write(a, 1, "hv", 60.0) == 0 and await write(a, 1, "mode", float(Mode.MAN)) == 0
                assert await write(b, 1, "epoch", 6) == 0  # the lease taken over: B's epoch is the newest
                assert await read(c, 1, "epoch") == 6.0 and plc.epoch == 6
                # Every write function of A's is refused now (exception 4), and changes nothing.
                tbsy = DEFAULT_MAP["tbsy"].address
                mode = DEFAULT_MAP["mode"].address
                refused = [await write(a, 1, "hv", 70.0), await write(a, 1, "mode", float(Mode.AUTO)),
                           await refusal(a.write_register(mode, int(Mode.AUTO), device_id=1)),  # FC 6
                           await refusal(a.write_coil(tbsy, True, device_id=1)),  # FC 5
                           await refusal(a.write_coils(tbsy, [True, True], device_id=1))]  # FC 15
                assert refused == [DEVICE_FAILURE] * 5
                assert await read(c, 1, "hv") == 60.0 and await read(c, 1, "mode") == float(Mode.MAN)
                assert not plc.flags.tbsy and not plc.flags.te
                # An older epoch is refused as a value (exception 3), and the newest stays.
                assert await write(a, 1, "epoch", 4) == ILLEGAL_VALUE
                assert await read(c, 1, "epoch") == 6.0
                assert plc.fenced == 6
                # B, the owner now, writes; so does the HMI that never wrote an epoch; A reads as before.
                assert await write(b, 1, "hv", 65.0) == 0 and await write(c, 1, "sp", 45.0) == 0
                assert await read(a, 1, "hv") == 65.0 and plc.sp == 45.0
                # The fence is per unit: A never wrote an epoch to unit 2.
                assert await write(a, 2, "hv", 30.0) == 0 and plant.plcs[1].hv == 30.0
                # A daemon that takes the lease again writes a newer epoch still: it writes, B is fenced.
                assert await write(a, 1, "epoch", 7) == 0 and await write(a, 1, "hv", 55.0) == 0
                assert await write(b, 1, "hv", 66.0) == DEVICE_FAILURE and await read(c, 1, "hv") == 55.0
            finally:
                for client in (a, b, c):
                    client.close()
    arun(main())


def test_a_new_connection_of_a_fenced_daemon_is_fenced_again_by_its_epoch():
    """A connection is fenced by the epoch it writes: a daemon that reconnects writes its epoch first (the link
    does), and that write is refused — the device cannot tell the new connection from an HMI otherwise."""
    async def main():
        async with await serve_plant(1, parse_process(PLANT), ts=0.02) as plant:
            a, b = await client_of(plant.port), await client_of(plant.port)
            try:
                assert await write(b, 1, "epoch", 3) == 0
                a.close()
                a = await client_of(plant.port)
                assert await write(a, 1, "epoch", 2) == ILLEGAL_VALUE
                assert await write(a, 1, "hv", 10.0) == DEVICE_FAILURE
                assert plant.plcs[0].hv != 10.0
            finally:
                a.close()
                b.close()
    arun(main())


def test_the_link_writes_its_epoch_before_its_first_write_and_with_the_heartbeat():
    async def main():
        async with await serve_plant(1, parse_process(PLANT), ts=0.02) as plant:
            plc = plant.plcs[0]
            link = ModbusLink.tcp("127.0.0.1", plant.port, 1, pipeline=4)
            await link.open()
            try:
                await link.read_pv()
                assert plc.epoch == 0  # a read carries no epoch
                link.epoch = 5
                await link.write_mv(42.0)
                assert plc.epoch == 5 and plc.hv == 42.0
                before = link.requests
                await link.write_mv(43.0)
                assert link.requests == before + 1  # once per connection and epoch, not before every write
                plc.epoch = 0  # (as if the device had forgotten it without a new connection)
                await link.write_heartbeat(7)
                assert plc.heartbeat == 7 and plc.epoch == 5  # the epoch goes with every heartbeat
            finally:
                await link.close()
    arun(main())


def test_the_link_fenced_by_the_device_raises_fenced_naming_both_epochs():
    async def main():
        async with await serve_plant(1, parse_process(PLANT), ts=0.02) as plant:
            plc = plant.plcs[0]
            link = ModbusLink.tcp("127.0.0.1", plant.port, 1)
            link.epoch = 5
            other = await client_of(plant.port)
            await link.open()
            try:
                await link.write_mv(42.0)
                assert await write(other, 1, "epoch", 6) == 0
                with pytest.raises(Fenced, match="lease epoch 6, newer than this daemon.s epoch 5"):
                    await link.write_mode(Mode.MAN)
                with pytest.raises(Fenced, match="lease epoch 6, newer than this daemon.s epoch 5"):
                    await link.write_flags(TuneFlags(tbsy=True))
                assert plc.mode is Mode.AUTO and not plc.flags.tbsy and plc.hv != 0.0
                # A new connection writes the epoch first, and is fenced by it.
                await link.close()
                await link.open()
                with pytest.raises(Fenced, match="lease epoch 6, newer than this daemon.s epoch 5"):
                    await link.write_mv(10.0)
                assert plc.hv != 10.0
                # Another exception to a writer whose epoch is the device's is no fence: a LinkError as before.
                plant.servers[0].fail_with_exception(True, writes=True)
                link.epoch = 6
                with pytest.raises(LinkError, match="exception 4") as refused:
                    await link.write_mv(11.0)
                assert not isinstance(refused.value, Fenced)
            finally:
                await link.close()
                other.close()
    arun(main())


def test_without_an_epoch_or_an_epoch_register_the_link_writes_none():
    async def main():
        without = ModbusMap({n: r for n, r in DEFAULT_MAP.registers.items() if n != "epoch"})
        async with await serve_plant(1, parse_process(PLANT), ts=0.02) as plant:
            plc = plant.plcs[0]
            plain = ModbusLink.tcp("127.0.0.1", plant.port, 1)  # no fleet: no epoch
            custom = ModbusLink.tcp("127.0.0.1", plant.port, 1, map=without)
            custom.epoch = 9  # a fleet's daemon, a map without the register: no device-side fence
            assert plain.carries_epoch and not custom.carries_epoch
            try:
                await plain.write_mv(20.0)
                await plain.write_heartbeat(1)
                await custom.write_mv(21.0)
                await custom.write_heartbeat(2)
                assert plc.epoch == 0 and plc.hv == 21.0 and plc.heartbeat == 2
            finally:
                await plain.close()
                await custom.close()
    arun(main())
