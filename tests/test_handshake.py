"""The PLC handshake of the daemon: TUNE/TBRK coils set by an HMI over Modbus TCP, TBSY/TE/ite read back.

Each test serves a simulated PLC over a real Modbus TCP server on localhost
(its plant 20× real time), runs a :class:`LoopManager` whose loop has
``handshake: true``, and plays the HMI with a plain pymodbus client writing
and reading the coils and the ``ite`` register of the default map.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import logging
import math
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass

import numpy as np
import pytest
from pymodbus.client import AsyncModbusTcpClient

from autotuner.service.config import ConfigError, DaemonConfig, TuneRequest, parse_config
from autotuner.service.demo import demo_config
from autotuner.service.daemon import PLC_USER, LoopManager
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.control.gains import Gains
from autotuner.service.history import History
from autotuner.engine.outcome import Code
from autotuner.service.remote_tuning import PLANT_TICKS_PER_SAMPLE
from autotuner.engine.simulated_tuning import default_sample_time
from drivers.link import Mode
from drivers.modbus_map import DEFAULT_MAP
from drivers.modbus_server import ModbusPlcServer, serve_modbus
from drivers.simplc import SimulatedPlc, run
from helpers import until

PLANT = "exp(-s)/(2*s+1)"
SPEED = 20.0
# The experiment that must succeed runs slower: at 20× its sampling over Modbus jitters too much on a busy machine.
SUCCESS_SPEED = 10.0
# 40 experiment samples per period of the 135° point.
TS = default_sample_time(parse_process(PLANT)) * 100 / 40
POLL = 0.05
TUNE, TBRK, TBSY, TE = (DEFAULT_MAP[s].address for s in ("tune", "tbrk", "tbsy", "te"))


class Hmi:
    """An operator panel wired to the PLC: sets TUNE/TBRK, reads TBSY/TE and ite (unit 1, default map)."""

    def __init__(self, port: int) -> None:
        self.client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=2.0)

    async def set(self, coil: int, value: bool) -> None:
        r = await self.client.write_coil(coil, value, device_id=1)
        assert not r.isError(), r

    async def pulse(self, coil: int) -> None:
        """Hold the bit for a few polls (the daemon samples it every POLL seconds), then release it."""
        await self.set(coil, True)
        await asyncio.sleep(6 * POLL)
        await self.set(coil, False)

    async def read(self) -> dict[str, float]:
        bits = await self.client.read_coils(0, count=4, device_id=1)
        words = await self.client.read_holding_registers(DEFAULT_MAP["ite"].address, count=2, device_id=1)
        assert not bits.isError() and not words.isError()
        return {"tune": bits.bits[TUNE], "tbrk": bits.bits[TBRK], "tbsy": bits.bits[TBSY], "te": bits.bits[TE],
                "ite": DEFAULT_MAP.decode("ite", words.registers)}


@dataclass
class Plant:
    plc: SimulatedPlc
    server: ModbusPlcServer
    halt: asyncio.Event
    task: asyncio.Task[None]

    @property
    def url(self) -> str:
        return f"modbus://127.0.0.1:{self.server.port}/1"


@contextlib.asynccontextmanager
async def plants(n: int, speed: float = SPEED) -> AsyncIterator[list[Plant]]:
    """``n`` simulated PLCs, each run ``speed`` × real time behind its own Modbus TCP server."""
    out = []
    for _ in range(n):
        plc = SimulatedPlc(parse_process(PLANT), ts=TS / PLANT_TICKS_PER_SAMPLE)
        halt = asyncio.Event()
        task = asyncio.create_task(run(plc, speed, halt))
        out.append(Plant(plc, await serve_modbus(plc), halt, task))
    try:
        yield out
    finally:
        for p in out:
            p.halt.set()
            await p.task
            await p.server.close()


def loop(loop_id: str, url: str, **extra) -> dict:
    return {"id": loop_id, "link": url, "ts": TS, "speed": SPEED, "handshake": True, "handshake_poll": POLL,
            "tuning": {"amp": 5.0, "time_limit": 500.0}, "limits": {"pv": [0.0, 100.0], "mv": [0.0, 100.0]},
            **extra}


@contextlib.asynccontextmanager
async def daemon(*loops: dict) -> AsyncIterator[LoopManager]:
    config = DaemonConfig.model_validate({"history": ":memory:", "loops": list(loops)})
    m = LoopManager(config, History(":memory:"))
    await m.start()
    try:
        yield m
    finally:
        await m.stop()


def step_response(plc: SimulatedPlc, step: float, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Step the set point of (a copy of) ``plc`` by ``step`` and tick it ``seconds`` of plant time; (t, pv)."""
    plc = copy.deepcopy(plc)
    plc.sp += step
    t0 = plc.t
    t, pv = [], []
    while plc.t - t0 < seconds:
        plc.tick()
        t.append(plc.t - t0)
        pv.append(plc.pv)
    return np.asarray(t), np.asarray(pv)


