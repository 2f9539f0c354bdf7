"""Hardware in the loop: tuning a simulated PLC through a real Modbus TCP server and a real CAN bus.

The simulated plant runs in real time (sped up) behind pymodbus's server on
an ephemeral localhost port, or behind a node on a python-can virtual bus;
the session talks to it through the same link code a real device gets.
"""

from __future__ import annotations

import asyncio
import math

import pytest

from autotuner.engine.plant.expression import parse_process
from autotuner.engine.outcome import Code
from autotuner.engine.experiment.relay import RelayConfig
from autotuner.service.remote_tuning import field_config, open_link, served, tune_via
from autotuner.service.link_session import SessionPlan, tune_link
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import default_sample_time, tune
from drivers.link import Mode
from drivers.simplc import SimulatedPlc

PLANT = parse_process("exp(-s)/(2*s+1)")
SPEED = 5.0
TS = default_sample_time(PLANT) * 2  # 50 samples per period: 18 ms of wall time each at SPEED
CONFIG = RelayConfig(amp=5.0, time_limit=600.0)


@pytest.fixture(scope="module")
def direct():
    return tune(PlantSim(PLANT, TS), CONFIG)


@pytest.mark.parametrize("transport", ["modbus", "can"])
def test_same_point_and_gains_as_the_direct_simulation(transport, direct):
    result = asyncio.run(tune_via(PLANT, transport, CONFIG, TS, speed=SPEED))
    assert result.ok, result.message
    point, reference = result.identification.point, direct.identification.point
    assert point.omega == pytest.approx(reference.omega, rel=0.05)
    assert point.gain == pytest.approx(reference.gain, rel=0.05)
    assert abs(point.phase_deg - reference.phase_deg) < 2.0
    assert result.design.gains.k == pytest.approx(direct.design.gains.k, rel=0.1)
    assert result.design.gains.ki == pytest.approx(direct.design.gains.ki, rel=0.1)


@pytest.mark.parametrize(("transport", "size"), [("modbus", 1.0), ("modbus", -1.5), ("can", 1.0)])
def test_a_load_step_during_the_experiment_is_estimated_through(transport, size):
    # 0.2 and −0.3 × amp at the process input, 1.3 periods in (a quiet run ends at 2.2: the model rule), made by
    # the PLC itself. Load following was off over links: the relay took the load's response for its own and K0
    # came out of the wrong sign.
    # At 2× real time (26 ms of wall time per sample). At 5×, with the field benchmark or two CPU burners
    # running besides, the in-process PLC's and the session's timing scattered the estimates after the load
    # (ω ±5 %, |F| ±3 %, phase ±3°) and about one run in three refused with 11 — honest (docs/experiment.md),
    # but not what this test is about.
    result = asyncio.run(tune_via(PLANT, transport, CONFIG, TS / 2.0, speed=2.0, loads=[(7.0, size)]))
    assert result.ok, result.message
    ident = result.identification
    assert ident.disturbance and ident.load_estimate == pytest.approx(size, abs=0.15)
    assert ident.static_gain == pytest.approx(PLANT.static_gain(), rel=0.05)
    true = complex(PLANT.freqresp(ident.point.omega))
    assert abs(ident.point.value - true) / abs(true) < 0.03


async def _faulted(transport: str, inject, heal=None, after: float = 1.0, outage: float = 0.5):
    """Tune through ``transport``; ``inject(plc, server)`` after ``after`` wall seconds, ``heal`` ``outage`` s later."""
    plc = SimulatedPlc(PLANT, ts=TS / 5)
    async with served(plc, transport, SPEED) as (url, server):
        link = open_link(url)
        await link.open()

        async def faults():
            await asyncio.sleep(after)
            await inject(plc, server)
            if heal is not None:
                await asyncio.sleep(outage)
                await heal(plc, server)

        injector = asyncio.create_task(faults())
        try:
            result = await tune_link(link, SessionPlan(field_config(CONFIG), TS, speed=SPEED))
        finally:
            await injector
            await link.close()
        # Read the loop back through the protocol, as an operator's HMI would.
        check = open_link(url)
        await check.open()
        try:
            state = await check.read_state()
            flags = await check.read_flags()
        finally:
            await check.close()
    return result, state, flags, plc


def _restored(state, plc) -> None:
    assert state.mode is Mode.AUTO
    assert plc.mode is Mode.AUTO
    assert math.isfinite(state.mv)


def test_modbus_exception_responses_end_with_link_fault_and_a_restored_loop():
    async def inject(plc, server):
        server.fail_with_exception(True)

    async def heal(plc, server):
        server.fail_with_exception(False)

    result, state, flags, plc = asyncio.run(_faulted("modbus", inject, heal))
    assert result.code is Code.LINK_FAULT
    _restored(state, plc)
    assert flags.te is True and flags.ite == int(Code.LINK_FAULT) and flags.tbsy is False


def test_modbus_nan_pv_is_refused_and_the_loop_restored():
    async def inject(plc, server):
        plc.nan_pv = True

    async def heal(plc, server):
        plc.nan_pv = False

    result, state, _, plc = asyncio.run(_faulted("modbus", inject, heal))
    assert result.code is Code.LINK_FAULT
    assert "pv" in result.message
    _restored(state, plc)


def test_modbus_server_that_stops_and_comes_back():
    from drivers.modbus_server import serve_modbus

    holder = {}

    async def inject(plc, server):
        holder["port"] = server.port
        await server.close()

    async def heal(plc, server):
        holder["server"] = await serve_modbus(plc, "127.0.0.1", holder["port"])

    async def scenario():
        try:
            # Longer than the link's retries (timeout 1 s, 2 retries, reconnecting): a
            # shorter outage is bridged, as it should be.
            return await _faulted("modbus", inject, heal, outage=4.0)
        finally:
            if "server" in holder:
                await holder["server"].close()

    result, state, _, plc = asyncio.run(scenario())
    assert result.code is Code.LINK_FAULT
    _restored(state, plc)


def test_can_node_that_goes_silent():
    async def inject(plc, node):
        node.silent = True

    async def heal(plc, node):
        node.silent = False

    # Longer than the link's 1 s timeout; a shorter silence is bridged.
    result, state, _, plc = asyncio.run(_faulted("can", inject, heal, outage=2.0))
    assert result.code is Code.LINK_FAULT
    _restored(state, plc)


@pytest.mark.parametrize("transport", ["modbus", "can"])
def test_health_reports_the_link_and_its_failures(transport):
    async def scenario():
        plc = SimulatedPlc(PLANT, ts=TS / 5)
        async with served(plc, transport, SPEED) as (url, server):
            link = open_link(url)
            await link.open()
            try:
                await link.read_pv()
                healthy = link.health()
                plc.nan_pv = True
                await asyncio.sleep(0.05)
                with pytest.raises(Exception):
                    await link.read_pv()
                return healthy, link.health()
            finally:
                await link.close()

    healthy, after = asyncio.run(scenario())
    assert healthy["transport"] == transport and healthy["connected"] is True
    assert after["connected"] is True  # a NaN is refused as data; the link itself is fine
