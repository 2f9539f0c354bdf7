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
from autotuner.service.link_session import tune_link
from autotuner.engine.simulated_tuning import default_sample_time
from drivers.link import Mode
from drivers.simlink import SimLink
from drivers.simplc import SimulatedPlc, run
from helpers import until

PLANT = "exp(-s)/(2*s+1)"
SPEED = 5.0
# 40 samples per period: 11 ms of wall time per sample at SPEED, which a
# busy test machine keeps without much jitter.
SAMPLES_PER_PERIOD = 40


def analytic(w: float) -> complex:
    s = 1j * w
    return cmath.exp(-s) / (2 * s + 1)


async def session(link_kwargs=None, *, apply=False, stop_after=None, mode=Mode.AUTO, **config):
    process = parse_process(PLANT)
    ts = default_sample_time(process) * 100 / SAMPLES_PER_PERIOD
    plc = SimulatedPlc(process, ts=ts / 5)
    plc.mode = mode
    before = (plc.mode, plc.gains, plc.hv)
    halt = asyncio.Event()
    plant = asyncio.create_task(run(plc, SPEED, halt))
    stop = asyncio.Event()
    if stop_after is not None:
        asyncio.get_running_loop().call_later(stop_after, stop.set)
    link = SimLink(plc, **(link_kwargs or {}))
    try:
        cfg = field_config(RelayConfig(amp=5.0, time_limit=500.0, **config))
        result = await tune_link(link, cfg, ts,
                                 apply=apply, speed=SPEED, stop=stop)
        for _ in range(3):  # let the plant take the restored MV
            plc.tick()
    finally:
        halt.set()
        await plant
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


def test_a_link_that_never_returns_is_reported_as_not_restored(monkeypatch):
    monkeypatch.setattr("autotuner.service.link_session.RESTORE_WINDOW", 1.0)
    result, _, _ = asyncio.run(session({"outage": (60, 10**9)}))
    assert result.code is Code.LINK_FAULT
    assert "LOOP NOT RESTORED" in result.message


def test_nan_pv_is_never_used_as_data():
    async def scenario():
        process = parse_process(PLANT)
        plc = SimulatedPlc(process)
        plc.nan_pv = True
        return await tune_link(SimLink(plc), RelayConfig(amp=1.0), plc.ts, speed=SPEED), plc

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
        task = asyncio.create_task(tune_link(SimLink(plc), RelayConfig(amp=5.0), ts, speed=SPEED))
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
