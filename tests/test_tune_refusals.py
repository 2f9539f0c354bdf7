"""TUNE refused on a fresh read, before the loop is touched: the PV outside its limits, NaN, stale (CAN), the link
failing, or the device already showing TBSY. Real pymodbus server and python-can virtual bus; the PLC's mode, manual
MV and flags are checked unchanged, and nothing is recorded in the history."""

from __future__ import annotations

import asyncio
import os
from collections.abc import Callable

import pytest

from autotuner.engine.outcome import Code
from autotuner.service.config import DaemonConfig, TuneRequest
from autotuner.service.daemon import LoopManager, Refused
from autotuner.service.history import History
from drivers.can_node import serve_can
from drivers.link import Mode, TuneFlags
from drivers.modbus_server import ModbusPlcServer, serve_modbus
from drivers.simplc import SimulatedPlc
from autotuner.engine.plant.expression import parse_process
from helpers import until

PLANT = "exp(-s)/(2*s+1)"


def _manager(link: str, **extra) -> LoopManager:
    config = DaemonConfig.model_validate({"history": ":memory:", "loops": [
        {"id": "L", "link": link, "ts": 0.2, "limits": {"pv": [0.0, 100.0], "mv": [0.0, 100.0]}, **extra}]})
    return LoopManager(config, History(":memory:"))


def _untouched(plc: SimulatedPlc, m: LoopManager, flags: TuneFlags) -> None:
    assert plc.mode is Mode.AUTO and plc.hv == plc.mv0 and plc.flags == flags
    assert m.history.of_loop("L") == [] and not m.loops["L"].busy


async def _refused_over_modbus(fault: Callable[[SimulatedPlc, ModbusPlcServer], None], code: str, ite: Code,
                               **extra) -> str:
    plc = SimulatedPlc(parse_process(PLANT), ts=0.05)
    server = await serve_modbus(plc, "127.0.0.1", 0, unit=1)
    try:
        m = _manager(f"modbus://127.0.0.1:{server.port}/1?timeout=0.5&retries=0", **extra)
        fault(plc, server)
        flags = plc.flags
        with pytest.raises(Refused) as refused:
            await m.request_tune("L", TuneRequest(), "alice")
        assert refused.value.code == code and refused.value.ite is ite
        _untouched(plc, m, flags)
        return refused.value.message
    finally:
        await server.close()


@pytest.mark.parametrize("fault, extra, code, ite, says", [
    (lambda plc, server: None, {"limits": {"pv": [60.0, 100.0]}}, "pv_out_of_limits", Code.REFUSED_PV_LIMITS,
     "PV 50 is outside its limits [60, 100]"),
    (lambda plc, server: setattr(plc, "nan_pv", True), {}, "pv_invalid", Code.REFUSED_BAD_PV, "pv is not a number"),
    (lambda plc, server: server.fail_with_exception(True), {}, "link_unhealthy", Code.REFUSED_LINK, "exception"),
    (lambda plc, server: setattr(plc, "flags", TuneFlags(tbsy=True)), {}, "device_busy", Code.REFUSED_DEVICE_BUSY,
     "already shows TBSY"),
])
def test_tune_is_refused_on_a_fresh_modbus_read_and_the_loop_is_untouched(fault, extra, code, ite, says):
    assert says in asyncio.run(_refused_over_modbus(fault, code, ite, **extra))


def test_tune_on_an_offline_modbus_device_is_refused_as_an_unhealthy_link():
    async def scenario() -> None:
        server = await serve_modbus(SimulatedPlc(parse_process(PLANT), ts=0.05), "127.0.0.1", 0, unit=1)
        port = server.port
        await server.close()
        m = _manager(f"modbus://127.0.0.1:{port}/1?timeout=0.5&retries=0")
        with pytest.raises(Refused) as refused:
            await m.request_tune("L", TuneRequest(), "alice")
        assert refused.value.code == "link_unhealthy" and m.history.of_loop("L") == []

    asyncio.run(scenario())


def test_tune_on_a_silent_can_node_is_refused_as_a_stale_pv():
    async def scenario() -> None:
        plc = SimulatedPlc(parse_process(PLANT), ts=0.05)
        channel = f"refusal-{os.getpid()}"
        node = await serve_can(plc, "virtual", channel, period=0.05)
        try:
            m = _manager(f"can://virtual/{channel}?timeout=0.5")
            assert await m.request_tune("L", TuneRequest(), "alice")  # a live node: accepted...
            m.abort("L")
            await until(lambda: not m.loops["L"].busy, 60, "the aborted session to end")
            node.silent = True
            with pytest.raises(Refused) as refused:  # ... a silent one: its PV is stale, nothing is sent
                await m.request_tune("L", TuneRequest(), "alice")
            assert refused.value.code == "pv_invalid" and "stale PV" in refused.value.message
            assert len(m.history.of_loop("L")) == 1 and not m.loops["L"].busy
        finally:
            await node.close()

    asyncio.run(scenario())


def test_a_tune_from_the_device_refused_on_the_fresh_read_shows_te_and_its_code_on_the_device():
    async def scenario() -> None:
        config = DaemonConfig.model_validate({"history": ":memory:", "loops": [
            {"id": "H", "sim": {"plant": PLANT}, "ts": 0.2, "handshake": True, "handshake_poll": 0.05,
             "monitor_period": 0.05, "limits": {"pv": [0.0, 100.0]}}]})
        m = LoopManager(config, History(":memory:"))
        plc = m.loops["H"].plc
        await m.start()
        try:
            await until(lambda: m.loops["H"].mode is not None, 30, "the watch task's first reading")
            plc.nan_pv = True
            plc.flags = TuneFlags(tune=True)  # the HMI's TUNE: a rising edge
            await until(lambda: plc.flags.te, 30, "TE on the device")
            assert plc.flags.ite == Code.REFUSED_BAD_PV and not plc.flags.tbsy
            assert plc.mode is Mode.AUTO and m.history.of_loop("H") == []
        finally:
            await m.stop()

    asyncio.run(scenario())
