"""The OPC UA server with a real client (asyncua's) over TCP on localhost, beside the REST API on the same loops.

One daemon for the module (REST through Starlette's TestClient, OPC UA on a
free port), three simulated loops exp(-0.5·s)/(s+1) at 2× real time (50 ms of wall time per sample, so
the experiment converges on a loaded machine too); a tuning takes about 10 wall seconds.
"""

from __future__ import annotations

import math
import threading
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.crypto import cert_gen
from cryptography.x509.oid import ExtendedKeyUsageOID
from fastapi.testclient import TestClient

from api.app import create_app
from api.auth import token_hash
from api.opcua.address_space import HEALTH, NAMESPACE, PID_PARAMETERS, VARIABLES
from api.opcua.passwords import hash_password
from autotuner.service.config import DaemonConfig
from tests import opcua_client
from tests.helpers import free_port
from tests.opcua_client import Changes, call, now, run, until, value

OPERATOR, VIEWER_TOKEN, VIEWER_PASSWORD = "op-secret", "view-token", "viewer-pw"
API = "/api/v1"
NAN = math.nan
LOOPS = ("TIC-1", "TIC-2", "TIC-3")
UNITS = {"pv": "°C", "mv": "%", "pv_range": [0.0, 150.0]}


def config(tmp_path, port: int) -> DaemonConfig:
    loops = [{"id": loop_id, "sim": {"plant": "exp(-0.5*s)/(s+1)"}, "ts": 0.1, "speed": 2.0, "monitor_period": 0.1,
              "tuning": {"amp": 5.0, "time_limit": 200.0}, "limits": {"pv": [0.0, 100.0], "mv": [0.0, 100.0]}}
             for loop_id in LOOPS]
    loops[0]["units"] = UNITS  # TIC-2 and TIC-3 have none
    loops[1]["group"] = loops[2]["group"] = "reactor"  # an exclusion group: never tuned together
    loops[2]["health"] = {"window": 60.0, "every": 5.0}  # assessed within seconds; the others pending for long
    return DaemonConfig.model_validate({
        "history": str(tmp_path / "history.sqlite"),
        "tokens": [{"name": "hmi", "role": "viewer", "sha256": token_hash(VIEWER_TOKEN)}],
        "opcua": {"port": port, "users": [{"name": "viewer", "role": "viewer",
                                           "password_hash": hash_password(VIEWER_PASSWORD)}]},
        "loops": loops})


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("opcua")
    app = create_app(config(tmp, free_port()), env_token=OPERATOR)
    with TestClient(app, raise_server_exceptions=False) as rest:
        yield rest, app.state.opcua_url, tmp


def client(url: str, user: str | None = "operator", password: str = OPERATOR) -> Client:
    return opcua_client.client(url, user, password)


def test_browse_the_address_space_with_units_and_stable_ids(daemon):
    _, url, _ = daemon

    async def main() -> None:
        async with client(url, "viewer", VIEWER_PASSWORD) as c:
            idx = await c.get_namespace_index(NAMESPACE)
            folder = await c.nodes.objects.get_child([f"{idx}:Loops"])
            loops = await folder.get_children()
            assert [n.nodeid for n in loops] == [ua.NodeId(i, idx) for i in LOOPS]
            names = {(await n.read_browse_name()).Name for n in await loops[0].get_children()}
            assert {v.name for v in VARIABLES} | {"PIDParameters", "Tune", "Break", "Apply", "AutoTuningOn",
                                                  "AutoTuningOff"} <= names
            pid = c.get_node(ua.NodeId("TIC-1.PIDParameters", idx))
            assert {(await n.read_browse_name()).Name for n in await pid.get_children()} == \
                {v.name for v in PID_PARAMETERS}
            ti_unit = await c.get_node(ua.NodeId("TIC-1.ti", idx)).get_child(["0:EngineeringUnits"])
            eu = await ti_unit.read_value()
            assert eu.DisplayName.Text == "s" and eu.UnitId == 5457219  # UNECE "SEC"
            assert await value(c, "TIC-1", "TBSY") is False and await value(c, "TIC-1", "Mode") == "AUTO"
            await until(lambda: _finite(value(c, "TIC-1", "PV")), 10, "the monitor's PV")
            assert abs(await value(c, "TIC-1", "PV") - 50.0) < 5  # the simulated PLC sits at PV = MV = 50
            tune = c.get_node(ua.NodeId("TIC-1.Tune", idx))
            args = await (await tune.get_child(["0:InputArguments"])).read_value()
            assert [a.Name for a in args] == ["controller", "amp", "hysteresis", "phase", "ms", "apply"]

    run(main())


