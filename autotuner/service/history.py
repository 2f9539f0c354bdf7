"""History of tuning sessions: an SQLite file by default, or any SQLAlchemy database URL (PostgreSQL, ...).

A session is written when it is requested (state ``running``), again when
the loop's state — mode, MV, SP, gains — has been saved, before the
experiment touches the loop (so a daemon that crashes mid-experiment can put
the loop back on its next start), and when it ends
(``finished``, or ``interrupted`` when a restart found it still running;
``not_restored`` while its loop could not be handed back — the daemon retries
it, also after a restart, and :meth:`History.restored` then gives the row its
final state),
with the result, the gains after and a downsampled trace. Gains written to the
controller are recorded as applied (``applied_at``, ``applied_by``): at the
end of a session asked to apply them, or later by ``POST /loops/{id}/apply``
(:meth:`History.applied`), which also replaces the gains after.

Records are plain JSON-able dicts; times are UTC ISO 8601 strings (they sort
as text). JSON is stored as text, so the one table works on every database
SQLAlchemy Core speaks.
"""

from __future__ import annotations

import json
import threading
from datetime import UTC, datetime
from typing import Any

import numpy as np
import sqlalchemy as sa
from sqlalchemy.engine import Engine, RowMapping
from sqlalchemy.pool import StaticPool

from autotuner.engine.control.gains import Gains
from drivers.link import LoopState, Mode

from autotuner.engine.simulated_tuning import Trace

# Largest number of points of a stored trace.
TRACE_POINTS = 500

_META = sa.MetaData()
_SESSIONS = sa.Table(
    "sessions", _META,
    sa.Column("id", sa.String(64), primary_key=True),
    sa.Column("loop", sa.String(64), nullable=False),
    sa.Column("user", sa.Text, nullable=False),
    sa.Column("started_at", sa.String(40), nullable=False),
    sa.Column("finished_at", sa.String(40)),
    sa.Column("state", sa.String(16), nullable=False),
    sa.Column("request", sa.Text, nullable=False),
    sa.Column("saved", sa.Text),
    sa.Column("result", sa.Text),
    sa.Column("gains_after", sa.Text),
    sa.Column("trace", sa.Text),
    sa.Column("applied_at", sa.String(40)),
    sa.Column("applied_by", sa.Text),
    sa.Index("sessions_by_loop", "loop", "started_at"),
)
# Columns added since the first schema, added to an older database when it is opened.
_ADDED = ("applied_at", "applied_by")
# Newest first; the id breaks a tie of two sessions started in the same microsecond.
_NEWEST_FIRST = (_SESSIONS.c.started_at.desc(), _SESSIONS.c.id.desc())


