"""What a loop's trend holds in memory, so a page opened mid-tune (or after) sees it from the experiment's start.

The daemon publishes every ``sample`` event to the loop's :class:`Trend` too:
the samples of the running (or last) session from its first one, at full
resolution, and the monitor's samples since that session ended (or, before
any session, the newest monitor samples). A new session starts a fresh trend.
After a restart the daemon seeds it with the newest finished session from the
history (:meth:`Trend.seed`), so the last experiment is drawn as before.
:meth:`Trend.replay` gives them as columns (the event stream's ``replay``
event, docs/daemon.md).

Memory is bounded: at most :data:`SESSION_KEPT` session samples (past that
every other one is dropped, so a long experiment is kept whole at half the
resolution, and so on) and :data:`MONITOR_KEPT` monitor samples (the oldest
dropped).
"""

from __future__ import annotations

import math
from collections import deque
from datetime import datetime
from typing import Any

# Session samples kept per loop (a 2-hour experiment at 0.2 s is 36 000 samples).
SESSION_KEPT = 40_000
# Monitor samples kept per loop (40 minutes at the default period of 1 s, 10 at the demo's 0.25 s).
MONITOR_KEPT = 2400
# The columns of a replay: wall time (unix s), plant seconds since the session began (None for monitor
# samples), PV, SP, MV (engineering units) and the relay's output ±1 (None for monitor samples).
COLUMNS = ("time", "t", "pv", "sp", "mv", "relay")


def _number(value: Any) -> float | None:
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


class Trend:
    """One loop's recent samples: the session's from its start, then the monitor's."""

    def __init__(self) -> None:
        self.session: str | None = None
        self._session: list[tuple[float | None, ...]] = []
        self._monitor: deque[tuple[float | None, ...]] = deque(maxlen=MONITOR_KEPT)

    def start(self, session: str) -> None:
        """A new session begins: forget the previous trend."""
        self.session = session
        self._session.clear()
        self._monitor.clear()

    def seed(self, record: dict[str, Any], speed: float) -> None:
        """Take a finished session of the history (``record`` with its ``trace``) as the session's samples, when
        the trend holds none (after a restart); ``speed``: the loop's plant seconds per wall second.

        The history keeps, per sample, plant seconds since the session began,
        PV and MV, at the resolution it stores (docs/daemon.md): the wall time is
        ``started_at`` plus the plant seconds over ``speed``, the SP is the one
        saved before the experiment (the session holds it), and the relay's
        output, which is not stored, is the sign of MV minus the saved MV (0 in
        the noise stage, when the MV is the saved one).
        """
        trace, saved = record.get("trace"), record.get("saved")
        if self.session is not None or self._session or not trace or not trace.get("t") or not saved:
            return
        start = datetime.fromisoformat(record["started_at"]).timestamp()
        sp, mv0 = _number(saved.get("sp")), _number(saved.get("mv"))
        for t, pv, mv in zip(trace["t"], trace["pv"], trace["mv"]):
            relay = None if mv0 is None or _number(mv) is None else float((mv > mv0) - (mv < mv0))
            self._session.append((start + t / speed, _number(t), _number(pv), sp, _number(mv), relay))
        self.session = record["id"]

    def add(self, sample: dict[str, Any]) -> None:
        """A ``sample`` event's data: an experiment sample (it has ``stage``) or a monitor reading."""
        row = tuple(_number(sample.get(name)) for name in COLUMNS)
        if "stage" in sample:
            self._session.append(row)
            if len(self._session) > SESSION_KEPT:
                del self._session[1::2]
        else:
            self._monitor.append(row)

    def replay(self) -> dict[str, Any]:
        """``{"session", "time", "t", "pv", "sp", "mv", "relay"}``: every kept sample, oldest first, as columns."""
        rows = [*self._session, *self._monitor]
        return {"session": self.session, **{name: [row[i] for row in rows] for i, name in enumerate(COLUMNS)}}
