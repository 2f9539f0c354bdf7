"""The LoopManager: the PIDAT state machine per loop, exclusion groups, history, crash recovery."""

from __future__ import annotations

import asyncio

import pytest

from autotuner.service.config import DaemonConfig, TuneRequest
from autotuner.service.daemon import LoopManager, Pending, Refused, found
from autotuner.service.session_record import Tap
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.control.gains import Gains
from autotuner.service.history import TRACE_POINTS, History
from autotuner.engine.outcome import Code
from autotuner.engine.simulated_tuning import default_sample_time
from drivers.link import LinkError, LoopState, Mode
from drivers.simlink import SimLink
from drivers.simplc import SimulatedPlc
from helpers import until

PLANT = "exp(-s)/(2*s+1)"
SPEED = 10.0
# 40 samples per period: 11 ms of wall time per sample at SPEED.
TS = default_sample_time(parse_process(PLANT)) * 100 / 40


def loop(loop_id: str, group: str | None = None, **extra) -> dict:
    return {"id": loop_id, "sim": {"plant": PLANT}, "ts": TS, "speed": SPEED, "group": group,
            "tuning": {"amp": 5.0, "time_limit": 500.0}, **extra}


def manager(*loops: dict, history: History | None = None) -> LoopManager:
    config = DaemonConfig.model_validate({"history": ":memory:", "loops": list(loops)})
    return LoopManager(config, history or History(":memory:"))


async def running(m: LoopManager, body):
    await m.start()
    try:
        return await body(m)
    finally:
        await m.stop()


def test_tune_busy_ite_counts_down_then_success_with_gains_applied():
    async def body(m: LoopManager):
        plc = m.loops["TIC1"].plc
        before = plc.gains
        await until(lambda: m.loops["TIC1"].pv is not None, 10.0, "a monitor reading")
        monitored = m.loops["TIC1"].as_json()
        events = m.subscribe("TIC1")
        sid = m.tune("TIC1", TuneRequest(apply=True), user="alice")
        status = m.loops["TIC1"].as_json()
        assert status["tbsy"] and status["te"] is False and status["session"] == sid
        ites = []
        replay = None
        while m.loops["TIC1"].busy:
            await asyncio.sleep(0.2)
            s = m.loops["TIC1"].as_json()
            if s["tbsy"] and s["stage"] == "relay":
                ites.append(s["ite"])
                if replay is None and len(ites) >= 3:
                    replay = m.replay("TIC1")  # what a page opened now is sent first
        done = m.loops["TIC1"].as_json()
        samples = []
        while not events.empty():
            samples.append(events.get_nowait())
        return sid, done, ites, plc, before, samples, monitored, replay

    m = manager(loop("TIC1"))
    sid, done, ites, plc, before, samples, monitored, replay = asyncio.run(running(m, body))
    assert done["tbsy"] is False and done["te"] is False and done["ite"] == 0, done["message"]
    # The estimate of the seconds left is rough until the first periods are measured, then goes down.
    peak = ites.index(max(ites))
    assert len(ites) - peak >= 3 and ites[-1] < 0.5 * ites[peak], ites
    gains = Gains.from_json(done["gains"])
    assert plc.gains.k == pytest.approx(gains.k) and plc.gains.ti == pytest.approx(gains.ti)
    assert plc.mode is Mode.AUTO
    assert plc.flags.tbsy is False and plc.flags.te is False
    record = m.history.get(sid)
    assert record["user"] == "alice" and record["state"] == "finished" and record["outcome"] == "success"
    assert record["request"]["apply"] is True and record["request"]["amp"] == 5.0
    assert record["gains_before"] == before.as_json()
    assert record["gains_after"]["pk"] == pytest.approx(gains.k)
    # The whole experiment is stored at full resolution (fewer samples than TRACE_POINTS).
    assert len(record["trace"]["t"]) == record["result"].experiment.samples
    assert 10 < len(record["trace"]["t"]) <= TRACE_POINTS
    kinds = {e["event"] for e in samples}
    # health: pending from the start of the tuning (an old event, which a full queue may have dropped)
    assert {"sample", "state"} <= kinds <= {"sample", "state", "health"}
    sample = next(e["data"] for e in samples if e["event"] == "sample" and e["data"].get("stage") == "relay")
    assert {"t", "time", "pv", "sp", "mv", "relay", "filter_phase_deg", "ite"} <= sample.keys()
    assert sample["sp"] == record["saved"]["sp"]
    # The last state is the end of the session (the monitor's samples follow it once the loop is idle and
    # update the live values pv, sp, mv).
    last = [e["data"] for e in samples if e["event"] == "state"][-1]
    # The replay mid-experiment starts at the experiment's first sample and holds every sample published until
    # then (the subscriber here may have lost its oldest events: it reads only at the end).
    published = [e["data"] for e in samples if e["event"] == "sample" and "stage" in e["data"]]
    assert replay["session"] == sid and len(replay["time"]) > 10
    assert replay["t"][0] < 2.0 and replay["t"] == sorted(replay["t"])
    until_then = [p["time"] for p in published if p["time"] <= replay["time"][-1]]
    assert until_then and replay["time"][-len(until_then):] == until_then
    # The final state carries the session's last values, not the monitor's from before the experiment.
    assert last["pv"] == published[-1]["pv"] or last["pv"] != monitored["pv"]
    assert last["pv"] != monitored["pv"] and last["mv"] is not None
    live = ("pv", "sp", "mv")
    assert {k: v for k, v in last.items() if k not in live} == {k: v for k, v in done.items() if k not in live}
    assert done["mode"] == "AUTO" and done["current_gains"] == done["gains"] and done["pending_gains"] is False
    assert done["last_outcome"] == "success" and done["last_tuned_at"] == record["finished_at"]
    assert record["applied_by"] == "alice" and record["applied_at"] == record["finished_at"]


