"""CAN between real processes: the daemon (`autotuner serve --config`) and a simulated CAN node (`autotuner sim
--can GROUP --interface udp_multicast --can-port P --hop-limit 0`, a process of its own) on python-can's udp_multicast interface (hop limit 0: the frames never leave this host), the
node read by a CanLink of this test process. python-can's `virtual` bus is in-process only, so it cannot carry
this fault: SIGKILL of the daemon with the relay at a level, and the node's watchdog hands the loop back."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import random
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest

from autotuner.engine.outcome import Code
from drivers.can_bus import open_bus
from drivers.can_link import CanLink, encode, epoch_to_wire
from drivers.link import Fenced, Mode, TuneFlags, Watchdog
from helpers import free_port
from test_handback import PLC_TS, SAVED_MV, AMP, SPEED, START, TOKEN, WAIT, wait_for

try:
    import msgpack  # noqa: F401 - python-can's udp_multicast needs it
except ImportError:
    pytest.fail("tests/test_can_process.py needs msgpack (python-can's udp_multicast): pip install -e '.[test]'",
                pytrace=False)

class Reader:
    """A CanLink of this process on the node's bus, in a thread with its own event loop: the device as read by a
    client that is not the daemon."""

    def __init__(self, url: str) -> None:
        self.url = url
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)
        self._thread.start()
        self.link = CanLink.from_url(url, timeout=2.0)
        self._call(self.link.open())

    def _call(self, coro) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(30)

    def read(self) -> dict[str, Any]:
        state = self._call(self.link.read_state())
        flags = self._call(self.link.read_flags())
        return {"mode": state.mode, "mv": state.mv, "tbsy": flags.tbsy, "te": flags.te, "ite": flags.ite}

    def close(self) -> None:
        self._call(self.link.close())
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(30)


@contextmanager
def processes(tmp: Path) -> Iterator[tuple[subprocess.Popen, Reader, Path, Path]]:
    group = f"239.{random.randint(1, 254)}.{random.randint(1, 254)}.{random.randint(1, 254)}"
    port = free_port()
    url = f"can://udp_multicast/{group}?port={port}&hop_limit=0"
    node_log = tmp / "node.log"
    with open(node_log, "w") as out:
        node = subprocess.Popen([sys.executable, "-m", "autotuner.cli", "sim", "--plant", "exp(-s)/(2*s+1)",
                                 "--ts", str(PLC_TS), "--speed", str(SPEED), "--can", group,
                                 "--interface", "udp_multicast", "--can-port", str(port), "--hop-limit", "0"],
                                stdout=out, stderr=subprocess.STDOUT)
    reader = None
    try:
        wait_for(lambda: "serving" in node_log.read_text() or node.poll() is not None, START, "the CAN node")
        assert node.poll() is None, node_log.read_text()
        assert f"serving {url}" in node_log.read_text()  # the URL a link to it takes, options included
        reader = Reader(url)
        config = tmp / "daemon.yaml"
        config.write_text(json.dumps({"history": str(tmp / "history.sqlite"), "handback": {
            "window": 2.0, "retry_first": 0.3, "retry_max": 1.0, "track_timeout": 2.0, "shutdown": 8.0,
            "watchdog": 1.5}, "loops": [{
                "id": "L1", "link": url + "&timeout=0.5", "ts": 0.3, "speed": SPEED, "monitor_period": 0.5,
                "tuning": {"controller": "PI", "amp": AMP, "time_limit": 2000},
                "limits": {"pv": [0, 100], "mv": [0, 100]}}]}))
        yield node, reader, config, node_log
    finally:
        if reader is not None:
            reader.close()
        node.kill()
        node.wait()


def test_sigkill_of_the_daemon_over_can_between_processes_and_the_node_watchdog_hands_back(tmp_path):
    with processes(tmp_path) as (node, reader, config, node_log):
        assert reader.read()["mode"] is Mode.AUTO
        port = free_port()
        base = f"http://127.0.0.1:{port}/api/v1"
        headers = {"Authorization": f"Bearer {TOKEN}"}
        with open(tmp_path / "daemon.log", "w") as out:
            # A session of its own: the whole tuner (the daemon and its sampler) is killed, as a lost machine.
            daemon = subprocess.Popen([sys.executable, "-m", "autotuner.cli", "serve", "--config", str(config),
                                       "--port", str(port)], env={**os.environ, "AUTOTUNER_TOKEN": TOKEN},
                                      stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            def up() -> bool:
                assert daemon.poll() is None, (tmp_path / "daemon.log").read_text()
                try:
                    return httpx.get(f"{base}/health", timeout=2.0).status_code == 200
                except httpx.TransportError:
                    return False

            wait_for(up, START, "the daemon to answer")
            r = httpx.post(f"{base}/loops/L1/tune", headers=headers, json={}, timeout=10.0)
            assert r.status_code == 202, r.text
            at_level = wait_for(lambda: (now := reader.read())["mode"] is Mode.MAN
                                and abs(now["mv"] - SAVED_MV) > 0.5 * AMP and now["tbsy"] and now, WAIT,
                                "the relay to hold the MV at a level, read over CAN")
            os.killpg(daemon.pid, signal.SIGKILL)
            daemon.wait(30)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(daemon.pid, signal.SIGKILL)
            daemon.wait()
        back = wait_for(lambda: (now := reader.read())["mode"] is Mode.AUTO and now, WAIT,
                        "the node's watchdog to hand the loop back")
        now = reader.read()  # the fallback sets mode and flags in one tick; nothing writes them after
    assert at_level["tbsy"] is True
    # Near the saved MV, not at the relay level (the PV drifted for the watchdog's time: the tolerance of
    # test_handback's watchdog test).
    assert abs(back["mv"] - SAVED_MV) < 2 * 0.1 * AMP, back
    assert now["tbsy"] is False and now["te"] is True and now["ite"] == float(Code.WATCHDOG_FALLBACK), now


def test_the_node_of_a_process_of_its_own_fences_an_older_epoch_and_the_link_learns_it(tmp_path):
    """The fleet's fence over CAN between processes (docs/can.md): the short epoch of AT_CmdFlags read by the node
    against its newest, a superseded daemon's frame ignored and reported, and its link refusing what follows."""
    with processes(tmp_path) as (node, reader, config, node_log):
        old, new = reader.link, CanLink.from_url(reader.url, timeout=2.0)
        reader._call(new.open())
        try:
            old.epoch, new.epoch = 5, 6
            reader._call(old.write_mv(40.0))
            reader._call(old.write_flags(TuneFlags(tbsy=True, ite=3.0)))
            wait_for(lambda: reader.read()["ite"] == 3.0, WAIT, "the old owner's flags")
            reader._call(new.write_flags(TuneFlags(tbsy=True, ite=4.0)))  # the new owner's first frame
            wait_for(lambda: reader.read()["ite"] == 4.0, WAIT, "the new owner's flags")
            # The old owner's flags already on their way (sent by a bus of this test's own: the old link, once the
            # node has reported epoch 6, sends nothing more): ignored, and reported.
            frame = encode(old.db, "AT_CmdFlags", {"TBSY": 0, "TE": 1, "ITE": 22.0, "Epoch": epoch_to_wire(5, 24)})
            raw = open_bus("udp_multicast", old.channel, **old.bus_kwargs)
            try:
                raw.send(frame)
            finally:
                raw.shutdown()
            wait_for(lambda: old.reported_epoch == (6, 1), WAIT, "the node's report of its fence")
            for write in (old.write_flags(TuneFlags(te=True, ite=22.0)), old.write_watchdog(Watchdog(0.0, 0.0))):
                with pytest.raises(Fenced, match="has seen lease epoch 6, newer than this daemon.s epoch 5"):
                    reader._call(write)
            now = reader.read()  # the new owner's flags stand
            assert (now["tbsy"], now["te"], now["ite"]) == (True, False, 4.0), now
        finally:
            reader._call(new.close())
    assert "ignored AT_CmdFlags of lease epoch 5, older than the newest seen, 6" in node_log.read_text()


def test_sim_takes_the_udp_multicast_options_only_with_that_interface():
    for extra in (["--modbus", "127.0.0.1:0"], ["--can", "can0"], ["--can", "239.1.2.3", "--interface", "virtual"]):
        done = subprocess.run([sys.executable, "-m", "autotuner.cli", "sim", *extra, "--hop-limit", "0", "--duration",
                               "0.1"], capture_output=True, text=True, timeout=60)
        assert done.returncode == 2, (extra, done.stdout, done.stderr)
        assert "--can-port and --hop-limit are options of --can with --interface udp_multicast" in done.stderr