def database_url(history: str) -> str:
    """The SQLAlchemy URL of a config's ``history``: a URL as given, ``:memory:``, else the path of an SQLite file."""
    if "://" in history:
        return history
    return "sqlite://" if history == ":memory:" else f"sqlite:///{history}"


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
    """Sessions in the database of ``history`` (see :func:`database_url`); safe across threads.

    Raises ValueError naming the database if it cannot be opened.
    """

    def __init__(self, history: str) -> None:
        url = database_url(history)
        memory = url == "sqlite://"
        try:
            # One shared connection for an in-memory SQLite (each new one would be another, empty database).
            self._engine: Engine = sa.create_engine(
                url, poolclass=StaticPool if memory else None,
                connect_args={"check_same_thread": False} if url.startswith("sqlite") else {})
            with self._engine.begin() as db:
                _META.create_all(db)
                columns = {c["name"] for c in sa.inspect(db).get_columns("sessions")}
                for name in _ADDED:
                    if name not in columns:
                        db.execute(sa.text(f"ALTER TABLE sessions ADD COLUMN {name} {_SESSIONS.c[name].type}"))
        except (sa.exc.SQLAlchemyError, ImportError) as exc:
            shown = sa.engine.make_url(url).render_as_string(hide_password=True) if "://" in url else url
            raise ValueError(f"history database {shown}: {exc}") from None
        self._lock = threading.Lock()

    def close(self) -> None:
        """Close the database connections."""
        with self._lock:
            self._engine.dispose()

    def _write(self, sid: str, **values: Any) -> None:
        with self._lock, self._engine.begin() as db:
            db.execute(_SESSIONS.update().where(_SESSIONS.c.id == sid).values(**values))

    def _read(self, query: sa.Select[Any]) -> list[RowMapping]:
        with self._lock, self._engine.connect() as db:
            return list(db.execute(query).mappings())

    def begin(self, sid: str, loop: str, user: str, request: dict[str, Any]) -> None:
        """Record a session that starts now on ``loop``, asked by ``user`` with ``request`` (settings in force)."""
        with self._lock, self._engine.begin() as db:
            db.execute(_SESSIONS.insert().values(id=sid, loop=loop, user=user, started_at=now(), state="running",
                                                 request=json.dumps(request)))

    def saved(self, sid: str, saved: LoopState, relay_levels: tuple[float, ...] = ()) -> None:
        """Record the loop's state before session ``sid`` touches it (what a restart after a crash restores), and
        the MV levels the experiment will hold it at (``relay_levels``: how a restart tells the loop as the session
        left it from one an operator changed)."""
        self._write(sid, saved=json.dumps({**state_json(saved), "relay_levels": [float(x) for x in relay_levels]}))

    def finish(self, sid: str, result: dict[str, Any], gains_after: Gains | None,
               trace: dict[str, list[float]] | None, state: str = "finished", applied_by: str | None = None) -> None:
        """Record the end of session ``sid``: the result JSON, the controller's gains after it and the trace.

        ``applied_by``: who had the designed gains written at the end of the
        session (the session's user, when it asked to apply them and they
        were written); None if they were not.
        """
        at = now()
        self._write(sid, finished_at=at, state=state, result=json.dumps(result, allow_nan=False),
                    gains_after=None if gains_after is None else json.dumps(gains_after.as_json()),
                    trace=None if trace is None else json.dumps(trace, allow_nan=False),
                    applied_at=None if applied_by is None else at, applied_by=applied_by)

    def restored(self, sid: str, state: str, message: str, code: int | None = None) -> None:
        """A ``not_restored`` session whose loop has now been dealt with: its final ``state``, a message that says
        how (appended to the result's message) and, if given, the result's new ``code`` (te stays true)."""
        rows = self._read(sa.select(_SESSIONS.c.result).where(_SESSIONS.c.id == sid))
        result = _load(rows[0]["result"]) if rows else None
        values: dict[str, Any] = {"state": state}
        if result is not None:
            result["message"] = f"{result['message']}; {message}"
            if code is not None:
                result["ite"] = code
            values["result"] = json.dumps(result, allow_nan=False)
        self._write(sid, **values)

    def not_restored(self) -> list[dict[str, Any]]:
        """Sessions whose loops were not handed back (the daemon retries them)."""
        rows = self._read(sa.select(_SESSIONS).where(_SESSIONS.c.state == "not_restored")
                          .order_by(_SESSIONS.c.started_at))
        return [_record(row, with_trace=False) for row in rows]

    def applied(self, sid: str, user: str, gains_after: Gains) -> None:
        """Record that ``user`` had the gains of session ``sid`` written now; ``gains_after``: read back."""
        self._write(sid, applied_at=now(), applied_by=user, gains_after=json.dumps(gains_after.as_json()))

    def latest(self, loop: str) -> dict[str, Any] | None:
        """The newest finished (or interrupted) session of ``loop``, without its trace, or None."""
        rows = self._read(sa.select(_SESSIONS).where(_SESSIONS.c.loop == loop, _SESSIONS.c.finished_at.is_not(None))
                          .order_by(*_NEWEST_FIRST).limit(1))
        return _record(rows[0], with_trace=False) if rows else None

    def running(self) -> list[dict[str, Any]]:
        """Sessions recorded as running (after a crash: the ones whose loops must be put back)."""
        rows = self._read(sa.select(_SESSIONS).where(_SESSIONS.c.state == "running")
                          .order_by(_SESSIONS.c.started_at))
        return [_record(row, with_trace=False) for row in rows]

    def of_loop(self, loop: str, limit: int = 100) -> list[dict[str, Any]]:
        """The latest ``limit`` sessions of ``loop``, newest first, without their traces."""
        rows = self._read(sa.select(_SESSIONS).where(_SESSIONS.c.loop == loop).order_by(*_NEWEST_FIRST)
                          .limit(limit))
        return [_record(row, with_trace=False) for row in rows]

    def get(self, sid: str) -> dict[str, Any] | None:
        """Session ``sid`` in full, or None."""
        rows = self._read(sa.select(_SESSIONS).where(_SESSIONS.c.id == sid))
        return _record(rows[0], with_trace=True) if rows else None


def _load(text: str | None) -> Any:
    return None if text is None else json.loads(text)


def _record(row: RowMapping, with_trace: bool) -> dict[str, Any]:
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
