"""The OPC UA server of a real daemon process (`autotuner serve --config`) on a loop over Modbus TCP to a simulated
PLC process (`autotuner sim --modbus`, tests/test_handback.py's rig), with asyncua's client: how refusals are
logged (the daemon's stderr), and the loop-not-restored event while the PLC is frozen.

Every wait is a condition with a generous deadline; the plant runs 20× real time.
"""

from __future__ import annotations

import asyncio
import json
import math
import re
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from asyncua import ua

from api.opcua.address_space import NAMESPACE
from api.opcua.passwords import hash_password
from autotuner.engine.outcome import Code
from helpers import Daemon, free_port
from opcua_client import Changes, call, client, now, run, until, value
from test_handback import AMP, SPEED, WAIT, Plc, at_relay_level

OPERATOR, VIEWER_PASSWORD = "faults-operator", "faults-viewer"
# The not-restored outcome and its event's severity (docs/opcua.md, "Events").
NOT_RESTORED, NOT_RESTORED_SEVERITY = float(Code.LOOP_NOT_RESTORED), 1000


@pytest.fixture(scope="module")
def rig(tmp_path_factory) -> Iterator[tuple[Plc, Daemon, str]]:
    """A simulated PLC and a daemon with OPC UA over one loop ``L1`` on it; (plc, daemon, the OPC UA endpoint)."""
    tmp = tmp_path_factory.mktemp("opcua-faults")
    plc = Plc(tmp)
    try:
        opcua_port = free_port()
        config = tmp / "daemon.yaml"
        config.write_text(json.dumps({  # JSON is YAML
            "history": str(tmp / "history.sqlite"),
            # A short restore window and retries: a frozen PLC makes the loop not restored within seconds.
            "handback": {"window": 1.0, "retry_first": 0.3, "retry_max": 1.0, "track_timeout": 2.0,
                         "shutdown": 8.0, "watchdog": 0.0},
            "opcua": {"port": opcua_port, "users": [{"name": "viewer", "role": "viewer",
                                                     "password_hash": hash_password(VIEWER_PASSWORD)}]},
            "loops": [{"id": "L1", "link": plc.url, "ts": 0.3, "speed": SPEED, "monitor_period": 0.5,
                       "tuning": {"controller": "PI", "amp": AMP, "time_limit": 2000},
                       "limits": {"pv": [0, 100], "mv": [0, 100]}}]}))
        with Daemon(config, token=OPERATOR) as daemon:  # /health answers once the OPC UA server listens
            yield plc, daemon, f"opc.tcp://127.0.0.1:{opcua_port}/autotuner/"
    finally:
        plc.close()


def rest_status(daemon: Daemon) -> dict[str, Any]:
    return httpx.get(f"{daemon.base}/loops/L1", headers=daemon.headers, timeout=5.0).json()


def test_refusals_are_logged_once_as_expected_outcomes_with_the_loop_and_reason_without_asyncua_errors(rig):
    _, daemon, url = rig
    start = len(daemon.log())

    async def main() -> None:
        for user, password in ((None, ""), ("viewer", "wrong")):
            with pytest.raises(ua.UaStatusCodeError):
                async with client(url, user, password):
                    pass
        async with client(url, "viewer", VIEWER_PASSWORD) as c:
            idx = await c.get_namespace_index(NAMESPACE)
            forbidden = await call(c, "L1", "Tune", "", math.nan, math.nan, math.nan, math.nan, "")
            assert forbidden.StatusCode.value == ua.StatusCodes.BadUserAccessDenied, forbidden
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await c.get_node(ua.NodeId("L1.TBSY", idx)).write_value(True)
        async with client(url, "operator", OPERATOR) as c:
            assert (await call(c, "L1", "AutoTuningOn")).StatusCode.is_good()
            busy = await call(c, "L1", "AutoTuningOn")
            assert busy.StatusCode.value == ua.StatusCodes.BadInvalidState, busy
            invalid = await call(c, "L1", "Tune", "", -1.0, math.nan, math.nan, math.nan, "")
            assert invalid.StatusCode.value == ua.StatusCodes.BadInvalidArgument, invalid
            assert (await call(c, "L1", "Break")).StatusCode.is_good()
            await until(lambda: _idle(c, daemon), WAIT, "the loop handed back after the break")
            idle = await call(c, "L1", "AutoTuningOff")
            assert idle.StatusCode.value == ua.StatusCodes.BadInvalidState, idle

    run(main())
    expected = [
        r"WARNING autotuner\.api\.opcua: OPC UA: a login refused: only user name and password are accepted",
        r"WARNING autotuner\.api\.opcua: OPC UA: login of 'viewer' refused: unknown user or wrong password",
        r"WARNING autotuner\.api\.opcua: loop L1: Tune over OPC UA by opcua:viewer \(viewer\) refused: forbidden: "
        r"this needs the operator role",
        r"WARNING autotuner\.api\.opcua: OPC UA: write of L1\.TBSY by opcua:viewer \(viewer\) refused: forbidden: the "
        r"variables are read-only",
        r"INFO autotuner\.api\.opcua: loop L1: AutoTuningOn over OPC UA by opcua:operator refused: busy: ",
        r"INFO autotuner\.api\.opcua: loop L1: Tune over OPC UA by opcua:operator refused: invalid: amp: Input should "
        r"be greater than 0",
        r"INFO autotuner\.api\.opcua: loop L1: AutoTuningOff over OPC UA by opcua:operator refused: idle: ",
    ]
    daemon.wait_until(lambda: re.search(expected[-1], daemon.log()[start:]), WAIT, "the last refusal's log line")
    log = daemon.log()[start:]
    for pattern in expected:
        assert len(re.findall(pattern, log)) == 1, f"{pattern!r} once in:\n{log}"
    assert not re.search(r"ERROR asyncua|Traceback", log), log  # asyncua's own error lines for them are kept out
    assert log.count(" refused") == len(expected), log  # one line per refusal


