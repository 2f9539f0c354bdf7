"""One loop of a daemon config, tuned without the daemon: ``autotuner tune --config FILE --loop ID``.

The loop is reached exactly as ``autotuner serve`` reaches it (its link and
map, or its simulated plant run at the configured speed), with its tuning
defaults and safety limits; options given on the command line override the
defaults the way a REST TUNE body does. Before the loop is touched it is
checked on a fresh read exactly as the daemon checks a TUNE
(:func:`~autotuner.service.daemon.fresh_check`): a PV outside its limits, not
finite or stale, an unhealthy link, or TBSY already set on the device (another
tuner, e.g. the daemon, owns the loop) ends the run with the refusal's code
(23-26), nothing written. Nothing else guards against the daemon tuning the
same loop at the same time: stop it or leave that loop out.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from drivers.simplc import run

from autotuner.service.config import DaemonConfig, LoopConfig, TuneRequest
from autotuner.service.daemon import Refused, connector, fresh_check, relay_config, settings_of, simulated_plc
from autotuner.engine.outcome import MESSAGES
from autotuner.engine.experiment.relay import Status
from autotuner.service.link_session import HandBack, tune_link
from autotuner.service.remote_tuning import tune_opened
from autotuner.engine.result import TuneResult


def find_loop(config: DaemonConfig, loop_id: str) -> LoopConfig:
    """The loop ``loop_id`` of ``config``; ValueError listing the configured ids if there is none."""
    loop = config.loop(loop_id)
    if loop is not None:
        return loop
    known = ", ".join(loop.id for loop in config.loops) or "none"
    raise ValueError(f"no loop {loop_id!r} in the config (loops: {known})")


async def tune_configured(
    loop: LoopConfig, request: TuneRequest, on_status: Callable[[Status], None] | None = None,
    handback: HandBack | None = None,
) -> TuneResult:
    """Tune ``loop`` once with ``request`` over the loop's defaults (a simulated loop's plant runs meanwhile),
    handed back as ``handback`` says (the config's ``handback`` section: its watchdog armed as the daemon arms
    it; None: the defaults).

    A loop the daemon's fresh check refuses is not touched: the result is failed with the refusal's code.
    ValueError for an ``amp`` above the loop's bound."""
    settings = settings_of(loop, request)
    if settings.amp > loop.max_amp:
        raise ValueError(f"amp {settings.amp:g} is above loop {loop.id!r}'s largest relay amplitude "
                         f"{loop.max_amp:g} MV units (the span of its MV limits, else its tuning.max_amp)")
    plc = simulated_plc(loop)
    halt = asyncio.Event()
    plant = None if plc is None else asyncio.create_task(run(plc, loop.speed, halt))
    connect = connector(loop, plc)
    try:
        try:
            await fresh_check(loop, connect)
        except Refused as refused:
            code = refused.ite
            assert code is not None  # every refusal of the fresh check has its code
            return TuneResult.failed(code, f"{MESSAGES[code]}: {refused.message}", settings.controller)
        return await tune_opened(connect(), settings.controller, lambda link: tune_link(
            link, relay_config(loop, settings), loop.ts, settings.controller, settings.ms, settings.apply, loop.speed,
            on_status=on_status, handback=handback))
    finally:
        halt.set()
        if plant is not None:
            await plant
