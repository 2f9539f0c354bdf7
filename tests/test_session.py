"""The real-time session over a link: identification, restoring the loop in every outcome, applying gains."""

from __future__ import annotations

import asyncio
import cmath
import math

import pytest

from autotuner.engine.plant.expression import parse_process
from autotuner.engine.outcome import Code
from autotuner.engine.experiment.relay import RelayConfig
from autotuner.service.remote_tuning import field_config
from autotuner.service.link_session import HandBack, SessionHooks, SessionPlan, tune_link
from autotuner.engine.simulated_tuning import default_sample_time
from drivers.link import Mode, TuneFlags
from drivers.simlink import SimLink
from drivers.simplc import SimulatedPlc, run
from helpers import first_auto, record_ticks, until

PLANT = "exp(-s)/(2*s+1)"
SPEED = 5.0
# 40 samples per period: 11 ms of wall time per sample at SPEED, which a
# busy test machine keeps without much jitter.
SAMPLES_PER_PERIOD = 40


def analytic(w: float) -> complex:
    s = 1j * w
    return cmath.exp(-s) / (2 * s + 1)


async def session(link_kwargs=None, *, apply=False, stop_after=None, mode=Mode.AUTO, handback=None, ticks=None,
                  stop_at_relay=False, **config):
    process = parse_process(PLANT)
    ts = default_sample_time(process) * 100 / SAMPLES_PER_PERIOD
    plc = SimulatedPlc(process, ts=ts / 5)
    plc.mode = mode
    before = (plc.mode, plc.gains, plc.hv)
    if ticks is not None:
        record_ticks(plc, ticks)
    halt = asyncio.Event()
    plant = asyncio.create_task(run(plc, SPEED, halt))
    stop = asyncio.Event()
    if stop_after is not None:
        asyncio.get_running_loop().call_later(stop_after, stop.set)
    link = SimLink(plc, **(link_kwargs or {}))
    watcher = None
    if stop_at_relay:  # TBRK once the relay holds the MV at a level
        async def at_relay() -> None:
            await until(lambda: plc.mode is Mode.MAN and abs(plc.mv - before[2]) > 2.0, 20.0, "the relay to run")
            stop.set()

        watcher = asyncio.create_task(at_relay())
    try:
        cfg = field_config(RelayConfig(amp=5.0, time_limit=500.0, **config))
        plan = SessionPlan(cfg, ts, apply=apply, speed=SPEED, handback=handback or HandBack())
        result = await tune_link(link, plan, SessionHooks(stop=stop))
        for _ in range(3):  # let the plant take the restored MV
            plc.tick()
    finally:
        halt.set()
        await plant
        if watcher is not None:
            await watcher
    return result, plc, before


def test_tunes_the_loop_and_restores_it():
    result, plc, (mode, gains, _) = asyncio.run(session())
    assert result.ok, result.message
    point = result.identification.point
    true = analytic(point.omega)
    # The plant is sampled by a PLC clocked apart from the session: a few percent.
    assert abs(point.value - true) / abs(true) < 0.05
    assert plc.mode is mode and plc.gains == gains  # not applied unless asked
    assert result.trace.t.size > 100


def test_apply_writes_the_new_gains():
    result, plc, _ = asyncio.run(session(apply=True))
    assert result.ok, result.message
    assert plc.gains.k == pytest.approx(result.design.gains.k)
    assert plc.gains.ti == pytest.approx(result.design.gains.ti)
    assert plc.flags.tbsy is False and plc.flags.te is False and plc.flags.ite == 0


def test_tbrk_aborts_and_restores():
    result, plc, (mode, gains, _) = asyncio.run(session(stop_after=0.3))
    assert result.code is Code.ABORTED
    assert plc.mode is mode and plc.gains == gains
    assert plc.flags.te is True and plc.flags.ite == int(Code.ABORTED)


def test_manual_loop_gets_its_mv_back():
    result, plc, (mode, _, hv) = asyncio.run(session(stop_after=0.3, mode=Mode.MAN))
    assert result.code is Code.ABORTED
    assert plc.mode is Mode.MAN
    assert plc.hv == pytest.approx(hv)
    assert plc.mv == pytest.approx(hv)


def test_link_loss_ends_with_link_fault_and_the_loop_is_restored_when_it_returns():
    result, plc, (mode, gains, _) = asyncio.run(session({"outage": (60, 62)}))
    assert result.code is Code.LINK_FAULT
    assert "simulated link lost" in result.message
    assert plc.mode is mode and plc.gains == gains