def test_each_loop_has_a_health_object_showing_the_summary_rest_shows(daemon):
    rest, url, _ = daemon
    viewer = {"Authorization": f"Bearer {VIEWER_TOKEN}"}

    async def main() -> None:
        async with client(url, "viewer", VIEWER_PASSWORD) as c:
            idx = await c.get_namespace_index(NAMESPACE)
            for loop_id in LOOPS:
                health = c.get_node(ua.NodeId(f"{loop_id}.Health", idx))
                assert {(await n.read_browse_name()).Name for n in await health.get_children()} == \
                    {v.name for v in HEALTH}
            # TIC-1 keeps the default hour's window: pending while it collects its samples
            assert await value(c, "TIC-1", "Health.State") == "pending"
            assert (await value(c, "TIC-1", "Health.Reason")).startswith("collecting: ")
            assert await value(c, "TIC-1", "Health.Flags") == "" and await value(c, "TIC-1", "Health.Rank") == 0
            time_node = c.get_node(ua.NodeId("TIC-1.Health.Time", idx))
            assert (await time_node.read_data_value(raise_on_bad_status=False)).StatusCode.is_bad()  # none yet

            async def same_as_rest() -> bool:  # the OPC UA values of one assessment are REST's summary of it
                summary = rest.get(f"{API}/loops/TIC-3", headers=viewer).json()["health"]
                if summary["state"] != "ok":
                    return False
                shown = {name: await value(c, "TIC-3", f"Health.{name}") for name in (
                    "State", "Severity", "Rank", "Flags", "Recommendation", "Reason", "Time")}
                return shown == {"State": "ok", "Severity": summary["severity"], "Rank": summary["rank"],
                                 "Flags": ",".join(summary["flags"]), "Recommendation": summary["recommendation"],
                                 "Reason": summary["reason"], "Time": summary["time"]}

            await until(same_as_rest, 60, "TIC-3's health assessed and published over OPC UA")

    run(main())


async def _eu(c: Client, idx: int, node: str) -> tuple[str, int, str, str] | None:
    """(display name, UnitId, description, namespace URI) of the node's EngineeringUnits; None without one."""
    prop = c.get_node(ua.NodeId(f"{node}.EngineeringUnits", idx))
    try:
        eu = await prop.read_value()
    except ua.uaerrors.BadNodeIdUnknown:
        return None
    assert (await prop.read_browse_name()) == ua.QualifiedName("EngineeringUnits", 0)  # the standard property
    return eu.DisplayName.Text, eu.UnitId, eu.Description.Text, eu.NamespaceUri


