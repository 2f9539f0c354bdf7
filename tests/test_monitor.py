"""The watch task's monitor: live mode, PV, SP, MV and gains of idle loops, `sample` events, link errors.

Loops are simulated PLCs inside the daemon (10× real time), watched through
their in-process link; a link that can be switched off stands for a dead
field device.
"""

from __future__ import annotations

import asyncio
import logging
import time

import pytest

from autotuner.service.config import ConfigError, TuneRequest, parse_config
from autotuner.service.daemon.watch import GAINS_EVERY, Watch
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.simulated_tuning import default_sample_time
from drivers.link import LinkError, Mode
from drivers.modbus_link import ModbusLink
from drivers.modbus_server import serve_modbus
from drivers.simlink import SimLink
from drivers.simplc import SimulatedPlc

from test_daemon import manager
from helpers import until

PLANT = "exp(-s)/(2*s+1)"
SPEED = 10.0
TS = default_sample_time(parse_process(PLANT)) * 100 / 40
PERIOD = 0.05


def loop(loop_id: str, **extra) -> dict:
    return {"id": loop_id, "sim": {"plant": PLANT}, "ts": TS, "speed": SPEED, "monitor_period": PERIOD,
            "tuning": {"amp": 5.0, "time_limit": 500.0}, **extra}


def drain(queue: asyncio.Queue) -> list[dict]:
    out = []
    while not queue.empty():
        out.append(queue.get_nowait())
    return out


class Switchable(SimLink):
    """A SimLink whose every call fails while ``down[0]`` is true; counts the monitor's readings (``read_sample``)."""

    def __init__(self, plc, down: list[bool], reads: list[float]) -> None:
        super().__init__(plc)
        self.down, self.reads = down, reads

    def _call(self) -> None:
        super()._call()
        if self.down[0]:
            raise LinkError("simulated device unreachable")

    async def read_sample(self):
        self.reads.append((self, time.monotonic()))
        return await super().read_sample()


def test_idle_loops_are_monitored_with_samples_and_state_on_mode_change():
    async def body():
        m = manager(loop("A"), loop("B", monitor_period=0.5))
        await m.start()
        try:
            events = m.subscribe("A")
            plc = m.loops["A"].plc
            await until(lambda: m.loops["A"].mode is not None and m.loops["B"].mode is not None, 2.0, "reading")
            first = m.loops["A"].as_json()
            await asyncio.sleep(10 * PERIOD)
            plc.sp = 55.0
            plc.mode = Mode.MAN
            await until(lambda: m.loops["A"].as_json()["mode"] == "MAN", 2.0, "mode MAN")
            await asyncio.sleep(3 * PERIOD)
            return first, m.loops["A"].as_json(), plc.gains, drain(events), m.loops["B"].as_json()
        finally:
            await m.stop()

    before = time.time()
    first, later, gains, events, slow = asyncio.run(body())
    assert first["mode"] == "AUTO" and first["monitor_error"] is None
    assert first["pv"] == pytest.approx(50.0, abs=0.5) and first["sp"] == 50.0
    assert first["mv"] == pytest.approx(50.0, abs=0.5)
    assert first["current_gains"] == gains.as_json()
    assert first["last_tuned_at"] is None and first["last_outcome"] is None and first["pending_gains"] is False
    assert later["mode"] == "MAN" and later["sp"] == 55.0
    samples = [e["data"] for e in events if e["event"] == "sample"]
    assert len(samples) >= 8  # every 0.05 s
    assert set(samples[0]) == {"time", "pv", "sp", "mv", "mode"}
    assert before <= samples[0]["time"] <= samples[-1]["time"] <= time.time()
    assert samples[-1]["mode"] == "MAN" and samples[-1]["sp"] == 55.0
    states = [e["data"] for e in events if e["event"] == "state"]
    assert [s["mode"] for s in states] == ["AUTO", "MAN"]  # the first reading, then the change of mode
    assert slow["mode"] == "AUTO"  # another period, its own pace


def test_the_monitor_does_not_read_a_loop_while_its_session_runs():
    async def body():
        m = manager(loop("A"))
        reads: list[tuple[Switchable, float]] = []
        plc = m.loops["A"].plc
        links: list[Switchable] = []

        def connect():
            links.append(Switchable(plc, [False], reads))
            return links[-1]

        m.loops["A"].connect = connect
        await m.start()
        try:
            await until(lambda: len(reads) >= 3, 2.0, "monitor reads")
            events = m.subscribe("A")
            sid = m.tune("A", TuneRequest(), user="u")
            await until(lambda: m.loops["A"].status is not None, 2.0, "the session's first sample")
            started = time.monotonic()
            await asyncio.sleep(1.0)
            during = m.loops["A"].as_json()
            aborted = time.monotonic()
            m.abort("A")
            await m.wait("A")
            ended = time.monotonic()
            await until(lambda: reads[-1][1] > ended, 2.0, "the monitor again")
            session = links[1]  # links[0]: the watch task's, opened at start; then the session's
            watch_reads = [t for link, t in reads if link is not session and started <= t <= aborted]
            return sid, during, watch_reads, drain(events), m.history.get(sid)
        finally:
            await m.stop()

    sid, during, watch_reads, events, record = asyncio.run(body())
    assert watch_reads == []
    assert during["tbsy"] is True and during["mode"] == "MAN" and during["sp"] == record["saved"]["sp"]
    assert during["pv"] is not None and during["mv"] is not None
    samples = [e["data"] for e in events if e["event"] == "sample"]
    tuning = [s for s in samples if "stage" in s]
    assert tuning and all("time" in s and s["sp"] == record["saved"]["sp"] for s in tuning)
    first_tuning = samples.index(tuning[0])
    last_tuning = samples.index(tuning[-1])
    assert all("stage" in s for s in samples[first_tuning:last_tuning + 1])  # no monitor sample in between


