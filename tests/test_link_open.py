"""A link that cannot be opened never leaves a loop busy: a device that is offline (a real daemon process, a
Modbus port nobody listens on) has its TUNE refused promptly with the link code, a session whose device went
offline after that check fails promptly with the link code, and an exception while opening the
link (its map file removed after the config was loaded) ends the session like any link fault."""

from __future__ import annotations

import asyncio
import gc
import signal
import time
from pathlib import Path

import httpx
import yaml

from autotuner.engine.outcome import Code
from autotuner.service.config import DaemonConfig, TuneRequest
from autotuner.service.daemon import LoopManager
from autotuner.service.history import History
from drivers.modbus_map import DEFAULT_MAP
from helpers import Daemon, free_port, until


def test_an_offline_plc_does_not_stop_the_daemon_and_tune_is_refused_promptly_with_the_link_code(tmp_path: Path):
    config = tmp_path / "daemon.yaml"
    config.write_text(yaml.safe_dump({"history": "h.db", "loops": [
        {"id": "OFF", "link": f"modbus://127.0.0.1:{free_port()}/1?timeout=0.3&retries=0", "ts": 0.5,
         "monitor_period": 0.2}]}))
    with Daemon(config) as daemon:
        for _ in range(2):  # the same answer again: the loop was never made busy
            start = time.monotonic()
            tune = httpx.post(f"{daemon.base}/loops/OFF/tune", headers=daemon.headers, timeout=30)
            assert tune.status_code == 409 and tune.json()["code"] == "link_unhealthy", tune.text
            assert time.monotonic() - start < 10
            status = httpx.get(f"{daemon.base}/loops/OFF", headers=daemon.headers).json()
            assert status["tbsy"] is False and status["session"] is None
        assert httpx.get(f"{daemon.base}/loops/OFF/history", headers=daemon.headers).json() == []
        assert httpx.post(f"{daemon.base}/loops/OFF/break", headers=daemon.headers).status_code == 409
        daemon.wait_until(lambda: "monitor link failed" in daemon.log(), 30, "the monitor's warning")
    assert daemon.proc.returncode in (0, -signal.SIGTERM)  # uvicorn re-raises SIGTERM after the shutdown
    assert "Traceback" not in daemon.log()


def test_a_session_on_a_device_gone_offline_fails_promptly_with_the_link_code_and_the_loop_is_idle_again():
    config = DaemonConfig.model_validate({"history": ":memory:", "loops": [
        {"id": "OFF", "link": f"modbus://127.0.0.1:{free_port()}/1?timeout=0.3&retries=0", "ts": 0.5}]})

    async def scenario() -> None:
        m = LoopManager(config, History(":memory:"))
        for _ in range(2):
            sid = m.tune("OFF", TuneRequest(), "alice")  # past the fresh read: the device went offline since
            await until(lambda: not m.loops["OFF"].busy, 30, "the session to end")
            assert m.loops["OFF"].as_json()["ite"] == Code.LINK_FAULT
            await m.wait("OFF")
            assert m.history.get(sid)["state"] == "finished" and m.history.get(sid)["code"] == Code.LINK_FAULT
        await m.stop()

    asyncio.run(scenario())


def test_an_exception_while_opening_the_link_leaves_the_loop_idle_and_the_session_recorded(tmp_path: Path):
    path = tmp_path / "map.yaml"
    path.write_text(yaml.safe_dump(DEFAULT_MAP.as_dict()))
    config = DaemonConfig.model_validate({"history": ":memory:", "loops": [
        {"id": "M", "link": f"modbus://127.0.0.1:{free_port()}/1", "map": str(path), "ts": 0.5}]})
    path.unlink()  # after the config was loaded: opening the link now raises

    async def scenario() -> None:
        m = LoopManager(config, History(":memory:"))
        errors: list[dict] = []  # a session task that ended with an exception of its own end (none may)
        asyncio.get_running_loop().set_exception_handler(lambda _, context: errors.append(context))
        await m.start()
        try:
            for _ in range(2):
                sid = m.tune("M", TuneRequest(), "alice")
                await until(lambda: not m.loops["M"].busy, 30, "the session to end")
                status = m.loops["M"].as_json()
                assert status["te"] is True and status["ite"] == Code.LINK_FAULT
                assert "cannot read the map" in status["message"]
                assert m.history.get(sid)["state"] == "finished"
            gc.collect()  # an unretrieved task exception is reported when the task is collected
            assert errors == []
        finally:
            await m.stop()

    asyncio.run(scenario())