def test_the_loops_engineering_units_are_published_on_pv_sp_mv_and_the_gains(daemon):
    _, url, _ = daemon
    unece = "http://www.opcfoundation.org/UA/units/un/cefact"

    async def main() -> None:
        async with client(url, "viewer", VIEWER_PASSWORD) as c:
            idx = await c.get_namespace_index(NAMESPACE)
            celsius = ("°C", 4408652, "degree Celsius", unece)  # UNECE "CEL"
            assert await _eu(c, idx, "TIC-1.PV") == await _eu(c, idx, "TIC-1.SP") == celsius
            assert await _eu(c, idx, "TIC-1.MV") == ("%", 20529, "percent", unece)  # "P1"
            for gain in ("TIC-1.k", "TIC-1.pk", "TIC-1.PIDParameters.P"):  # no UNECE code for %/°C: UnitId -1
                assert await _eu(c, idx, gain) == ("%/°C", -1, "%/°C", unece), gain
            for gain in ("TIC-1.gain", "TIC-1.static_gain"):
                assert await _eu(c, idx, gain) == ("°C/%", -1, "°C/%", unece), gain
            pv_range = await c.get_node(ua.NodeId("TIC-1.PV.EURange", idx)).read_value()
            assert (pv_range.Low, pv_range.High) == (0.0, 150.0)
            nodes = {(await n.read_browse_name()).Name for n in await c.get_node(ua.NodeId("TIC-1.MV", idx))
                     .get_properties()}
            assert "EURange" not in nodes  # no mv_range in its config
            for name in ("PV", "SP", "MV", "k", "gain"):  # a loop without units: no unit is published
                assert await _eu(c, idx, f"TIC-2.{name}") is None, name
            assert (await _eu(c, idx, "TIC-2.ti"))[:2] == ("s", 5457219)  # seconds are seconds everywhere
            # Typed as OPC 10000-8's Analog types, whose mandatory properties these are (HMIs look there).
            types = {node: (await c.get_node(ua.NodeId(node, idx)).read_type_definition()).Identifier for node in
                     ("TIC-1.PV", "TIC-1.MV", "TIC-1.PIDParameters.I", "TIC-2.PV", "TIC-2.ti", "TIC-1.TBSY")}
            assert types == {"TIC-1.PV": ua.ObjectIds.AnalogUnitRangeType, "TIC-1.MV": ua.ObjectIds.AnalogUnitType,
                             "TIC-1.PIDParameters.I": ua.ObjectIds.AnalogUnitType,
                             "TIC-2.PV": ua.ObjectIds.BaseDataVariableType, "TIC-2.ti": ua.ObjectIds.AnalogUnitType,
                             "TIC-1.TBSY": ua.ObjectIds.BaseDataVariableType}

    run(main())


def test_anonymous_and_wrong_passwords_get_nothing_and_nobody_writes(daemon):
    _, url, _ = daemon

    async def main() -> None:
        for c in (client(url, None), client(url, "viewer", "wrong"), client(url, "nobody", "x")):
            with pytest.raises(ua.UaStatusCodeError):
                async with c:
                    await value(c, "TIC-1", "PV")
        for user, password in (("viewer", VIEWER_PASSWORD), ("operator", OPERATOR)):
            async with client(url, user, password) as c:
                idx = await c.get_namespace_index(NAMESPACE)
                with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                    await c.get_node(ua.NodeId("TIC-1.TBSY", idx)).write_value(True)
                assert await value(c, "TIC-1", "TBSY") is False

    run(main())


def test_a_viewers_tune_is_refused_with_a_bad_status(daemon):
    rest, url, _ = daemon

    async def main() -> None:
        async with client(url, "viewer", VIEWER_PASSWORD) as c:
            for method, args in (("Tune", ("", NAN, NAN, NAN, NAN, "")), ("AutoTuningOn", ()), ("Apply", ())):
                refused = await call(c, "TIC-1", method, *args)  # a Bad status and the message, as REST's 403
                assert refused.StatusCode.value == ua.StatusCodes.BadUserAccessDenied, (method, refused)
                assert [o.Value for o in refused.OutputArguments] == ["", "forbidden: this needs the operator role"]
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):  # asyncua's ordinary call raises it
                idx = await c.get_namespace_index(NAMESPACE)
                await c.get_node(ua.NodeId("TIC-1", idx)).call_method(f"{idx}:AutoTuningOn")
            assert await value(c, "TIC-1", "TBSY") is False

    run(main())
    assert rest.get(f"{API}/loops/TIC-1/history", headers={"Authorization": f"Bearer {VIEWER_TOKEN}"}).json() == []