def settled(plc: SimulatedPlc, seconds: float) -> SimulatedPlc:
    """A copy of ``plc`` ticked ``seconds`` of plant time (the transient of the experiment dies out)."""
    plc = copy.deepcopy(plc)
    t0 = plc.t
    while plc.t - t0 < seconds:
        plc.tick()
    return plc


def settling_time(t: np.ndarray, pv: np.ndarray, target: float, band: float) -> float:
    """The time after which ``pv`` stays within ``band`` of ``target``."""
    outside = np.flatnonzero(np.abs(pv - target) > band)
    return 0.0 if outside.size == 0 else float(t[outside[-1]])


def test_tune_from_the_hmi_runs_the_experiment_then_a_set_point_step_settles(caplog):
    """TUNE coil → TBSY, ite counting down → TE false, gains written; then SP +5 with the new gains."""
    async def body():
        async with (plants(1, SUCCESS_SPEED) as [plant],
                    daemon(loop("TIC-1", plant.url, apply=True, speed=SUCCESS_SPEED)) as m):
            plc = plant.plc
            before = plc.gains
            hmi = Hmi(plant.server.port)
            await hmi.client.connect()
            await asyncio.sleep(3 * POLL)  # the daemon has its reference reading
            await hmi.set(TUNE, True)
            seen = []
            started = time.monotonic()
            while time.monotonic() - started < 40.0:
                seen.append(await hmi.read())
                if seen[-1]["tbsy"]:
                    await hmi.set(TUNE, False)  # the HMI releases TUNE once TBSY answers
                if len(seen) > 2 and not seen[-1]["tbsy"] and any(s["tbsy"] for s in seen):
                    break
                await asyncio.sleep(0.1)
            await m.wait("TIC-1")
            status = m.loops["TIC-1"].as_json()
            record = m.history.get(status["session"])
            # The set point step, written by the HMI over Modbus, on the loop as the session left it.
            plant.halt.set()
            await plant.task
            rest = settled(plc, 150.0)
            r = await hmi.client.write_registers(DEFAULT_MAP["sp"].address, DEFAULT_MAP.encode("sp", 55.0),
                                                 device_id=1)
            assert not r.isError()
            hmi.client.close()
            return plc, before, seen, status, record, rest

    plc, before, seen, status, record, rest = asyncio.run(body())
    busy = [s for s in seen if s["tbsy"]]
    assert busy, seen
    assert seen[-1]["tbsy"] is False and seen[-1]["te"] is False and seen[-1]["ite"] == 0.0, (seen[-1], status["message"])
    # ite counts down the seconds left (rough until the first periods are measured), to about a period at the last
    # switch (progress.LAST_SHARE: whether that switch ends the run is not known before it). (Not half its first
    # reading: that is the prior the time limit implies, 10 s here against the plant's 5.3 s period, and a run of 2.5–4
    # periods read 5.5 s — 1.04 periods — at its last busy reading in CI-like runs.)
    ites = [s["ite"] for s in busy]
    peak = int(np.argmax(ites))
    period = 2 * math.pi / status["point"]["omega"]
    assert len(ites) - peak >= 3 and ites[-1] < ites[peak] and ites[-1] <= 1.3 * period, (str(ites), period)
    assert status["te"] is False and status["ite"] == 0, status["message"]
    assert record["user"] == PLC_USER and record["outcome"] == "success" and record["request"]["apply"] is True
    gains = Gains.from_json(status["gains"])
    assert plc.gains.k == pytest.approx(gains.k, rel=1e-3) and plc.gains != before and plc.mode is Mode.AUTO

    # Set-point step with the new gains: ~20 periods of the identified point.
    assert plc.sp == pytest.approx(55.0)  # written through Modbus
    rest.sp = 50.0
    assert abs(rest.pv - 50.0) < 0.05  # settled before the step
    t, pv = step_response(rest, 5.0, 20 * period)
    overshoot = (pv.max() - 55.0) / 5.0
    last = t > 17 * period
    assert np.all(np.abs(pv[last] - 55.0) <= 0.02 * 5.0), np.abs(pv[last] - 55.0).max()
    assert overshoot <= 0.20, overshoot
    # The PLC's initial cautious gains, same step: slower.
    cautious = SimulatedPlc(parse_process(PLANT), ts=TS / PLANT_TICKS_PER_SAMPLE)
    assert cautious.gains == before
    t0, pv0 = step_response(cautious, 5.0, 20 * period)
    new, old = settling_time(t, pv, 55.0, 0.1), settling_time(t0, pv0, 55.0, 0.1)
    dt = t[1] - t[0]
    iae, iae0 = np.abs(pv - 55.0).sum() * dt, np.abs(pv0 - 55.0).sum() * dt
    print(f"\nperiod {period:.2f} s; overshoot {overshoot:.1%}; 2 % settling {new:.2f} s, IAE {iae:.2f}; "
          f"cautious: overshoot {(pv0.max() - 55.0) / 5.0:.1%}, settling {old:.2f} s, IAE {iae0:.2f}")
    assert new < old and iae < 0.8 * iae0, (new, old, iae, iae0)


