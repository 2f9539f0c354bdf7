"""A simulated plant of many loops behind one Modbus TCP server (drivers.modbus_plant, ``autotuner sim --loops``),
read and written with the real pymodbus client: every unit id is its own PLC, an unknown one answers exception 11.
"""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time

import pytest
from pymodbus.client import AsyncModbusTcpClient, ModbusTcpClient

from autotuner.cli.field import MAX_LOOPS
from autotuner.engine.plant.expression import parse_process
from drivers.link import Mode
from drivers.modbus_map import DEFAULT_MAP
from drivers.modbus_plant import UNITS_PER_SERVER, serve_plant
from drivers.simplc import SimulatedPlc, run_many

from helpers import free_port

PLANT = "exp(-0.5*s)/(s+1)"
BOUND = 30.0  # no test may take longer than this, whatever happens
GATEWAY_NO_RESPONSE = 11  # Modbus exception 0x0B: gateway target device failed to respond


def arun(coro):
    """Run ``coro`` with an overall bound (a hang is a failure, not a stuck suite)."""
    async def bounded():
        return await asyncio.wait_for(coro, BOUND)
    return asyncio.run(bounded())


async def read(client: AsyncModbusTcpClient, unit: int, signal: str) -> float:
    reg = DEFAULT_MAP[signal]
    if reg.table == "input":
        r = await client.read_input_registers(reg.address, count=reg.size, device_id=unit)
    else:
        r = await client.read_holding_registers(reg.address, count=reg.size, device_id=unit)
    assert not r.isError(), (unit, signal, r)
    return DEFAULT_MAP.decode(signal, r.registers)


async def write(client: AsyncModbusTcpClient, unit: int, signal: str, value: float) -> None:
    reg = DEFAULT_MAP[signal]
    r = await client.write_registers(reg.address, DEFAULT_MAP.encode(signal, value), device_id=unit)
    assert not r.isError(), (unit, signal, r)


def test_units_are_separate_plcs_read_and_written_independently():
    async def main():
        async with await serve_plant(3, parse_process(PLANT), ts=0.02, speed=5.0) as plant:
            assert [plant.url(k) for k in (1, 3)] == [f"modbus://127.0.0.1:{plant.port}/1",
                                                    f"modbus://127.0.0.1:{plant.port}/3"]
            client = AsyncModbusTcpClient("127.0.0.1", port=plant.port, timeout=2, retries=0)
            await client.connect()
            try:
                # Each unit serves its own PLC: give them different set points and read them back.
                for unit, sp in ((1, 40.0), (2, 50.0), (3, 60.0)):
                    await write(client, unit, "sp", sp)
                assert [plc.sp for plc in plant.plcs] == [40.0, 50.0, 60.0]
                assert [await read(client, unit, "sp") for unit in (1, 2, 3)] == [40.0, 50.0, 60.0]
                # Unit 2 to MAN at MV 80: unit 2 only.
                await write(client, 2, "hv", 80.0)
                await write(client, 2, "mode", float(Mode.MAN))
                assert [await read(client, unit, "mode") for unit in (1, 2, 3)] == [1.0, 0.0, 1.0]
                assert [plc.mode for plc in plant.plcs] == [Mode.AUTO, Mode.MAN, Mode.AUTO]
                deadline = time.monotonic() + 20.0
                while await read(client, 2, "mv") != 80.0:  # the PLC applies it on its next tick
                    assert time.monotonic() < deadline, "unit 2 never applied its manual MV"
                    await asyncio.sleep(0.02)
                assert plant.plcs[1].mv == 80.0 and plant.plcs[1].hv == 80.0
                assert plant.plcs[0].hv != 80.0 and plant.plcs[2].hv != 80.0
                # The PVs move apart as each loop follows its own set point (AUTO) or its MV (MAN).
                deadline = time.monotonic() + 20.0
                while True:
                    pvs = [await read(client, unit, "pv") for unit in (1, 2, 3)]
                    if pvs[0] < 45.0 and pvs[1] > 55.0 and pvs[2] > 55.0:
                        break
                    assert time.monotonic() < deadline, f"the loops did not follow their own set points: {pvs}"
                    await asyncio.sleep(0.05)
                for unit, plc in zip((1, 2, 3), plant.plcs):
                    assert await read(client, unit, "pv") == pytest.approx(plc.pv, abs=0.5)
            finally:
                client.close()
    arun(main())


