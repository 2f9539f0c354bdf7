"""One session on a live loop, recorded: the one runner of the daemon's sessions and of ``tune --config``.

:func:`run_session` opens the loop's link, runs the experiment of a
:class:`~autotuner.service.link_session.SessionPlan` through it
(:func:`~autotuner.service.link_session.tune_link`: the loop saved, taken
over, sampled, handed back, designed), writes through a
:class:`~autotuner.service.session_record.SessionRecord` (the saved state,
an MV outside the recorded range and a gains intent are recorded durably
before the writes they guard), reads the gains back and closes the link. What
it returns, :class:`SessionOutcome`, is all the caller records at the end —
picklable, so the session can run in another process than the history (the
daemon's samplers).

The begin and the end of the session are the caller's to record; everything
in between is recorded here, through the caller's ``durable``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace

from drivers.link import Link, LinkError

from autotuner.engine.control.gains import Gains
from autotuner.engine.outcome import MESSAGES, Code
from autotuner.engine.result import TuneResult
from autotuner.service.link_session import SessionHooks, SessionPlan, tune_link
from autotuner.service.session_record import SessionRecord

log = logging.getLogger("autotuner.service.session_runner")


@dataclass(frozen=True)
class SessionOutcome:
    """How a session ended, as its caller records it.

    ``result``: the result (its trace is every sample); ``gains_after``:
    the controller's gains read back after it (None: unknown);
    ``restore_error``: '' when the loop was handed back, else why not;
    ``applied_by``: who applied gains in it (None: nobody); ``intended``: the
    gains a write was attempted with (None: none was).
    """

    result: TuneResult
    gains_after: Gains | None
    restore_error: str
    applied_by: str | None
    intended: Gains | None


async def run_session(connect: Callable[[], Link], plan: SessionPlan, record: SessionRecord,
                      hooks: SessionHooks | None = None) -> SessionOutcome:
    """Run ``plan`` on the loop behind a new link from ``connect()`` (opened and closed here), recorded through
    ``record``.

    ``hooks`` as :func:`~autotuner.service.link_session.tune_link` takes them;
    their ``on_saved`` is the record's (the saved state recorded durably before
    the loop is touched). A link that fails ends the session with LINK_FAULT,
    a bug with ABORTED (logged); either way ``tune_link`` has handed the loop
    back. A cancellation (Ctrl-C, SIGTERM, a daemon that stops) propagates
    once the loop is handed back.
    """
    hooks = SessionHooks() if hooks is None else hooks
    restore_error = ""
    reported = hooks.on_handed_back

    def handed_back(error: str) -> None:
        nonlocal restore_error
        restore_error = error
        if reported is not None:
            reported(error)

    link: Link | None = None
    gains_after: Gains | None = None
    try:
        link = connect()
        tap = record.link(link)
        await link.open()
        result = await tune_link(tap, plan, replace(hooks, on_saved=record.on_saved, on_handed_back=handed_back))
        gains_after = await record.gains_after(link, result, plan.apply)
    except LinkError as exc:
        result = TuneResult.failed(Code.LINK_FAULT, f"{MESSAGES[Code.LINK_FAULT]}: {exc}", plan.controller)
    except Exception as exc:  # a bug: tune_link's own finally has restored the loop; the session must still end
        log.exception("loop %s: session %s failed", record.loop_id, record.sid)
        result = TuneResult.failed(Code.ABORTED, f"aborted: internal error ({type(exc).__name__}: {exc}); see the "
                                   "daemon's log", plan.controller)
    finally:
        if link is not None:
            await link.close()
    return SessionOutcome(result, gains_after, restore_error, record.applied_by(gains_after), record.intended)
