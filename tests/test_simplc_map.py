"""The simulated PLC behind a real pymodbus server conforms to docs/modbus.md: unmapped coils answer exception 2,
only its own unit id answers with data; and no written value can wedge it (extreme but valid gains written over
Modbus, then sane ones: the MV comes off its limit at once instead of staying pinned for minutes)."""

from __future__ import annotations

import asyncio
import math

import pytest
from pymodbus.client import AsyncModbusTcpClient

from autotuner.engine.control.gains import Gains
from autotuner.engine.control.pid import INTEGRAL_SPANS, PidUnit
from autotuner.engine.plant.expression import parse_process
from drivers.modbus_link import ModbusLink
from drivers.modbus_server import serve_modbus
from drivers.simplc import SimulatedPlc

PLANT = "exp(-s)/(2*s+1)"


async def _with_server(body) -> None:
    plc = SimulatedPlc(parse_process(PLANT), ts=0.05)
    server = await serve_modbus(plc, "127.0.0.1", 0)
    client = AsyncModbusTcpClient("127.0.0.1", port=server.port, timeout=2, retries=0)
    await client.connect()
    try:
        await body(plc, server, client)
    finally:
        client.close()
        await server.close()


def test_unmapped_coils_answer_exception_2_and_mapped_ones_work():
    async def body(plc, server, client) -> None:
        for coil in range(4, 16):
            read = await client.read_coils(coil, count=1, device_id=1)
            written = await client.write_coil(coil, True, device_id=1)
            assert read.isError() and read.exception_code == 2, coil
            assert written.isError() and written.exception_code == 2, coil
        many = await client.write_coils(2, [True, True, True], device_id=1)  # 2, 3 mapped; 4 is not
        assert many.isError() and many.exception_code == 2 and plc.flags.tbsy is False
        # Range reads that run into unmapped coils (inside the first 16-bit word and past it) are refused too.
        for first, count in ((0, 5), (3, 2), (2, 8), (0, 16), (0, 17), (15, 2)):
            read = await client.read_coils(first, count=count, device_id=1)
            assert read.isError() and read.exception_code == 2, (first, count)
        assert (await client.read_discrete_inputs(0, count=1, device_id=1)).exception_code == 2  # none mapped
        for first, count in ((0, 4), (1, 3), (3, 1)):
            read = await client.read_coils(first, count=count, device_id=1)
            assert not read.isError() and len(read.bits) >= count, (first, count)
        assert not (await client.read_coils(0, count=4, device_id=1)).isError()
        assert not (await client.write_coil(2, True, device_id=1)).isError() and plc.flags.tbsy is True

    asyncio.run(_with_server(body))


def test_the_simulated_plc_process_refuses_range_reads_into_unmapped_coils(tmp_path):
    """The same on `autotuner sim --modbus` as a process, read by a client of its own."""
    from test_handback import Plc

    plc = Plc(tmp_path)
    try:
        into = plc.client.read_coils(0, count=5, device_id=1)
        assert into.isError() and into.exception_code == 2
        assert not plc.client.read_coils(0, count=4, device_id=1).isError()
    finally:
        plc.close()


def test_only_its_own_unit_id_answers_with_data():
    async def body(plc, server, client) -> None:
        assert not (await client.read_input_registers(0, count=2, device_id=1)).isError()
        for unit in (0, 2, 247):  # exception 11, gateway target device failed to respond (docs/modbus.md)
            assert (await client.read_input_registers(0, count=2, device_id=unit)).exception_code == 11, unit

    asyncio.run(_with_server(body))


def test_extreme_gains_written_over_modbus_do_not_pin_the_mv_after_sane_gains_are_back():
    async def body(plc, server, client) -> None:
        link = ModbusLink.tcp("127.0.0.1", server.port, unit=1, timeout=2.0)
        await link.open()
        try:
            sane = plc.gains
            await link.write_gains(Gains(k=1e38, ti=1e-30))
            plc.sp = 51.0
            for _ in range(200):  # 10 plant seconds under the wild gains: the MV slams to a limit
                plc.tick()
            assert plc.mv in (0.0, 100.0)
            await link.write_gains(sane)
            ticks = 0
            while plc.mv in (0.0, 100.0):
                plc.tick()
                ticks += 1
                assert ticks < 200, "MV still pinned 10 plant seconds after sane gains were written back"
            for _ in range(4000):
                plc.tick()
            assert plc.pv == pytest.approx(51.0, abs=0.05)
        finally:
            await link.close()

    asyncio.run(_with_server(body))


def test_the_pid_units_integral_stays_within_a_span_of_its_finite_limits():
    pid = PidUnit(Gains(k=1e38, ti=1e-30), kind="PI", lolim=0.0, hilim=100.0)
    pid.reset(50.0, 50.0, 50.0)
    for i in range(100):
        pid.step(0.05 * i, 51.0, 50.0)
    band = (-INTEGRAL_SPANS * 100.0, 100.0 + INTEGRAL_SPANS * 100.0)
    assert band[0] <= pid.integral <= band[1] and math.isfinite(pid.integral)
    pid.gains = Gains(k=1.0, ti=5.0)  # the bumpless change cannot push it out of the band either
    assert band[0] <= pid.integral <= band[1]
    free = PidUnit(Gains(k=1.0, ti=5.0), kind="PI")  # no limits: nothing is bounded
    free.reset(0.0, 1.0, 0.0)
    for i in range(10):
        free.step(float(i), 1.0, 0.0)
    assert free.integral == pytest.approx(-1.0 + 9 * 0.2, rel=1e-9)  # reset to -k·(b·sp − pv), then ki·h per step