def test_the_hand_back_is_bumpless_the_first_auto_output_is_the_saved_mv():
    ticks: list[tuple[Mode, float]] = []
    result, plc, (_, _, saved_mv) = asyncio.run(session(stop_at_relay=True, ticks=ticks))
    assert result.code is Code.ABORTED
    first = first_auto(ticks)
    assert ticks[first - 1][1] == saved_mv  # the last MAN tick ran at the saved MV: the unit tracked it
    # One sample of a PI from where it tracked: far below the relay's amplitude (5), which a switch from the last
    # relay level would show.
    assert abs(ticks[first][1] - saved_mv) < 0.01 * 5.0
    assert any(abs(mv - saved_mv) > 2.0 for mode, mv in ticks[:first] if mode is Mode.MAN)  # the relay ran


def test_a_link_that_never_returns_is_reported_as_not_restored():
    result, plc, _ = asyncio.run(session({"outage": (60, 10**9)}, handback=HandBack(window=1.0)))
    assert result.code is Code.LINK_FAULT
    assert "LOOP NOT RESTORED" in result.message
    assert plc.mode is Mode.MAN  # left where the outage found it (the daemon retries; see test_handback.py)


def test_the_watchdog_hands_the_loop_back_when_the_heartbeat_stops():
    async def scenario():
        process = parse_process(PLANT)
        ts = default_sample_time(process) * 100 / SAMPLES_PER_PERIOD
        plc = SimulatedPlc(process, ts=ts / 5)
        saved_mv = plc.hv
        record_ticks(plc, ticks)
        halt = asyncio.Event()
        plant = asyncio.create_task(run(plc, SPEED, halt))
        link = SimLink(plc)
        # An outage from the 60th call on: the session goes silent with the loop at a relay level.
        link.outage = (60, 10**9)
        task = asyncio.create_task(tune_link(link, SessionPlan(RelayConfig(amp=5.0), ts, speed=SPEED,
                                                                   handback=HandBack(window=30.0, watchdog=2.0))))
        await until(lambda: plc.fallbacks == 1, 20.0, "the watchdog to fall back")
        mode, flags = plc.mode, plc.flags
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        halt.set()
        await plant
        return mode, flags, saved_mv

    # The MV of the first AUTO sample, as the PLC ran it (the PI moves on from there while the test polls).
    ticks: list[tuple[Mode, float]] = []
    mode, flags, saved_mv = asyncio.run(scenario())
    assert mode is Mode.AUTO
    first = first_auto(ticks)
    assert ticks[first - 1][1] == saved_mv  # the fallback tick ran in MAN at the saved MV
    assert abs(ticks[first][1] - saved_mv) < 0.01 * 5.0  # bumpless: one PI sample from the saved MV
    assert flags.tbsy is False and flags.te is True and flags.ite == float(Code.WATCHDOG_FALLBACK)


def test_nan_pv_is_never_used_as_data():
    async def scenario():
        process = parse_process(PLANT)
        plc = SimulatedPlc(process)
        plc.nan_pv = True
        return await tune_link(SimLink(plc), SessionPlan(RelayConfig(amp=1.0), plc.ts, speed=SPEED)), plc

    result, plc = asyncio.run(scenario())
    assert result.code is Code.LINK_FAULT and "pv is not a number" in result.message
    assert plc.mode is Mode.AUTO


def test_pv_limits_end_the_experiment_and_restore():
    result, plc, (mode, _, _) = asyncio.run(session(pv_limits=(49.5, 50.5)))
    assert result.code is Code.PV_OUT_OF_LIMITS
    assert plc.mode is mode


def test_cancellation_restores_before_propagating():
    async def scenario():
        process = parse_process(PLANT)
        ts = default_sample_time(process) * 100 / SAMPLES_PER_PERIOD
        plc = SimulatedPlc(process, ts=ts / 5)
        halt = asyncio.Event()
        plant = asyncio.create_task(run(plc, SPEED, halt))
        task = asyncio.create_task(tune_link(SimLink(plc), SessionPlan(RelayConfig(amp=5.0), ts, speed=SPEED)))
        await until(lambda: plc.mode is Mode.MAN, 5.0, "the experiment to take the loop over")
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        halt.set()
        await plant
        return plc

    plc = asyncio.run(scenario())
    assert plc.mode is Mode.AUTO
    assert not math.isnan(plc.pv)


