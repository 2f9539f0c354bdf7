"""One loop of a daemon config, tuned without the daemon: ``autotuner tune --config FILE --loop ID``.

The loop is reached exactly as ``autotuner serve`` reaches it (its link and
map, or its simulated plant run at the configured speed), with its tuning
defaults and safety limits; options given on the command line override the
defaults the way a REST TUNE body does. Before the loop is touched it is
checked on a fresh read exactly as the daemon checks a TUNE
(:func:`~autotuner.service.daemon.fresh_check`): a PV outside its limits, not
finite or stale, an unhealthy link, or TBSY already set on the device (another
tuner, e.g. the daemon, owns the loop) ends the run with the refusal's code
(23-26), nothing written.

The session is recorded in the config's history as the daemon records its
own (:class:`~autotuner.service.session_record.SessionRecord`, user
``cli:NAME``): its begin, the saved state before the loop is touched (not
recorded: not touched, code 27), a gains intent before the gains are written
(not recorded: not written) and the end with the gains read back. What a
killed command leaves — a session still ``running``, an open intent — is
recovered and reconciled with the device by the next start of ``autotuner
serve`` with that config (docs/handback.md). Nothing else guards against
the daemon tuning the same loop at the same time: stop it or leave that
loop out.
"""

from __future__ import annotations

import asyncio
import dataclasses
import getpass
import uuid
from collections.abc import Callable

from drivers.link import Link
from drivers.simplc import run

from autotuner.engine.experiment.relay import Status
from autotuner.engine.outcome import MESSAGES, Code
from autotuner.engine.result import TuneResult
from autotuner.service.config import RECORD_WAIT, DaemonConfig, LoopConfig, TuneRequest
from autotuner.service.daemon import Refused, Settings, connector, fresh_check, plan_of, settings_of, simulated_plc
from autotuner.service.daemon.recorder import Recorder
from autotuner.service.history import History, downsample
from autotuner.service.link_session import HandBack, SessionHooks, SessionPlan, tune_link
from autotuner.service.remote_tuning import tune_opened
from autotuner.service.session_record import SessionRecord
from autotuner.service.session_runner import SessionOutcome, run_session


def find_loop(config: DaemonConfig, loop_id: str) -> LoopConfig:
    """The loop ``loop_id`` of ``config``; ValueError listing the configured ids if there is none."""
    loop = config.loop(loop_id)
    if loop is not None:
        return loop
    known = ", ".join(loop.id for loop in config.loops) or "none"
    raise ValueError(f"no loop {loop_id!r} in the config (loops: {known})")


def cli_user() -> str:
    """Who the history records for a session of ``tune --config``: ``cli:`` and the login name."""
    try:
        return f"cli:{getpass.getuser()}"
    except (KeyError, OSError):  # no name for this uid (a container)
        return "cli"


async def tune_configured(
    loop: LoopConfig, request: TuneRequest, on_status: Callable[[Status], None] | None = None,
    handback: HandBack | None = None, history: History | None = None, user: str = "cli",
    record_wait: float = RECORD_WAIT,
) -> TuneResult:
    """Tune ``loop`` once with ``request`` over the loop's defaults (a simulated loop's plant runs meanwhile),
    handed back as ``handback`` says (the config's ``handback`` section: its watchdog armed as the daemon arms
    it; None: the defaults), recorded in ``history`` as asked by ``user`` (None: not recorded), each record
    awaited at most ``record_wait`` wall seconds (the config's ``record_wait``).

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
        plan = plan_of(loop, settings, handback)
        if history is None:
            return await tune_opened(connect(), settings.controller,
                                     lambda link: tune_link(link, plan, SessionHooks(on_status=on_status)))
        return await _recorded(loop.id, settings, plan, connect, Recorder(history, record_wait), user, on_status)
    finally:
        halt.set()
        if plant is not None:
            await plant


async def _recorded(loop_id: str, settings: Settings, plan: SessionPlan, connect: Callable[[], Link],
                    recorder: Recorder, user: str, on_status: Callable[[Status], None] | None) -> TuneResult:
    """The session (:func:`~autotuner.service.session_runner.run_session`, the daemon's), recorded through
    ``recorder`` (the daemon's :class:`~autotuner.service.daemon.recorder.Recorder`) as the daemon records its
    sessions: writes in order in a thread of their own, each awaited at most ``recorder.wait`` s, the saved state
    and a gains intent dropped rather than written after that."""
    sid = uuid.uuid4().hex
    history = recorder.history
    try:
        why = await recorder.durable(history.begin, sid, loop_id, user, settings.as_json())
        if why:
            return TuneResult.failed(Code.HISTORY_UNAVAILABLE, f"{MESSAGES[Code.HISTORY_UNAVAILABLE]}: {why}",
                                     settings.controller)
        record = SessionRecord(recorder.session_record, sid, loop_id, user)
        restore_error = ""

        def handed_back(error: str) -> None:
            nonlocal restore_error
            restore_error = error

        outcome: SessionOutcome | None = None
        state = "finished"
        try:
            outcome = await run_session(connect, plan, record, SessionHooks(on_status=on_status,
                                                                             on_handed_back=handed_back))
        except asyncio.CancelledError:  # Ctrl-C, SIGTERM: tune_link has handed the loop back (or said why not)
            state = "interrupted"
            raise
        finally:
            result = outcome.result if outcome is not None else TuneResult.failed(
                Code.ABORTED, "aborted: the command was interrupted", settings.controller)
            gains_after = None if outcome is None else outcome.gains_after
            if restore_error and record.saved is not None:  # the next start of the daemon resumes the restore
                state = "not_restored"
            why = await recorder.durable(history.finish, sid, result.record(), gains_after, downsample(result.trace),
                                         state, record.applied_by(gains_after))
            if why:
                result = dataclasses.replace(result, message=f"{result.message}; its end is not recorded in the "
                                             f"history: {why}")
        return result
    finally:
        recorder.close(wait=True)  # a write still failing is given up now (logged): the command ends
