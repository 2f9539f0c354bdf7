"""History of tuning sessions in SQLite (the standard library's ``sqlite3``; one file, kept across restarts).

A session is written when it is requested (state ``running``), again when
the loop's state — mode, MV, SP, gains — has been saved, before the
experiment touches the loop (so a daemon that crashes mid-experiment can put
the loop back on its next start), and when it ends
(``finished``, or ``interrupted`` when a restart found it still running),
with the result, the gains after and a downsampled trace. Gains written to the
controller are recorded as applied (``applied_at``, ``applied_by``): at the
end of a session asked to apply them, or later by ``POST /loops/{id}/apply``
(:meth:`History.applied`), which also replaces the gains after.

Records are plain JSON-able dicts; times are UTC ISO 8601 strings.
"""

from __future__ import annotations

import json
import sqlite3
import threading
from datetime import UTC, datetime
from typing import Any

import numpy as np

from autotuner.gains import Gains
from drivers.link import LoopState, Mode

from .tuning import Trace

# Largest number of points of a stored trace.
TRACE_POINTS = 500

_SCHEMA = """
CREATE TABLE IF NOT EXISTS sessions (
    id TEXT PRIMARY KEY,
    loop TEXT NOT NULL,
    user TEXT NOT NULL,
    started_at TEXT NOT NULL,
    finished_at TEXT,
    state TEXT NOT NULL,
    request TEXT NOT NULL,
    saved TEXT,
    result TEXT,
    gains_after TEXT,
    trace TEXT,
    applied_at TEXT,
    applied_by TEXT
);
CREATE INDEX IF NOT EXISTS sessions_by_loop ON sessions (loop, started_at);
"""
# Columns added since the first schema, added to an older file when it is opened.
_ADDED = (("applied_at", "TEXT"), ("applied_by", "TEXT"))


def now() -> str:
    """The current UTC time, ISO 8601 with microseconds."""
    return datetime.now(UTC).isoformat()


def state_json(state: LoopState) -> dict[str, Any]:
    """A loop snapshot as JSON: mode name, MV, SP (engineering units) and gains."""
    return {"mode": Mode(state.mode).name, "mv": state.mv, "sp": state.sp, "gains": state.gains.as_json()}


def state_of(data: dict[str, Any]) -> LoopState:
    """Inverse of :func:`state_json`."""
    return LoopState(mode=Mode[data["mode"]], mv=data["mv"], sp=data["sp"], gains=Gains.from_json(data["gains"]))


def downsample(trace: Trace, points: int = TRACE_POINTS) -> dict[str, list[float]]:
    """At most ``points`` evenly spaced samples of ``trace`` (plant seconds, PV, MV), the last one included."""
    n = len(trace.t)
    index = np.unique(np.linspace(0, n - 1, min(n, points)).round().astype(int)) if n else np.zeros(0, int)
    return {name: [float(x) for x in getattr(trace, name)[index]] for name in ("t", "pv", "mv")}