def test_set_point_steps_after_tuning_the_demo_loops_settle_faster_than_with_the_cautious_gains():
    """The three process classes of the demo, tuned concurrently (apply), then SP +5 on each: small overshoot.

    The design keeps Ms ≈ 1.4 and sets the set-point weight b so the
    set-point response of the model has no resonance peak: measured
    overshoot 0–2 % here (4–8 % on the loop of the Modbus test above, whose
    dead time is half its lag). The same gains with b = 1 overshoot 9 %,
    28 % and 17 % on these three loops, so the 20 % bound checks that the
    weight is applied, with room for the scatter of the identified point.
    """
    async def body():
        # The demo's three healthy loops (the demo plant's others have faults), without their PV noise: with it
        # (σ 0.02) the tuned loop's PV wanders beyond the 2 % band now and then, and the settling time measures that.
        config = demo_config(SPEED)
        loops = [loop.model_copy(update={"sim": loop.sim.model_copy(update={"noise": 0.0})})
                 for loop in config.loops[:3]]
        m = LoopManager(config.model_copy(update={"loops": loops}), History(":memory:"))
        await m.start()
        try:
            for loop_id in m.loops:
                m.tune(loop_id, TuneRequest(apply=True), user="u")
            for loop_id in m.loops:
                await m.wait(loop_id)
            # Not what this test is about: at 20× on a busy machine the integrating loop's static gain is now
            # and then misjudged (code 8, about 1 run in 10); such a loop is tuned once more.
            for loop_id, loop in m.loops.items():
                if loop.as_json()["te"]:
                    print(f"\n{loop_id}: {loop.as_json()['message']}; tuned again")
                    m.tune(loop_id, TuneRequest(apply=True), user="u")
                    await m.wait(loop_id)
        finally:
            await m.stop()
        return m

    m = asyncio.run(body())
    for loop_id, loop in m.loops.items():
        status = loop.as_json()
        assert status["te"] is False and status["ite"] == 0, (loop_id, status["message"])
        period = 2 * math.pi / status["point"]["omega"]
        rest = settled(loop.plc, 20 * period)
        assert abs(rest.pv - rest.sp) < 0.05, loop_id
        target = rest.sp + 5.0
        t, pv = step_response(rest, 5.0, 20 * period)
        cautious = SimulatedPlc(loop.plc.process, ts=loop.plc.ts)
        assert cautious.gains.as_json() == m.history.get(status["session"])["gains_before"]
        t0, pv0 = step_response(cautious, 5.0, 20 * period)
        overshoot = (pv.max() - target) / 5.0
        new, old = settling_time(t, pv, target, 0.1), settling_time(t0, pv0, target, 0.1)
        print(f"\n{loop_id}: period {period:.1f} s; overshoot {overshoot:.1%}, 2 % settling {new:.1f} s; "
              f"cautious gains: overshoot {(pv0.max() - target) / 5.0:.1%}, settling {old:.1f} s")
        assert overshoot <= 0.20, (loop_id, overshoot)
        assert np.all(np.abs(pv[t > 17 * period] - target) <= 0.1), loop_id
        # (What was identified, so that a rare slow settling can be traced to the tuning: once in a loaded suite
        # run, 2026-12-05, TIC-101 settled in 31 s against 17-21 s in 8 other runs of the same code.)
        found = {k: status.get(k) for k in ("message", "point", "static_gain", "periods", "gains")}
        assert new < 0.7 * old, (loop_id, new, old, found)