def test_cancellation_and_a_bug_leave_the_device_not_busy():
    """Cancelled (Ctrl-C, shutdown) or failed with an unexpected exception: handed back and TBSY off on the device,
    TE on with ite ABORTED — a TBSY left set would refuse every later TUNE as another tuner's."""

    def broken(status) -> None:
        if status.progress > 0.0:
            raise RuntimeError("a bug in a status callback")

    async def scenario(cancel: bool):
        process = parse_process(PLANT)
        ts = default_sample_time(process) * 100 / SAMPLES_PER_PERIOD
        plc = SimulatedPlc(process, ts=ts / 5)
        halt = asyncio.Event()
        plant = asyncio.create_task(run(plc, SPEED, halt))
        task = asyncio.create_task(tune_link(SimLink(plc), SessionPlan(RelayConfig(amp=5.0), ts, speed=SPEED),
                                             SessionHooks(on_status=None if cancel else broken)))
        await until(lambda: plc.mode is Mode.MAN or task.done(), 20.0, "the experiment to take the loop over")
        if cancel:
            task.cancel()
        with pytest.raises(asyncio.CancelledError if cancel else RuntimeError):
            await task
        halt.set()
        await plant
        return plc

    for cancel in (True, False):
        plc = asyncio.run(scenario(cancel))
        assert plc.mode is Mode.AUTO, cancel
        assert (plc.flags.tbsy, plc.flags.te, plc.flags.ite) == (False, True, float(Code.ABORTED)), cancel


def test_a_slow_loop_keeps_the_heartbeat_and_a_tbrk_acts_at_once():
    """A sample time longer than the watchdog: the heartbeat goes on between samples (the watchdog never falls
    back during a healthy experiment), and a TBRK between two samples ends the session without waiting for the
    next one."""

    async def scenario():
        plc = SimulatedPlc(parse_process("exp(-20*s)/(40*s+1)"), ts=0.5)
        halt = asyncio.Event()
        plant = asyncio.create_task(run(plc, 1.0, halt))
        stop = asyncio.Event()
        # 20 wall seconds per sample, watchdog 5 s: without heartbeats between samples it would fall back.
        task = asyncio.create_task(tune_link(SimLink(plc), SessionPlan(RelayConfig(amp=5.0), 20.0, speed=1.0,
                                                                            handback=HandBack(window=30.0, watchdog=5.0)),
                                             SessionHooks(stop=stop)))
        await until(lambda: plc.mode is Mode.MAN, 20.0, "the experiment to take the loop over")
        beats = plc.heartbeat
        await until(lambda: plc.heartbeat >= beats + 12, 60.0, "heartbeats between samples, for over 5 s")
        fallbacks, mode = plc.fallbacks, plc.mode
        stop.set()
        asked = asyncio.get_running_loop().time()
        result = await task
        took = asyncio.get_running_loop().time() - asked
        halt.set()
        await plant
        return result, plc, fallbacks, mode, took

    result, plc, fallbacks, mode, took = asyncio.run(scenario())
    assert fallbacks == 0 and mode is Mode.MAN  # still the session's: the watchdog never fell back
    assert result.code is Code.ABORTED and plc.mode is Mode.AUTO and result.trace.t.size == 1
    # The TBRK came about 6 s after the only sample: waiting for the next one would take another 14 s.
    assert took < 10.0, took


def test_an_experiment_refused_before_it_starts_never_touches_the_loop():
    """MV limits the relay cannot straddle from the loop's MV: refused with MV_RANGE, and nothing is written to
    the loop (no manual MV, no MAN switched back and forth); the device shows TE with the code."""

    async def scenario():
        process = parse_process(PLANT)
        plc = SimulatedPlc(process, ts=default_sample_time(process) / 5)
        link = SimLink(plc)
        writes: list[str] = []
        record_writes(link, writes)
        result = await tune_link(link, SessionPlan(RelayConfig(amp=5.0, mv_limits=(60.0, 100.0)), plc.ts * 5, speed=SPEED,
                                                   handback=HandBack(watchdog=2.0)))
        return result, plc, writes

    result, plc, writes = asyncio.run(scenario())
    assert result.code is Code.MV_RANGE and "do not straddle" in result.message
    assert set(writes) == {"write_flags"} and plc.mode is Mode.AUTO  # TE and the code, nothing else
    assert (plc.flags.tbsy, plc.flags.te, plc.flags.ite) == (False, True, float(Code.MV_RANGE))


WRITES = ("write_mv", "write_mode", "write_gains", "write_flags", "write_watchdog", "write_heartbeat")


