"""What a loop's trend holds in memory, so a page opened mid-tune (or after) sees it from the experiment's start.

The daemon publishes every ``sample`` event to the loop's :class:`Trend` too:
the samples of the running (or last) session from its first one, at full
resolution, and the monitor's samples since that session ended (or, before
any session, the newest monitor samples). A new session starts a fresh trend.
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