def test_unknown_units_answer_exception_11_and_change_nothing():
    async def main():
        async with await serve_plant(2, parse_process(PLANT), ts=0.02) as plant:
            client = AsyncModbusTcpClient("127.0.0.1", port=plant.port, timeout=2, retries=0)
            await client.connect()
            try:
                for unit in (0, 3, 247):
                    r = await client.read_input_registers(0, count=2, device_id=unit)
                    w = await client.write_register(DEFAULT_MAP["mode"].address, 0, device_id=unit)
                    c = await client.write_coil(2, True, device_id=unit)
                    assert [x.exception_code for x in (r, w, c) if x.isError()] == [GATEWAY_NO_RESPONSE] * 3, unit
                assert [plc.mode for plc in plant.plcs] == [Mode.AUTO, Mode.AUTO]
                assert not any(plc.flags.tbsy for plc in plant.plcs)
                assert await read(client, 2, "mode") == 1.0  # the connection still serves the known units
            finally:
                client.close()
    arun(main())


def test_noise_is_seeded_per_loop_and_loop_1_is_the_single_plc():
    async def main():
        process = parse_process(PLANT)
        async with await serve_plant(3, process, ts=0.02, noise_std=0.5, seed=7) as plant:
            assert [plc.seed for plc in plant.plcs] == [7, 8, 9]
            alone = SimulatedPlc(process, ts=0.02, noise_std=0.5, seed=7)  # what `autotuner sim --seed 7` serves
            assert plant.plcs[0].pv == alone.pv
            assert len({plc.pv for plc in plant.plcs}) == 3  # three draws, not one
    arun(main())


def test_more_loops_than_unit_ids_take_further_servers():
    async def main():
        n = UNITS_PER_SERVER + 3
        async with await serve_plant(n, parse_process(PLANT), ts=0.02) as plant:
            assert len(plant.servers) == 2 and len(plant.plcs) == n
            assert plant.address(UNITS_PER_SERVER) == (plant.servers[0].port, UNITS_PER_SERVER)
            assert plant.address(UNITS_PER_SERVER + 1) == (plant.servers[1].port, 1)
            with pytest.raises(IndexError, match="loop 0"):
                plant.address(0)
            plant.plcs[UNITS_PER_SERVER].sp = 42.0  # loop 248: the second server's unit 1
            client = AsyncModbusTcpClient("127.0.0.1", port=plant.servers[1].port, timeout=2, retries=0)
            await client.connect()
            try:
                assert await read(client, 1, "sp") == 42.0
                assert (await client.read_input_registers(0, count=2, device_id=4)).exception_code == 11
            finally:
                client.close()
    arun(main())


def test_one_task_ticks_every_loop_in_step():
    async def main():
        process = parse_process(PLANT)
        plcs = [SimulatedPlc(process, ts=0.01) for _ in range(5)]
        halt = asyncio.Event()
        task = asyncio.create_task(run_many(plcs, 10.0, halt))
        while plcs[-1].t < 1.0:
            await asyncio.sleep(0.01)
        halt.set()
        await task
        assert len({plc.t for plc in plcs}) == 1  # no other task ran between their ticks
        with pytest.raises(ValueError, match="one sample time"):
            await run_many([plcs[0], SimulatedPlc(process, ts=0.02)])
        with pytest.raises(ValueError, match="one sample time"):
            await run_many([])
    arun(main())