def record_writes(link: SimLink, writes: list[str]) -> None:
    """Every write ``link`` makes from now on, by name, in ``writes``."""
    for name in WRITES:
        def recorder(original, name=name):
            async def write(*args):
                writes.append(name)
                await original(*args)
            return write
        setattr(link, name, recorder(getattr(link, name)))


async def taken_mid_relay(change, watchdog: float = 0.0):
    """A session whose loop ``change(plc)`` changes once the relay holds it at a level (by another hand than the
    session's); the result, the PLC, the writes the session made after the change, the PLC's mode and flags then."""
    process = parse_process(PLANT)
    ts = default_sample_time(process) * 100 / SAMPLES_PER_PERIOD
    plc = SimulatedPlc(process, ts=ts / 5)
    saved_mv = plc.hv
    halt = asyncio.Event()
    plant = asyncio.create_task(run(plc, SPEED, halt))
    link = SimLink(plc)
    writes: list[str] = []
    task = asyncio.create_task(tune_link(link, SessionPlan(field_config(RelayConfig(amp=5.0, time_limit=500.0)), ts,
                                                           speed=SPEED, handback=HandBack(watchdog=watchdog))))
    try:
        await until(lambda: plc.mode is Mode.MAN and abs(plc.mv - saved_mv) > 2.0, 20.0, "the relay to run")
        change(plc)
        record_writes(link, writes)
        after = (plc.mode, plc.flags, plc.hv)
        result = await asyncio.wait_for(task, 30.0)
    finally:
        halt.set()
        await plant
    return result, plc, writes, after


def restart(plc: SimulatedPlc) -> None:
    """The PLC starts again: a new boot token, its registers at their defaults (AUTO, no handshake)."""
    plc.boot = plc.boot % 65535 + 1
    plc.mode = Mode.AUTO
    plc.flags = TuneFlags()


def test_a_device_that_restarted_mid_session_ends_it_with_a_link_fault_and_nothing_more_is_written():
    result, plc, writes, after = asyncio.run(taken_mid_relay(restart))
    assert result.code is Code.LINK_FAULT
    assert "the device restarted during the session" in result.message
    assert writes == []
    assert (plc.mode, plc.flags, plc.hv) == after  # as it restarted


def test_a_loop_taken_out_of_man_mid_session_is_left_as_found():
    def operator(plc: SimulatedPlc) -> None:
        plc.mode = Mode.AUTO

    result, plc, writes, after = asyncio.run(taken_mid_relay(operator))
    assert result.code is Code.OPERATOR_INTERVENTION
    assert "left MAN during the session (AUTO read)" in result.message
    assert writes == []
    assert plc.mode is Mode.AUTO and plc.flags == after[1]


def test_the_reads_keep_their_schedule_while_a_period_is_analysed():
    # Each period's analysis waits here until the session has read one more sample: a session that waited
    # for its analysis before its next read would never finish one (the wait below times out). The samples read
    # meanwhile are stepped once it is over, their MV written late and the experiment told when it arrived: the
    # point is as accurate as a plain session's.
    from autotuner.service.link_session import analysed_in_thread

    async def slowly_analysed() -> tuple:
        process = parse_process(PLANT)
        ts = default_sample_time(process) * 100 / SAMPLES_PER_PERIOD
        plc = SimulatedPlc(process, ts=ts / 5)
        halt = asyncio.Event()
        plant = asyncio.create_task(run(plc, SPEED, halt))
        link = SimLink(plc)
        reads = [0]
        read_sample = link.read_sample

        async def counted():
            sample = await read_sample()
            reads[0] += 1
            return sample

        link.read_sample = counted
        analyses = []

        async def slow(experiment):
            start = reads[0]
            await until(lambda: reads[0] >= start + 1, 30.0, "a read while the period is analysed")
            analyses.append(reads[0] - start)
            return await analysed_in_thread(experiment)

        plan = SessionPlan(field_config(RelayConfig(amp=5.0, time_limit=500.0)), ts, speed=SPEED)
        try:
            result = await asyncio.wait_for(tune_link(link, plan, SessionHooks(analyse=lambda: slow)), 120.0)
        finally:
            halt.set()
            await plant
        return result, plc, analyses

    result, plc, analyses = asyncio.run(slowly_analysed())
    assert result.ok, result.message
    assert len(analyses) >= 3 and min(analyses) >= 1
    point = result.identification.point
    exact = analytic(point.omega)
    assert abs(point.value - exact) / abs(exact) < 0.03
    assert plc.mode is Mode.AUTO