def test_tbrk_from_the_hmi_aborts_and_restores_the_loop():
    async def body():
        async with plants(1) as [plant], daemon(loop("TIC-1", plant.url, apply=True)) as m:
            plc = plant.plc
            before = plc.gains
            hmi = Hmi(plant.server.port)
            await hmi.client.connect()
            await asyncio.sleep(3 * POLL)
            # TBRK while idle does nothing.
            await hmi.pulse(TBRK)
            assert not m.loops["TIC-1"].busy and m.loops["TIC-1"].session is None
            await hmi.pulse(TUNE)
            await until(lambda: plc.mode is Mode.MAN, 5.0, "the loop taken over")
            await asyncio.sleep(0.5)
            assert (await hmi.read())["tbsy"] is True
            await hmi.pulse(TBRK)
            await until(lambda: not m.loops["TIC-1"].busy, 5.0, "the session to end")
            flags = await hmi.read()
            status = m.loops["TIC-1"].as_json()
            record = m.history.get(status["session"])
            hmi.client.close()
            return plc, before, flags, status, record

    plc, gains, flags, status, record = asyncio.run(body())
    assert flags["tbsy"] is False and flags["te"] is True and flags["ite"] == float(Code.ABORTED)
    assert status["te"] is True and status["ite"] == int(Code.ABORTED)
    assert record["user"] == PLC_USER and record["code"] == int(Code.ABORTED)
    # Back in AUTO with the old gains, bumplessly from the saved MV (the PI has moved it a little since).
    assert record["saved"]["mode"] == "AUTO" and plc.mode is Mode.AUTO and plc.gains == gains
    assert plc.mv == pytest.approx(record["saved"]["mv"], abs=1.0)


def test_tune_from_the_hmi_while_a_group_member_tunes_is_refused_with_te():
    async def body():
        async with plants(2) as [a, b], daemon(loop("A", a.url, group="g"), loop("B", b.url, group="g")) as m:
            hmi = Hmi(b.server.port)
            await hmi.client.connect()
            await asyncio.sleep(3 * POLL)
            m.tune("A", TuneRequest(), user="alice")  # through the API
            state = (b.plc.mode, b.plc.hv, b.plc.gains)
            await hmi.pulse(TUNE)
            await asyncio.sleep(3 * POLL)
            refused = await hmi.read()
            state_after = (b.plc.mode, b.plc.hv, b.plc.gains)
            b_busy = m.loops["B"].busy
            # TUNE on A's own panel while A runs: ignored, A's session keeps its flags.
            hmi_a = Hmi(a.server.port)
            await hmi_a.client.connect()
            session = m.loops["A"].session
            await hmi_a.pulse(TUNE)
            a_flags = await hmi_a.read()
            same_session = m.loops["A"].session == session and m.loops["A"].busy
            m.abort("A")
            await m.wait("A")
            # Once the group is free, the next TUNE edge on B starts; TE is cleared.
            await hmi.pulse(TUNE)
            await until(lambda: m.loops["B"].busy, 2.0, "B to start")
            await asyncio.sleep(0.7)
            running = await hmi.read()
            m.abort("B")
            await m.wait("B")
            hmi.client.close()
            hmi_a.client.close()
            return refused, state, state_after, b_busy, a_flags, same_session, running

    refused, state, state_after, b_busy, a_flags, same_session, running = asyncio.run(body())
    assert refused["te"] is True and refused["tbsy"] is False and refused["ite"] == float(Code.GROUP_BUSY)
    assert state_after == state and state[0] is Mode.AUTO and not b_busy
    assert same_session and a_flags["tbsy"] is True and a_flags["te"] is False
    assert running["tbsy"] is True and running["te"] is False