def test_refused_calls_carry_the_rest_code_and_message(daemon):
    _, url, _ = daemon

    async def main() -> None:
        async with client(url) as c:
            bad = await call(c, "TIC-3", "Tune", "", -1.0, NAN, NAN, NAN, "")
            assert bad.StatusCode.value == ua.StatusCodes.BadInvalidArgument
            assert bad.OutputArguments[1].Value == "invalid: amp: Input should be greater than 0"
            assert bad.InputArgumentResults[1].value == ua.StatusCodes.BadInvalidArgument
            bad = await call(c, "TIC-3", "Tune", "PIDD", NAN, NAN, NAN, NAN, "maybe")
            assert bad.StatusCode.value == ua.StatusCodes.BadInvalidArgument
            assert "controller" in bad.OutputArguments[1].Value and "apply" in bad.OutputArguments[1].Value
            # The finding: 135 PV units of hysteresis was accepted (PV limits 0-100: the bound is 25).
            bad = await call(c, "TIC-3", "Tune", "", NAN, 135.0, NAN, NAN, "")
            assert bad.StatusCode.value == ua.StatusCodes.BadInvalidArgument, bad.OutputArguments[1].Value
            assert bad.OutputArguments[1].Value.startswith("invalid: hysteresis: 135 is above loop 'TIC-3''s "
                                                           "largest hysteresis 25 PV units")
            idle = await call(c, "TIC-3", "Break")
            assert idle.StatusCode.value == ua.StatusCodes.BadInvalidState
            assert idle.OutputArguments[1].Value.startswith("idle: ")
            with pytest.raises(ua.uaerrors.BadInvalidState):  # asyncua's ordinary call raises the Bad status
                idx = await c.get_namespace_index(NAMESPACE)
                await c.get_node(ua.NodeId("TIC-3", idx)).call_method(f"{idx}:AutoTuningOff")

    run(main())


def test_tune_over_opcua_subscribed_to_pv_and_tbsy_ends_in_the_rest_history(daemon):
    rest, url, _ = daemon

    async def main() -> dict[str, Any]:
        async with client(url) as c:
            idx = await c.get_namespace_index(NAMESPACE)
            changes = Changes()
            sub = await c.create_subscription(50, changes)
            nodes = {name: c.get_node(ua.NodeId(f"TIC-1.{name}", idx)) for name in ("PV", "TBSY", "ite", "TE")}
            for name, node in nodes.items():
                changes.names[node.nodeid] = name
            await sub.subscribe_data_change(list(nodes.values()))
            await sub.subscribe_events(c.get_node(ua.NodeId("TIC-1", idx)),
                                       c.get_node(ua.NodeId("TuningErrorEventType", idx)))
            result = await call(c, "TIC-1", "Tune", "PI", NAN, NAN, NAN, NAN, "true")
            assert result.StatusCode.is_good(), result
            sid = result.OutputArguments[0].Value
            await until(lambda: now(changes.values.get("TBSY", [])[-1:] == [True]), 10, "TBSY rising")
            await until(lambda: _not(value(c, "TIC-1", "TBSY")), 60, "the end of the tuning")
            await until(lambda: now(changes.values.get("TBSY", [])[-1:] == [False]), 10, "TBSY falling")
            te, message = await value(c, "TIC-1", "TE"), await value(c, "TIC-1", "message")
            assert te is False, message
            out = {name: await value(c, "TIC-1", name) for name in
                   ("TE", "ite", "session", "pk", "pti", "k", "ti", "omega", "pending_gains", "Mode")}
            out["P"] = await c.get_node(ua.NodeId("TIC-1.PIDParameters.P", idx)).read_value()
            out["I"] = await c.get_node(ua.NodeId("TIC-1.PIDParameters.I", idx)).read_value()
            out["changes"], out["sid"], out["events"] = changes.values, sid, changes.events
            await sub.delete()
            return out

    out = run(main())
    assert out["TE"] is False and out["ite"] == 0 and out["session"] == out["sid"]
    busy = [x for x in out["changes"]["ite"] if x > 0]  # plant seconds left: counts down, re-estimated per period
    assert sum(b < a for a, b in zip(busy, busy[1:])) >= 3, busy
    assert len(out["changes"]["PV"]) >= 5  # the experiment's samples moved the PV
    assert out["pk"] > 0 and 0 < out["pti"] < math.inf and out["omega"] > 0
    assert (out["k"], out["ti"]) == (out["P"], out["I"]) == pytest.approx((out["pk"], out["pti"]), rel=1e-5)
    assert out["pending_gains"] is False and out["Mode"] == "AUTO" and out["events"] == []  # applied, no TE
    record = rest.get(f"{API}/sessions/{out['sid']}", headers={"Authorization": f"Bearer {VIEWER_TOKEN}"}).json()
    assert record["user"] == "opcua:operator" and record["outcome"] == "success"
    assert record["result"]["gains"]["pk"] == pytest.approx(out["pk"])