async def _idle(c: Any, daemon: Daemon) -> bool:
    return await value(c, "L1", "TBSY") is False and rest_status(daemon)["restore"] is None


def test_a_loop_not_restored_raises_the_event_and_shows_ite_20_until_the_plc_is_back(rig):
    plc, daemon, url = rig

    async def main() -> None:
        async with client(url, "operator", OPERATOR) as c:
            idx = await c.get_namespace_index(NAMESPACE)
            etype = c.get_node(ua.NodeId("LoopNotRestoredEventType", idx))
            on_loop, on_server = Changes(), Changes()
            ite = c.get_node(ua.NodeId("L1.ite", idx))
            on_loop.names[ite.nodeid] = "ite"
            sub = await c.create_subscription(50, on_loop)
            await sub.subscribe_data_change([ite])
            await sub.subscribe_events(c.get_node(ua.NodeId("L1", idx)), etype)
            server_sub = await c.create_subscription(50, on_server)
            await server_sub.subscribe_events(c.nodes.server, etype)

            started = await call(c, "L1", "AutoTuningOn")
            assert started.StatusCode.is_good(), started
            sid = started.OutputArguments[0].Value
            await asyncio.to_thread(at_relay_level, plc)  # the experiment holds the loop in MAN at a relay level
            plc.freeze()
            await until(lambda: now(on_loop.events and on_server.events), WAIT, "the LoopNotRestored event")
            for event in on_loop.events + on_server.events:
                assert (event.Loop, event.Session, event.Ite, event.Severity) == \
                    ("L1", sid, NOT_RESTORED, NOT_RESTORED_SEVERITY)
                assert event.SourceNode == ua.NodeId("L1", idx)
                assert event.Message.Text.startswith("L1: LOOP NOT RESTORED"), event.Message.Text
            assert await value(c, "L1", "ite") == NOT_RESTORED
            assert await value(c, "L1", "TE") is True and await value(c, "L1", "TBSY") is False
            assert rest_status(daemon)["restore"]["session"] == sid  # the daemon keeps retrying the restore

            plc.thaw()
            await until(lambda: _ite_is_not(c, NOT_RESTORED), WAIT, "ite to clear once the PLC answers")
            # Back: the session's own outcome (the link failed under it), the loop restored.
            assert await value(c, "L1", "ite") == float(Code.LINK_FAULT)
            assert rest_status(daemon)["restore"] is None
            now_plc = plc.read()
            assert now_plc["mode"] == "AUTO" and now_plc["tbsy"] is False, now_plc
            await until(lambda: now(on_loop.values["ite"][-1:] == [float(Code.LINK_FAULT)]), WAIT,
                        "the data change of ite")
            changes = on_loop.values["ite"]
            assert changes.index(NOT_RESTORED) < len(changes) - 1, changes  # 20, then the outcome
            assert len(on_loop.events) == len(on_server.events) == 1  # one event per loop not restored
            await sub.delete()
            await server_sub.delete()

    run(main(), timeout=180)


async def _ite_is_not(c: Any, code: float) -> bool:
    return await value(c, "L1", "ite") != code