def test_bad_plant_size_is_a_value_error():
    with pytest.raises(ValueError, match="at least one loop"):
        arun(serve_plant(0, parse_process(PLANT)))


# -- the command ---------------------------------------------------------------------------------

def _sim(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "autotuner.cli", "sim", *args], capture_output=True, text=True,
                          timeout=timeout, env={**os.environ, "COLUMNS": "200"})


@pytest.mark.parametrize("loops", ["0", "248", "-1"])
def test_loops_out_of_range_exit_2_naming_the_option(loops):
    done = _sim("--loops", loops, "--modbus", "127.0.0.1:1")
    assert done.returncode == 2
    assert "--loops" in done.stderr and "Traceback" not in done.stderr
    assert MAX_LOOPS == UNITS_PER_SERVER == 247


@pytest.mark.parametrize("args", [["--can", "vcan0"], ["--can", "vcan0", "--modbus", "127.0.0.1:1"]])
def test_loops_over_can_is_refused_clearly(args):
    done = _sim("--loops", "2", *args)
    assert done.returncode == 2
    assert "--loops serves its loops over Modbus TCP only" in done.stderr and "Traceback" not in done.stderr


def test_sim_help_names_loops():
    done = _sim("--help")
    assert done.returncode == 0 and "--loops" in done.stdout and "unit id k" in done.stdout


def test_the_sim_command_serves_every_loop_on_its_unit_id(tmp_path):
    port = free_port()
    log = tmp_path / "sim.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "autotuner.cli", "sim", "--loops", "4", "--modbus",
                                 f"127.0.0.1:{port}", "--plant", PLANT, "--ts", "0.02", "--noise", "0.2"],
                                stdout=out, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 60.0
        while "serving" not in log.read_text() and proc.poll() is None:
            assert time.monotonic() < deadline, "the plant did not serve within 60 s"
            time.sleep(0.05)
        assert proc.poll() is None, log.read_text()
        assert f"serving modbus://127.0.0.1:{port}/1 … modbus://127.0.0.1:{port}/4: 4 loops" in log.read_text()
        client = ModbusTcpClient("127.0.0.1", port=port, timeout=2.0, retries=0)
        assert client.connect()
        try:
            pv = DEFAULT_MAP["pv"]
            reads = {unit: client.read_input_registers(pv.address, count=pv.size, device_id=unit)
                     for unit in range(0, 6)}
            assert [unit for unit, r in reads.items() if not r.isError()] == [1, 2, 3, 4]
            assert reads[0].exception_code == reads[5].exception_code == GATEWAY_NO_RESPONSE
            pvs = [DEFAULT_MAP.decode("pv", reads[unit].registers) for unit in (1, 2, 3, 4)]
            assert len(set(pvs)) == 4 and all(abs(p - 50.0) < 3.0 for p in pvs)  # noisy, each its own draw
            mode = DEFAULT_MAP["mode"]
            assert not client.write_register(mode.address, 0, device_id=2).isError()
            modes = [client.read_holding_registers(mode.address, count=1, device_id=u).registers[0] for u in (1, 2, 3)]
            assert modes == [1, 0, 1]
        finally:
            client.close()
    finally:
        proc.terminate()
        proc.wait(30)
    assert proc.returncode == 0, log.read_text()


def test_the_cpu_benchmark_measures_a_plant_in_a_process_of_its_own():
    from autotuner.benchmarks.plant_cpu import markdown, measure

    row = asyncio.run(measure(3, 0.05, read_period=0.2, seconds=1.0))
    assert (row.loops, row.ts, row.read_period) == (3, 0.05, 0.2)
    assert row.cpu > 0.0  # the child ticked (no bound on how much: the machine is shared)
    assert row.reads_per_s > 0.0  # every read answered without error, or measure raised
    assert markdown([row]).splitlines()[-1].startswith("| 3 | 0.05 | every loop every 0.2 s |")