def test_tbrk_aborts_restores_and_keeps_gains():
    async def body(m: LoopManager):
        plc = m.loops["TIC1"].plc
        before = plc.gains
        with pytest.raises(Refused) as idle:
            m.abort("TIC1")
        m.tune("TIC1", TuneRequest(apply=True), user="bob")
        await until(lambda: plc.mode is Mode.MAN, 5.0, "the loop taken over")
        m.abort("TIC1")
        await m.wait("TIC1")
        return idle.value, plc, before, m.loops["TIC1"].as_json()

    idle, plc, gains, status = asyncio.run(running(manager(loop("TIC1")), body))
    assert idle.code == "idle"
    assert status["tbsy"] is False and status["te"] is True and status["ite"] == int(Code.ABORTED)
    # (The MV itself moves on: the plant runs on in AUTO after the restore.)
    assert plc.mode is Mode.AUTO and plc.gains == gains


def test_tune_refused_while_busy_and_within_an_exclusion_group():
    async def body(m: LoopManager):
        m.tune("A", TuneRequest(), user="u")
        with pytest.raises(Refused) as busy:
            m.tune("A", TuneRequest(), user="u")
        with pytest.raises(Refused) as group:
            m.tune("B", TuneRequest(), user="u")
        m.tune("C", TuneRequest(), user="u")  # another group: concurrently
        both = m.loops["A"].busy and m.loops["C"].busy
        with pytest.raises(Refused) as unknown:
            m.tune("nope", TuneRequest(), user="u")
        m.abort("A")
        m.abort("C")
        await m.wait("A")
        await m.wait("C")
        return busy.value, group.value, unknown.value, both

    busy, group, unknown, both = asyncio.run(running(manager(loop("A", "g1"), loop("B", "g1"), loop("C", "g2")), body))
    assert busy.code == "busy" and group.code == "group_busy" and "'A'" in group.message
    assert unknown.code == "not_found" and both


def test_stop_aborts_running_sessions_and_records_them():
    async def body(m: LoopManager):
        sid = m.tune("A", TuneRequest(), user="u")
        await asyncio.sleep(0.3)
        return sid

    m = manager(loop("A"))
    sid = asyncio.run(running(m, body))
    record = m.history.get(sid)
    assert record["state"] == "finished" and record["code"] == int(Code.ABORTED)
    assert m.loops["A"].plc.mode is Mode.AUTO


def test_a_session_left_running_by_a_crash_is_closed_and_its_loop_restored(tmp_path):
    path = str(tmp_path / "history.db")
    crashed = History(path)
    saved = LoopState(mode=Mode.AUTO, mv=50.0, sp=50.0, gains=Gains(k=0.7, ti=3.0))
    crashed.begin("s1", "A", "alice", {"controller": "PI", "amp": 5.0})
    crashed.saved("s1", saved, (47.0, 55.0))  # with the relay's levels, as the daemon records them
    crashed.begin("s0", "B", "alice", {"controller": "PI"})  # never touched its loop
    crashed.close()

    m = manager(loop("A"), loop("B"), history=History(path))
    plc = m.loops["A"].plc
    plc.mode, plc.hv = Mode.MAN, 55.0  # where the relay left it

    async def body(m: LoopManager):
        return m.loops["A"].as_json()

    status = asyncio.run(running(m, body))
    assert plc.mode is Mode.AUTO and plc.hv == 50.0
    assert plc.flags.tbsy is False and plc.flags.te is True
    record = m.history.get("s1")
    assert record["state"] == "interrupted" and record["code"] == int(Code.ABORTED)
    assert "restored to AUTO with MV 50" in record["message"]
    assert m.history.get("s0")["state"] == "interrupted"
    assert status["session"] == "s1" and status["te"] is True
    assert m.history.running() == []


