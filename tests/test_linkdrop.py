"""A loop whose link drops in the middle of a session, in a daemon tuning another loop at the same time.

Two simulated PLCs, each behind its own real Modbus TCP server on localhost,
tuned together by one :class:`LoopManager`. The server of the first stops
mid-experiment for longer than its link's retries and comes back: that
session ends with the link fault (code 7) and its loop is put back (the
restore is retried until the device answers again); the other loop keeps
sampling on schedule through the outage and its tuning succeeds.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

from autotuner.service.config import DaemonConfig, TuneRequest
from autotuner.service.daemon import LoopManager
from autotuner.engine.plant.expression import parse_process
from autotuner.service.history import History
from helpers import TimedLink, stamp_reads
from autotuner.engine.outcome import Code
from autotuner.service.remote_tuning import PLANT_TICKS_PER_SAMPLE, served
from drivers.link import Mode
from drivers.modbus_server import serve_modbus
from drivers.simplc import SimulatedPlc

PLANT = "exp(-s)/(2*s+1)"
# B's, slower: its experiment must go on through the whole of A's outage (B's on PLANT took ~6 s once the
# experiments got shorter, and ended during it; on exp(-3*s)/(6*s+1), once the noisy model rule ended the
# daemon's runs sooner — its sampling's timing reads as noise —, it ended 0.4 s after the outage).
PLANT_B = "exp(-6*s)/(12*s+1)"
TS = 0.1
SPEED = 5.0  # 20 ms of wall time per sample
OUTAGE = 4.0  # wall seconds: longer than a Modbus call's retries (timeout 1 s, 2 retries)


async def scenario() -> dict[str, Any]:
    plcs = {name: SimulatedPlc(parse_process(plant), ts=TS / PLANT_TICKS_PER_SAMPLE)
            for name, plant in (("A", PLANT), ("B", PLANT_B))}
    async with served(plcs["A"], "modbus", SPEED) as (url_a, server_a), \
            served(plcs["B"], "modbus", SPEED) as (url_b, _):
        config = DaemonConfig.model_validate({"history": ":memory:", "loops": [
            {"id": name, "link": url, "ts": TS, "speed": SPEED, "monitor_period": 0.5,
             "tuning": {"amp": 5.0, "time_limit": 600.0}}
            for name, url in (("A", url_a), ("B", url_b))]})
        history = History(config.history)
        manager = LoopManager(config, history)
        links: list[TimedLink] = []
        stamp_reads(manager.loops["B"], links)
        await manager.start()
        replacement = None
        try:
            manager.tune("A", TuneRequest(), "test")
            manager.tune("B", TuneRequest(), "test")
            await asyncio.sleep(2.0)
            port = server_a.port
            await server_a.close()
            down = time.monotonic()
            await asyncio.sleep(OUTAGE)
            replacement = await serve_modbus(plcs["A"], "127.0.0.1", port)
            up = time.monotonic()
            await manager.wait("A")
            await manager.wait("B")
        finally:
            await manager.stop()
            history.close()
            if replacement is not None:
                await replacement.close()
    return {"a": manager.loops["A"].result.to_json(), "b": manager.loops["B"].result.to_json(), "plc_a": plcs["A"],
            "stamps": [t for link in links if link.session for t in link.done], "down": down, "up": up}


def test_a_link_dropping_mid_session_fails_that_loop_safely_and_never_blocks_the_other():
    out = asyncio.run(scenario())
    a, b = out["a"], out["b"]
    assert a["ite"] == Code.LINK_FAULT and a["te"] is True, a["message"]
    assert "NOT RESTORED" not in a["message"]  # the restore came through once the device answered
    assert out["plc_a"].mode is Mode.AUTO  # put back in its mode once the device answered again
    assert b["ite"] == Code.OK and b["te"] is False, b["message"]
    # B sampled on through A's outage: reads during it at least half as often as before it (as fast as the
    # machine's load lets this process read: the nominal rate is not the point, a B blocked by A's retries is),
    # never a gap near the outage's length.
    stamps, down, up = out["stamps"], out["down"], out["up"]
    before = [t for t in stamps if t < down]
    during = [t for t in stamps if down <= t <= up]
    rate = (len(before) - 1) / (before[-1] - before[0])
    assert stamps[-1] > up + 1.0, "B's experiment ended before A's outage did: nothing to judge"
    assert len(before) >= 10 and len(during) >= 0.5 * rate * (up - down), (len(before), rate, len(during))
    gaps = [later - earlier for earlier, later in zip(out["stamps"], out["stamps"][1:])]
    assert max(gaps) < 1.0