async def _not(awaitable: Any) -> bool:
    return not await awaitable


async def _is(awaitable: Any, expected: Any) -> bool:
    return await awaitable == expected


async def _finite(awaitable: Any) -> bool:
    return math.isfinite(await awaitable)


def test_break_restores_the_loop_and_raises_a_te_event(daemon):
    _, url, _ = daemon

    async def main() -> None:
        async with client(url) as c:
            idx = await c.get_namespace_index(NAMESPACE)
            changes = Changes()
            sub = await c.create_subscription(50, changes)
            await sub.subscribe_events(c.get_node(ua.NodeId("TIC-2", idx)),
                                       c.get_node(ua.NodeId("TuningErrorEventType", idx)))
            assert (await call(c, "TIC-2", "AutoTuningOn")).StatusCode.is_good()
            await until(lambda: value(c, "TIC-2", "AutoTuningActive"), 10, "AutoTuningActive")
            # TBSY rises first; the session takes the loop to MAN once its saved state is on record.
            await until(lambda: _is(value(c, "TIC-2", "Mode"), "MAN"), 30, "the loop in MAN")
            assert (await call(c, "TIC-2", "Tune", "", NAN, NAN, NAN, NAN, "")).OutputArguments[1].Value \
                .startswith("busy: ")
            stopped = await call(c, "TIC-2", "Break")
            assert stopped.StatusCode.is_good() and stopped.OutputArguments[0].Value
            await until(lambda: _not(value(c, "TIC-2", "TBSY")), 30, "the break")
            assert await value(c, "TIC-2", "TE") is True and await value(c, "TIC-2", "ite") == 1
            await until(lambda: now(len(changes.events) == 1), 10, "the TE event")
            event = changes.events[0]
            assert (event.Loop, event.Ite, event.Session) == ("TIC-2", 1.0, stopped.OutputArguments[0].Value)
            assert "aborted" in event.Message.Text
            await until(lambda: value(c, "TIC-2", "Mode"), 10, "the monitor")
            assert await value(c, "TIC-2", "Mode") == "AUTO"  # restored
            await sub.delete()

    run(main())


def test_concurrent_tune_over_opcua_and_rest_gives_exactly_one_session(daemon):
    rest, url, _ = daemon
    results: dict[str, Any] = {}
    go = threading.Barrier(2)

    def over_rest() -> None:
        go.wait()
        results["rest"] = rest.post(f"{API}/loops/TIC-3/tune", headers={"Authorization": f"Bearer {OPERATOR}"})

    async def main() -> None:
        async with client(url) as c:
            thread = threading.Thread(target=over_rest)
            thread.start()
            go.wait()
            results["opcua"] = await call(c, "TIC-3", "Tune", "", NAN, NAN, NAN, NAN, "")
            thread.join()
            assert (await call(c, "TIC-3", "Break")).StatusCode.is_good()  # whoever started it
            await until(lambda: _not(value(c, "TIC-3", "TBSY")), 30, "the break")

    run(main())
    accepted = [results["rest"].status_code == 202, results["opcua"].StatusCode.is_good()]
    assert accepted.count(True) == 1, (results["rest"].json(), results["opcua"])
    if accepted[0]:
        assert results["opcua"].OutputArguments[1].Value.startswith("busy: ")
    else:
        assert results["rest"].status_code == 409 and results["rest"].json()["code"] == "busy"
    history = rest.get(f"{API}/loops/TIC-3/history", headers={"Authorization": f"Bearer {VIEWER_TOKEN}"}).json()
    assert len(history) == 1