def test_a_tune_bit_already_set_when_the_daemon_starts_is_no_edge():
    async def body():
        async with plants(1) as [plant]:
            hmi = Hmi(plant.server.port)
            await hmi.client.connect()
            await hmi.set(TUNE, True)
            async with daemon(loop("TIC-1", plant.url)) as m:
                await asyncio.sleep(10 * POLL)
                idle = not m.loops["TIC-1"].busy
                await hmi.set(TUNE, False)
                await asyncio.sleep(3 * POLL)
                await hmi.set(TUNE, True)  # a real edge
                await until(lambda: m.loops["TIC-1"].busy, 30.0, "the session")
                m.abort("TIC-1")
                await m.wait("TIC-1")
            hmi.client.close()
            return idle

    assert asyncio.run(body())


def test_handshake_link_errors_are_logged_and_retried_without_blocking_other_loops(caplog):
    caplog.set_level(logging.INFO, logger="autotuner.service.daemon")

    async def body():
        async with plants(1) as [plant]:
            port = plant.server.port
            plant.server.fail_with_exception(True)  # every read answers "device failure"
            sim = {"id": "SIM", "sim": {"plant": PLANT}, "ts": TS, "speed": SPEED,
                   "tuning": {"amp": 5.0, "time_limit": 500.0}}
            dead = loop("DEAD", "modbus://127.0.0.1:1/1")  # nothing listens: connection refused
            async with daemon(loop("TIC-1", plant.url), dead, sim) as m:
                m.tune("SIM", TuneRequest(), user="u")
                await until(lambda: all(m.loops[i].monitor_error for i in ("TIC-1", "DEAD")), 30.0,
                            "both handshake links to fail")
                errors = (m.loops["TIC-1"].monitor_error, m.loops["DEAD"].monitor_error)
                sim_running = m.loops["SIM"].busy and m.loops["SIM"].status is not None
                m.abort("SIM")
                plant.server.fail_with_exception(False)
                await until(lambda: m.loops["TIC-1"].monitor_error is None, 30.0, "the link back")
                await asyncio.sleep(3 * POLL)
                hmi = Hmi(port)
                await hmi.client.connect()
                await hmi.set(TUNE, True)
                await until(lambda: m.loops["TIC-1"].busy, 30.0, "the session")
                m.abort("TIC-1")
                await m.wait("TIC-1")
                hmi.client.close()
                dead_still = m.loops["DEAD"].monitor_error
            return errors, sim_running, dead_still

    errors, sim_running, dead_still = asyncio.run(body())
    assert all(errors) and sim_running and dead_still
    failed = [r for r in caplog.records if "handshake link failed" in r.getMessage()]
    assert {r.getMessage().split(":")[0] for r in failed} == {"loop TIC-1", "loop DEAD"}
    assert sum("DEAD" in r.getMessage() for r in failed) == 1  # logged once per outage, not per retry
    assert any("TIC-1: handshake link back" in r.getMessage() for r in caplog.records)


def test_handshake_config():
    config = parse_config({"loops": [{"id": "A", "sim": {"plant": PLANT}, "ts": 0.1}]}, "d.yaml")
    assert config.loops[0].handshake is False and config.loops[0].handshake_poll == 0.5
    with pytest.raises(ConfigError, match=r"d.yaml: loops\[0\].handshake_poll: "):
        parse_config({"loops": [{"id": "A", "sim": {"plant": PLANT}, "ts": 0.1, "handshake": True,
                                 "handshake_poll": 0}]}, "d.yaml")
