"""A loop not handed back yet: what the interrupted session left (:class:`Pending`) and one try at it.

Restore until it holds (docs/handback.md): a loop whose session could not
hand it back is *not restored* and tried again with back-off for as long as
the daemon runs, and after a restart. Each try (:func:`restore_once`) first
reads the loop and compares it with what the session left (:func:`found`):
MAN at an MV within the range the session may write (recorded durably before
the session wrote an MV outside it) is untouched and is handed back; already
in its saved mode is taken as handed back (by the device's watchdog, or by
hand); anything else is an operator's intervention, never overwritten.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Any, Literal

from drivers.link import Link, LinkError, LoopState, Mode, TuneFlags, Watchdog

from autotuner.engine.outcome import Code
from autotuner.service.daemon.status import RestoreStatus
from autotuner.service.history import now
from autotuner.service.link_session import NotTracking, hand_back_once


@dataclass
class Pending:
    """A loop not handed back yet: session ``sid`` saved ``saved`` and wrote MVs within ``mv_range`` only.

    ``code`` and ``final``: the result code and history state the session gets
    once the loop is back. ``since``: UTC, ISO 8601. ``attempts``: tries that
    failed so far (the session's own hand-back counts as one).
    """

    sid: str
    saved: LoopState
    mv_range: tuple[float, float]
    code: Code
    final: str
    error: str
    since: str = field(default_factory=now)
    attempts: int = 1

    def status(self) -> RestoreStatus:
        """The ``restore`` member of the loop's status."""
        return RestoreStatus(self.sid, Mode(self.saved.mode).name, self.saved.mv, self.since,  # type: ignore[arg-type]
                             self.attempts, self.error)

    def as_json(self) -> dict[str, Any]:
        """The ``restore`` member of the loop's status, as JSON."""
        return self.status().__dict__.copy()


def found(state: LoopState, pending: Pending, tolerance: float) -> Literal["left", "back", "changed"]:
    """How the loop is now, against what the interrupted session left (``tolerance``: the link's MV resolution).

    ``left``: MAN at an MV within the range the session may have written (the
    relay's levels, a switch sample between them, the saved MV: untouched, hand
    it back); ``back``: in its saved mode (AUTO, or MAN at the saved MV): handed
    back already; ``changed``: anything else (an operator's intervention).
    """
    low, high = pending.mv_range
    if state.mode is Mode.MAN and low - tolerance <= state.mv <= high + tolerance:
        return "left"
    if state.mode is Mode(pending.saved.mode) is Mode.AUTO:
        return "back"
    return "changed"


@dataclass(frozen=True)
class Restored:
    """A pending restore dealt with: the code the session ends with and what was done (for the record and log);
    ``warning``: it was not handed back by this try (found back, or left as an operator set it)."""

    code: Code
    message: str
    warning: bool


async def restore_once(link: Link, pending: Pending, track_timeout: float) -> Restored:
    """One try at ``pending`` on ``link`` (opened and closed here): hand the loop back, or take it as found.

    Raises LinkError or NotTracking when it must be tried again (TE and ite 20
    written to the device first, when it can be). ``track_timeout``: wall
    seconds the device may take to read the saved MV back.
    """
    saved = pending.saved
    try:
        await link.open()
        state = await link.read_state()
        how = found(state, pending, link.mv_resolution(saved.mv))
        if how == "left":
            await hand_back_once(link, saved, track_timeout)
            done = Restored(pending.code, f"loop restored to {Mode(saved.mode).name} with MV {saved.mv:g}", False)
        else:
            await link.write_watchdog(Watchdog())  # it must not override what is there now, later
            done = await _as_found(link, state, pending) if how == "back" else Restored(
                Code.OPERATOR_INTERVENTION,
                f"left as found: mode {state.mode.name}, MV {state.mv:g}, not MAN within the session's MV range "
                f"{pending.mv_range[0]:g}-{pending.mv_range[1]:g} or the saved {Mode(saved.mode).name} at MV "
                f"{saved.mv:g} (an operator's intervention): not restored", True)
        await link.write_flags(TuneFlags(tbsy=False, te=True, ite=float(done.code)))
        return done
    except (LinkError, NotTracking):
        with contextlib.suppress(LinkError):  # TE and ite 20 on the device, when it can be written
            await link.write_flags(TuneFlags(tbsy=False, te=True, ite=float(Code.LOOP_NOT_RESTORED)))
        raise
    finally:
        await link.close()


async def _as_found(link: Link, state: LoopState, pending: Pending) -> Restored:
    """A loop found back in its saved mode: by the device's watchdog (its ite says so) or by hand."""
    flags = await link.read_flags()
    by_watchdog = flags.ite == float(Code.WATCHDOG_FALLBACK)
    return Restored(Code.WATCHDOG_FALLBACK if by_watchdog else pending.code,
                    f"found back in {state.mode.name} with MV {state.mv:g}: "
                    + ("handed back by the device's watchdog" if by_watchdog else "nothing written"), True)