def test_basic256sha256_sign_and_encrypt_with_the_generated_certificate(daemon, tmp_path):
    _, url, tmp = daemon
    server_cert = tmp / "opcua-server-cert.der"
    assert server_cert.is_file() and (tmp / "opcua-server-key.pem").stat().st_mode & 0o077 == 0

    async def main() -> None:
        key, cert = tmp_path / "client-key.pem", tmp_path / "client-cert.der"
        await cert_gen.setup_self_signed_certificate(key, cert, "urn:test:client", "localhost",
                                                     [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "test"})
        c = client(url, "viewer", VIEWER_PASSWORD)
        await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{cert},{key},{server_cert}")
        async with c:
            assert c.security_policy.Mode == ua.MessageSecurityMode.SignAndEncrypt
            assert await value(c, "TIC-1", "Mode") in ("AUTO", "MAN")

    run(main())


def test_apply_over_opcua_writes_the_gains_and_the_loop_shows_them_applied_at_once(daemon):
    rest, url, _ = daemon

    async def main() -> dict[str, Any]:
        async with client(url) as c:
            await until(lambda: _not(value(c, "TIC-2", "TBSY")), 30, "TIC-2 idle")
            nothing = await call(c, "TIC-2", "Apply")  # no session yet, or the last one failed (the break above)
            assert nothing.StatusCode.value == ua.StatusCodes.BadInvalidState, nothing
            assert nothing.OutputArguments[1].Value.startswith("nothing_to_apply: "), nothing
            started = await call(c, "TIC-2", "Tune", "", NAN, NAN, NAN, NAN, "false")
            assert started.StatusCode.is_good(), started
            sid = started.OutputArguments[0].Value
            await until(lambda: _is(value(c, "TIC-2", "session"), sid), 10, "the session")
            await until(lambda: _not(value(c, "TIC-2", "TBSY")), 60, "the end of the tuning")
            assert await value(c, "TIC-2", "TE") is False, await value(c, "TIC-2", "message")
            await until(lambda: value(c, "TIC-2", "pending_gains"), 10, "the gains pending")
            pk = await value(c, "TIC-2", "pk")
            assert await value(c, "TIC-2", "k") != pk  # not written yet (apply false)
            applied = await call(c, "TIC-2", "Apply")
            assert applied.StatusCode.is_good(), applied
            # Read right after the call, no wait: the reply's status is the loop's after the apply.
            out = {name: await value(c, "TIC-2", name) for name in ("pending_gains", "k", "PIDParameters.P")}
            return {"sid": sid, "pk": pk, "applied": applied, **out}

    out = run(main())
    assert out["applied"].OutputArguments[0].Value == out["sid"]
    assert out["applied"].OutputArguments[1].Value.startswith("applied: pk=")
    assert out["pending_gains"] is False
    assert out["k"] == out["PIDParameters.P"] == pytest.approx(out["pk"])
    record = rest.get(f"{API}/sessions/{out['sid']}", headers={"Authorization": f"Bearer {VIEWER_TOKEN}"}).json()
    assert record["applied_by"] == "opcua:operator" and record["gains_after"]["pk"] == pytest.approx(out["pk"])


def test_a_method_called_with_the_wrong_number_of_arguments_is_refused_and_changes_nothing(daemon):
    _, url, _ = daemon

    async def main() -> None:
        async with client(url) as c:
            await until(lambda: _not(value(c, "TIC-3", "TBSY")), 30, "TIC-3 idle")
            session = await value(c, "TIC-3", "session")
            for method in ("AutoTuningOn", "Break", "AutoTuningOff", "Apply"):
                extra = await call(c, "TIC-3", method, "PID")
                assert extra.StatusCode.value == ua.StatusCodes.BadTooManyArguments, (method, extra)
                assert extra.OutputArguments[1].Value == f"invalid: {method} takes 0 arguments, got 1"
            short = await call(c, "TIC-3", "Tune", "", NAN, NAN, NAN, NAN)
            assert short.StatusCode.value == ua.StatusCodes.BadArgumentsMissing, short
            assert short.OutputArguments[1].Value.startswith("invalid: Tune takes 6 arguments (controller, amp, ")
            assert (await call(c, "TIC-3", "Tune", "", NAN, NAN, NAN, NAN, "", "")).StatusCode.value \
                == ua.StatusCodes.BadTooManyArguments
            assert await value(c, "TIC-3", "TBSY") is False and await value(c, "TIC-3", "session") == session

    run(main())