class History:
    """Sessions in the SQLite database ``path`` (``:memory:`` for a throw-away one); safe across threads."""

    def __init__(self, path: str) -> None:
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        self._db.row_factory = sqlite3.Row
        self._lock = threading.Lock()
        with self._lock:
            self._db.executescript(_SCHEMA)
            columns = {row["name"] for row in self._db.execute("PRAGMA table_info(sessions)")}
            for name, kind in _ADDED:
                if name not in columns:
                    self._db.execute(f"ALTER TABLE sessions ADD COLUMN {name} {kind}")

    def close(self) -> None:
        """Close the database."""
        with self._lock:
            self._db.close()

    def begin(self, sid: str, loop: str, user: str, request: dict[str, Any]) -> None:
        """Record a session that starts now on ``loop``, asked by ``user`` with ``request`` (settings in force)."""
        with self._lock:
            self._db.execute(
                "INSERT INTO sessions (id, loop, user, started_at, state, request) VALUES (?, ?, ?, ?, 'running', ?)",
                (sid, loop, user, now(), json.dumps(request)),
            )

    def saved(self, sid: str, saved: LoopState) -> None:
        """Record the loop's state before session ``sid`` touches it (what a restart after a crash restores)."""
        with self._lock:
            self._db.execute("UPDATE sessions SET saved = ? WHERE id = ?", (json.dumps(state_json(saved)), sid))

    def finish(self, sid: str, result: dict[str, Any], gains_after: Gains | None,
               trace: dict[str, list[float]] | None, state: str = "finished", applied_by: str | None = None) -> None:
        """Record the end of session ``sid``: the result JSON, the controller's gains after it and the trace.

        ``applied_by``: who had the designed gains written at the end of the
        session (the session's user, when it asked to apply them and they
        were written); None if they were not.
        """
        at = now()
        with self._lock:
            self._db.execute(
                "UPDATE sessions SET finished_at = ?, state = ?, result = ?, gains_after = ?, trace = ?, "
                "applied_at = ?, applied_by = ? WHERE id = ?",
                (at, state, json.dumps(result, allow_nan=False),
                 None if gains_after is None else json.dumps(gains_after.as_json()),
                 None if trace is None else json.dumps(trace, allow_nan=False),
                 None if applied_by is None else at, applied_by, sid),
            )

    def applied(self, sid: str, user: str, gains_after: Gains) -> None:
        """Record that ``user`` had the gains of session ``sid`` written now; ``gains_after``: read back."""
        with self._lock:
            self._db.execute("UPDATE sessions SET applied_at = ?, applied_by = ?, gains_after = ? WHERE id = ?",
                             (now(), user, json.dumps(gains_after.as_json()), sid))

    def latest(self, loop: str) -> dict[str, Any] | None:
        """The newest finished (or interrupted) session of ``loop``, without its trace, or None."""
        with self._lock:
            row = self._db.execute(
                "SELECT * FROM sessions WHERE loop = ? AND finished_at IS NOT NULL "
                "ORDER BY started_at DESC, rowid DESC LIMIT 1", (loop,)
            ).fetchone()
        return None if row is None else _record(row, with_trace=False)

    def running(self) -> list[dict[str, Any]]:
        """Sessions recorded as running (after a crash: the ones whose loops must be put back)."""
        with self._lock:
            rows = self._db.execute("SELECT * FROM sessions WHERE state = 'running' ORDER BY started_at").fetchall()
        return [_record(row, with_trace=False) for row in rows]

    def of_loop(self, loop: str, limit: int = 100) -> list[dict[str, Any]]:
        """The latest ``limit`` sessions of ``loop``, newest first, without their traces."""
        with self._lock:
            rows = self._db.execute(
                "SELECT * FROM sessions WHERE loop = ? ORDER BY started_at DESC, rowid DESC LIMIT ?", (loop, limit)
            ).fetchall()
        return [_record(row, with_trace=False) for row in rows]

    def get(self, sid: str) -> dict[str, Any] | None:
        """Session ``sid`` in full, or None."""
        with self._lock:
            row = self._db.execute("SELECT * FROM sessions WHERE id = ?", (sid,)).fetchone()
        return None if row is None else _record(row, with_trace=True)


def _load(text: str | None) -> Any:
    return None if text is None else json.loads(text)


def _record(row: sqlite3.Row, with_trace: bool) -> dict[str, Any]:
    saved = _load(row["saved"])
    result = _load(row["result"])
    record = {
        "id": row["id"],
        "loop": row["loop"],
        "user": row["user"],
        "started_at": row["started_at"],
        "finished_at": row["finished_at"],
        "state": row["state"],
        "request": json.loads(row["request"]),
        "saved": saved,
        "gains_before": None if saved is None else saved["gains"],
        "gains_after": _load(row["gains_after"]),
        "outcome": None if result is None else ("success" if not result["te"] else "failure"),
        "code": None if result is None else result["ite"],
        "message": None if result is None else result["message"],
        "result": result,
        "applied_at": row["applied_at"],
        "applied_by": row["applied_by"],
    }
    if with_trace:
        record["trace"] = _load(row["trace"])
    return record