def test_monitor_link_errors_are_kept_logged_once_and_retried_without_reaching_other_loops(caplog):
    caplog.set_level(logging.INFO, logger="autotuner.service.daemon")

    async def body():
        m = manager(loop("A"), loop("B"))
        down = [False]
        plc = m.loops["A"].plc
        m.loops["A"].connect = lambda: Switchable(plc, down, [])
        await m.start()
        try:
            await until(lambda: m.loops["A"].mode is not None, 2.0, "reading")
            events = m.subscribe("A")
            down[0] = True
            await until(lambda: m.loops["A"].monitor_error is not None, 2.0, "the error")
            await asyncio.sleep(1.0)  # several retries
            failed = m.loops["A"].as_json()
            other = m.loops["B"].as_json()
            down[0] = False
            await until(lambda: m.loops["A"].monitor_error is None and m.loops["A"].mode is not None, 6.0,
                        "the link back")
            return failed, other, m.loops["A"].as_json(), drain(events)
        finally:
            await m.stop()

    failed, other, back, events = asyncio.run(body())
    assert "unreachable" in failed["monitor_error"] and failed["mode"] is None
    assert other["monitor_error"] is None and other["mode"] == "AUTO"
    assert back["mode"] == "AUTO" and back["monitor_error"] is None
    states = [e["data"] for e in events if e["event"] == "state"]
    assert states[0]["monitor_error"] is not None and states[-1]["monitor_error"] is None
    messages = [r.getMessage() for r in caplog.records]
    assert sum("loop A: monitor link failed" in text for text in messages) == 1
    assert sum("loop A: monitor link back" in text for text in messages) == 1
    assert not any("loop B" in text for text in messages)


def test_a_dead_field_link_leaves_the_status_unknown_and_the_api_answering():
    async def body():
        m = manager(loop("A"), {"id": "DEAD", "link": "modbus://127.0.0.1:1/1", "ts": 1.0, "monitor_period": 0.1})
        await m.start()
        try:
            await until(lambda: m.loops["DEAD"].monitor_error is not None, 5.0, "the error")
            t0 = time.monotonic()
            status = m.loops["DEAD"].as_json()
            return status, time.monotonic() - t0, m.loops["A"].as_json()
        finally:
            await m.stop()

    status, took, other = asyncio.run(body())
    assert status["monitor_error"] and status["mode"] is None and status["pv"] is None
    assert status["current_gains"] is None and took < 0.05  # the status never waits for the link
    assert other["mode"] == "AUTO"


def test_monitor_period_config():
    config = parse_config({"loops": [{"id": "A", "sim": {"plant": PLANT}, "ts": 0.1}]}, "d.yaml")
    assert config.loops[0].monitor_period == 1.0
    for bad in (0.01, 61.0):
        with pytest.raises(ConfigError, match=r"d.yaml: loops\[0\].monitor_period: "):
            parse_config({"loops": [{"id": "A", "sim": {"plant": PLANT}, "ts": 0.1, "monitor_period": bad}]},
                         "d.yaml")


class Readings:
    """A watch's sink that keeps each reading with the requests its link had made by then."""

    def __init__(self, links: list[ModbusLink]) -> None:
        self.links, self.got = links, []

    def reading(self, loop_id, reading) -> None:
        self.got.append((reading, self.links[-1].requests))

    def link_failed(self, loop_id, error) -> None:
        raise AssertionError(f"the link failed: {error}")

    def link_back(self, loop_id) -> None:
        pass

    async def edges(self, loop_id, last, flags):
        return None


def test_a_monitor_reading_is_one_request_with_the_default_map_and_the_gains_are_read_every_10th():
    async def body():
        plc = SimulatedPlc(parse_process(PLANT))
        server = await serve_modbus(plc)
        config = parse_config({"loops": [{"id": "A", "link": f"modbus://127.0.0.1:{server.port}/1", "ts": 0.1,
                                          "monitor_period": PERIOD}]}, "d.yaml").loops[0]
        links: list[ModbusLink] = []

        def connect() -> ModbusLink:
            links.append(ModbusLink.from_url(str(config.link)))
            return links[-1]

        sink, idle, halt = Readings(links), asyncio.Event(), asyncio.Event()
        idle.set()
        task = asyncio.create_task(Watch(config, connect, sink, idle, halt).run())
        try:
            await until(lambda: len(sink.got) >= 2 * GAINS_EVERY + 1, 30.0, "21 readings")
        finally:
            halt.set()
            await task
            await server.close()
        return plc, links, sink.got[:2 * GAINS_EVERY + 1]

    plc, links, got = asyncio.run(body())
    assert len(links) == 1
    requests = [n - before for (_, before), (_, n) in zip([(None, 0)] + got, got)]
    # The first reading: PV, MV, SP and mode (one request) and the gains (read_state: two); then one request each.
    assert requests == ([3] + [1] * (GAINS_EVERY - 1)) * 2 + [3]
    assert [r.gains is not None for r, _ in got] == [i % GAINS_EVERY == 0 for i in range(len(got))]
    for reading, _ in got:
        assert reading.sample.sp == 50.0 and reading.sample.mode is Mode.AUTO
        assert reading.sample.pv == pytest.approx(50.0, abs=0.5) and reading.sample.mv == pytest.approx(50.0, abs=0.5)
        if reading.gains is not None:
            assert reading.gains.k == pytest.approx(plc.gains.k, rel=1e-6)
            assert reading.gains.ti == pytest.approx(plc.gains.ti, rel=1e-6)