def test_values_carry_the_source_and_the_server_timestamp(daemon):
    _, url, _ = daemon

    async def main() -> list[ua.DataValue]:
        async with client(url, "viewer", VIEWER_PASSWORD) as c:
            idx = await c.get_namespace_index(NAMESPACE)
            read = ua.ReadParameters(NodesToRead=[ua.ReadValueId(NodeId=ua.NodeId(f"TIC-1.{name}", idx),
                                                                 AttributeId=ua.AttributeIds.Value)
                                                  for name in ("PV", "TBSY")],
                                     TimestampsToReturn=ua.TimestampsToReturn.Both)
            return await c.uaclient.read(read)

    for data in run(main()):
        assert data.SourceTimestamp is not None and data.ServerTimestamp is not None, data


def test_a_compound_unit_inside_a_gains_unit_is_bracketed():
    from api.opcua.address_space import unit_symbol

    flow = {"pv": "m³/h", "mv": "%"}
    assert unit_symbol("{mv}/{pv}", flow) == "%/(m³/h)" and unit_symbol("{pv}/{mv}", flow) == "(m³/h)/%"
    assert unit_symbol("{pv}", flow) == "m³/h" and unit_symbol("{mv}/{pv}", {"pv": "°C", "mv": "%"}) == "%/°C"


def test_a_method_called_on_another_loops_object_is_refused_and_tunes_neither(daemon):
    _, url, _ = daemon

    async def main() -> None:
        async with client(url) as c:
            idx = await c.get_namespace_index(NAMESPACE)
            request = ua.CallMethodRequest(ObjectId=ua.NodeId("TIC-3", idx),
                                           MethodId=ua.NodeId("TIC-1.AutoTuningOn", idx), InputArguments=[])
            wrong = (await c.uaclient.call([request]))[0]
            assert wrong.StatusCode.value == ua.StatusCodes.BadMethodInvalid, wrong
            assert wrong.OutputArguments[1].Value == f"invalid: AutoTuningOn is a method of loop TIC-1, not of " \
                f"ns={idx};s=TIC-3"
            assert await value(c, "TIC-1", "TBSY") is False and await value(c, "TIC-3", "TBSY") is False

    run(main())


def test_an_exclusion_group_holds_across_opcua_and_rest(daemon):
    rest, url, _ = daemon
    operator = {"Authorization": f"Bearer {OPERATOR}"}

    async def main() -> None:
        async with client(url) as c:
            for loop_id in ("TIC-2", "TIC-3"):
                await until(lambda: _not(value(c, loop_id, "TBSY")), 30, f"{loop_id} idle")
            assert (await call(c, "TIC-2", "AutoTuningOn")).StatusCode.is_good()
            refused = rest.post(f"{API}/loops/TIC-3/tune", headers=operator)  # the other interface
            assert refused.status_code == 409 and refused.json()["code"] == "group_busy", refused.json()
            twin = await call(c, "TIC-3", "AutoTuningOn")
            assert twin.StatusCode.value == ua.StatusCodes.BadInvalidState, twin
            assert twin.OutputArguments[1].Value.startswith("group_busy: loop 'TIC-2' of exclusion group 'reactor'")
            assert (await call(c, "TIC-2", "Break")).StatusCode.is_good()
            await until(lambda: _not(value(c, "TIC-2", "TBSY")), 30, "the break")
            assert await value(c, "TIC-3", "TBSY") is False

    run(main())