def test_a_device_that_does_not_take_the_saved_mv_is_not_restored_and_retried_until_it_does(tmp_path, caplog):
    """Crash recovery of a loop whose PLC does not take the manual MV (its output is limited to 45): never AUTO
    unconfirmed; status, device and history say not restored (code 20), ERROR per try; once the PLC takes the MV
    the next try hands the loop back."""
    path = str(tmp_path / "history.db")
    crashed = History(path)
    saved = LoopState(mode=Mode.AUTO, mv=50.0, sp=50.0, gains=Gains(k=0.7, ti=3.0))
    crashed.begin("s1", "A", "alice", {"controller": "PI", "amp": 5.0})
    crashed.saved("s1", saved, (45.0, 55.0))
    crashed.close()
    config = DaemonConfig.model_validate({"history": path, "loops": [loop("A")], "handback": {
        "track_timeout": 0.3, "retry_first": 0.2, "retry_max": 0.4}})
    m = LoopManager(config, History(path))
    plc = m.loops["A"].plc
    plc.mode, plc.hv = Mode.MAN, 55.0
    plc.pid.hilim = 45.0  # the relay's low level: the loop reads as the session left it, but cannot reach 50
    plc.tick()

    async def body(m: LoopManager):
        status = m.loops["A"].as_json()
        await until(lambda: m.loops["A"].pending.attempts >= 3, 20.0, "three tries")
        stuck = m.loops["A"].as_json(), m.history.get("s1")["state"], plc.mode, plc.flags
        plc.pid.hilim = 100.0  # the PLC takes the MV again
        await until(lambda: m.loops["A"].pending is None, 20.0, "the restore to succeed")
        return status, stuck

    caplog.set_level("ERROR", logger="autotuner.service.daemon")
    status, (later, state, mode, flags) = asyncio.run(running(m, body))
    assert status["ite"] == float(Code.LOOP_NOT_RESTORED) and status["restore"]["session"] == "s1"
    assert later["restore"]["attempts"] >= 3 and "does not take the manual MV" in later["restore"]["last_error"]
    assert state == "not_restored" and mode is Mode.MAN  # never switched to AUTO unconfirmed
    assert flags.te is True and flags.ite == float(Code.LOOP_NOT_RESTORED)
    assert sum("loop A: LOOP NOT RESTORED" in r.getMessage() for r in caplog.records) >= 3
    assert plc.mode is Mode.AUTO and plc.hv == pytest.approx(50.0, abs=1.0)
    record = m.history.get("s1")
    assert record["state"] == "interrupted" and "loop restored to AUTO with MV 50" in record["message"]


def test_a_tune_while_an_apply_reads_the_history_is_refused(tmp_path):
    """The apply holds the loop from its first step: a TUNE that arrives while it reads which gains to write
    (a history read in another thread) is refused, never an experiment with gains written in its middle."""
    from test_apply import record_session

    path = str(tmp_path / "history.db")
    record_session(path, "s1", "TIC1")

    async def body(m: LoopManager):
        apply = asyncio.create_task(m.apply("TIC1", None, "alice"))
        await asyncio.sleep(0)  # the apply runs up to its first wait: the history read
        with pytest.raises(Refused) as refused:
            m.tune("TIC1", TuneRequest(), user="bob")
        out = await apply
        return refused.value.code, out, m.loops["TIC1"].plc.gains

    code, out, gains = asyncio.run(running(manager(loop("TIC1"), history=History(path)), body))
    assert code == "busy" and out["session"] == "s1"
    assert gains == Gains.from_json(out["gains"])


def test_an_mv_outside_the_sessions_range_on_record_is_recorded_before_it_is_written():
    async def main():
        plc = SimulatedPlc(parse_process(PLANT))
        seen: list[tuple[float, float]] = []

        async def widen(mv: float) -> None:  # what the daemon records durably; the device must not have it yet
            seen.append((mv, plc.hv))
            if mv > 90.0:
                raise LinkError("the history is locked")
            tap.mv_range = (tap.mv_range[0], mv)

        tap = Tap(SimLink(plc), before_mv=widen)
        await tap.write_mv(70.0)  # no range yet (the session has not saved the loop): nothing to record
        tap.mv_range = (47.0, 55.0)
        await tap.write_mv(51.3)  # a switch sample between the levels
        assert seen == [] and plc.hv == 51.3
        await tap.write_mv(60.0)
        assert seen == [(60.0, 51.3)] and plc.hv == 60.0 and tap.mv_range == (47.0, 60.0)
        with pytest.raises(LinkError, match="locked"):
            await tap.write_mv(95.0)
        assert plc.hv == 60.0  # not recorded: not written
    asyncio.run(main())


@pytest.mark.parametrize("mode, mv, how", [
    (Mode.MAN, 47.0, "left"), (Mode.MAN, 51.3, "left"), (Mode.MAN, 55.0 + 1e-6, "left"), (Mode.MAN, 55.1, "changed"),
    (Mode.MAN, 20.0, "changed"), (Mode.AUTO, 51.3, "back"),
])
def test_recovery_takes_man_within_the_sessions_mv_range_as_its_own(mode, mv, how):
    saved = LoopState(mode=Mode.AUTO, mv=50.0, sp=50.0, gains=Gains(k=1.0, ti=1.0))
    pending = Pending("s", saved, (47.0, 55.0), Code.ABORTED, "interrupted", "")
    assert found(LoopState(mode=mode, mv=mv, sp=50.0, gains=saved.gains), pending, 1e-5) == how
