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

A gains write is recorded twice: its *intent* (the gains about to be
written, who asked, when) before the write, and its outcome after it (the
gains read back, applied or not) — so a daemon killed between the two leaves
an open intent, which the next start reconciles with the gains read back from
the device (:meth:`History.open_intents`, :meth:`History.resolve_intent`):
history and device agree.

A write that fails because the database is busy (an SQLite file locked by
another process) is retried with growing pauses for ``retry_for`` seconds,
each failure logged; the daemon calls these methods from a worker thread,
never from its event loop.

Records are plain JSON-able dicts; times are UTC ISO 8601 strings (they sort
as text). JSON is stored as text, so the one table works on every database
SQLAlchemy Core speaks.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from datetime import UTC, datetime
from typing import Any

import sqlalchemy as sa
from sqlalchemy.engine import Engine, RowMapping
from sqlalchemy.pool import StaticPool

from autotuner.engine.control.gains import Gains
from drivers.link import LoopState, Mode

from autotuner.engine.result import ResultRecord, Trace
from autotuner.service.session_record import TRACE_POINTS


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
    sa.Column("gains_intent", sa.Text),
    sa.Index("sessions_by_loop", "loop", "started_at"),
)
# Columns added since the first schema, added to an older database when it is opened.
_ADDED = ("applied_at", "applied_by", "gains_intent")
# How long a write that fails on a busy database is retried, seconds (each try waits SQLite's busy timeout).
WRITE_RETRY_FOR = 120.0
# SQLite's own wait for a lock per try, seconds (its default, 5 s, is what stalled every loop when run inline).
SQLITE_BUSY_TIMEOUT = 1.0

log = logging.getLogger("autotuner.service.history")
# Newest first; the id breaks a tie of two sessions started in the same microsecond.
_NEWEST_FIRST = (_SESSIONS.c.started_at.desc(), _SESSIONS.c.id.desc())


def database_url(history: str) -> str:
    """The SQLAlchemy URL of a config's ``history``: a URL as given, ``:memory:``, else the path of an SQLite file."""
    if "://" in history:
        return history
    return "sqlite://" if history == ":memory:" else f"sqlite:///{history}"


def sqlite_file(url: str) -> str | None:
    """The file of an SQLite URL (``sqlite:///path``), None for any other database or for :memory:."""
    if not url.startswith("sqlite:///"):
        return None
    path = url[len("sqlite:///"):]
    return path if path and path != ":memory:" else None


def shown_url(url: str) -> str:
    """``url`` fit for a message: its password masked."""
    if "://" not in url:
        return url
    try:
        return sa.engine.make_url(url).render_as_string(hide_password=True)
    except (sa.exc.ArgumentError, ValueError):
        return "(a database URL that cannot be parsed)"


def database_password(url: str) -> str | None:
    """The password in the database ``url``, None if it has none (or is a file)."""
    try:
        password = sa.engine.make_url(url).password if "://" in url else None
    except (sa.exc.ArgumentError, ValueError):
        return None
    return None if password is None else str(password)


def mask(text: str, url: str) -> str:
    """``text`` with the password of the database ``url`` (if any) masked, wherever it appears."""
    password = database_password(url)
    return text.replace(password, "***") if password else text


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
    return trace.thinned(points)


class History:
    """Sessions in the database of ``history`` (see :func:`database_url`); safe across threads.

    Raises ValueError naming the database if it cannot be opened — the
    message masks a password — and for an SQLite file that is damaged (its
    integrity check fails) or empty: a zero-byte file, as a bind mount often
    pre-creates, is initialised only with ``init_empty`` (``serve
    --init-history``), since an empty file in place of a history is more often
    a mistake than a wish. A file that does not exist is created.
    """

    def __init__(self, history: str, retry_for: float = WRITE_RETRY_FOR, init_empty: bool = False) -> None:
        url = database_url(history)
        memory = url == "sqlite://"
        self.retry_for = retry_for
        file = sqlite_file(url)
        self.shown = file or shown_url(url)
        if file is not None and not init_empty and os.path.isfile(file) and os.path.getsize(file) == 0:
            raise ValueError(f"history database {file} is an empty file (0 bytes), not a history: if it is new "
                             "(a bind mount pre-creates one), start once with --init-history to initialise it")
        try:
            # One shared connection for an in-memory SQLite (each new one would be another, empty database).
            sqlite = {"check_same_thread": False, "timeout": SQLITE_BUSY_TIMEOUT}
            self._engine: Engine = sa.create_engine(
                url, poolclass=StaticPool if memory else None,
                connect_args=sqlite if url.startswith("sqlite") else {})
            with self._engine.begin() as db:
                if file is not None:
                    problems = [row[0] for row in db.execute(sa.text("PRAGMA quick_check"))]
                    if problems != ["ok"]:
                        shown = "; ".join(" ".join(str(p).split()) for p in problems[:3])
                        raise ValueError(f"history database {file} is damaged ({shown}): "
                                         "restore it from a backup, or move it away to start a new one")
                _META.create_all(db)
                columns = {c["name"] for c in sa.inspect(db).get_columns("sessions")}
                for name in _ADDED:
                    if name not in columns:
                        db.execute(sa.text(f"ALTER TABLE sessions ADD COLUMN {name} {_SESSIONS.c[name].type}"))
        except sa.exc.DatabaseError as exc:
            reason = mask(str(exc.orig) if exc.orig is not None else str(exc), url)
            hint = "" if file is None else ": restore it from a backup, or move it away to start a new one"
            raise ValueError(f"history database {self.shown}: {reason}{hint}") from None
        except (sa.exc.SQLAlchemyError, ImportError) as exc:
            raise ValueError(f"history database {self.shown}: {mask(str(exc), url)}") from None
        self._lock = threading.Lock()

    def close(self) -> None:
        """Close the database connections."""
        with self._lock:
            self._engine.dispose()

    def _retried(self, what: str, write: Callable[[], None]) -> None:
        """Run ``write``; on a database error retry with growing pauses for ``retry_for`` s (logged), then raise."""
        deadline = time.monotonic() + self.retry_for
        pause, failures = 0.05, 0
        while True:
            try:
                with self._lock:
                    write()
            except sa.exc.OperationalError as exc:
                failures += 1
                reason = str(exc.orig) if exc.orig is not None else str(exc)
                if time.monotonic() + pause > deadline:
                    log.error("history %s: %s failed %d times (%s); given up", self.shown, what, failures, reason)
                    raise
                log.warning("history %s: %s failed (%s); retrying in %.1f s", self.shown, what, reason, pause)
                time.sleep(pause)
                pause = min(2.0 * pause, 5.0)
            else:
                if failures:
                    log.info("history %s: %s written after %d failed tries", self.shown, what, failures)
                return

    def _write(self, sid: str, **values: Any) -> None:
        def write() -> None:
            with self._engine.begin() as db:
                db.execute(_SESSIONS.update().where(_SESSIONS.c.id == sid).values(**values))

        self._retried(f"session {sid}: {', '.join(values)}", write)

    def _read(self, query: sa.Select[Any]) -> list[RowMapping]:
        with self._lock, self._engine.connect() as db:
            return list(db.execute(query).mappings())

    def begin(self, sid: str, loop: str, user: str, request: dict[str, Any]) -> None:
        """Record a session that starts now on ``loop``, asked by ``user`` with ``request`` (settings in force)."""
        started = now()

        def write() -> None:
            with self._engine.begin() as db:
                db.execute(_SESSIONS.insert().values(id=sid, loop=loop, user=user, started_at=started,
                                                     state="running", request=json.dumps(request)))

        self._retried(f"session {sid}: begin", write)

    def saved(self, sid: str, saved: LoopState, relay_levels: tuple[float, ...] = (),
              mv_range: tuple[float, float] | None = None) -> None:
        """Record the loop's state before session ``sid`` touches it (what a restart after a crash restores), the
        MV levels the experiment will hold it at (``relay_levels``) and the range (low, high) of every MV the
        session may write (``mv_range``, MV units; recorded again, wider, before an MV outside it is written):
        how a restart tells the loop as the session left it from one an operator changed."""
        record = {**state_json(saved), "relay_levels": [float(x) for x in relay_levels]}
        if mv_range is not None:
            record["mv_range"] = [float(mv_range[0]), float(mv_range[1])]
        self._write(sid, saved=json.dumps(record))

    def finish(self, sid: str, result: ResultRecord, gains_after: Gains | None,
               trace: dict[str, list[float]] | None, state: str = "finished", applied_by: str | None = None) -> None:
        """Record the end of session ``sid``: its result, the controller's gains after it and the trace.

        ``applied_by``: who had the designed gains written at the end of the
        session (the session's user, when it asked to apply them and they
        were written); None if they were not. A gains intent stays open
        unless the gains after are known (read back, or what was written).
        """
        at = now()
        values: dict[str, Any] = {}
        if gains_after is not None:
            values["gains_intent"] = None
        self._write(sid, finished_at=at, state=state, result=json.dumps(result.to_json(), allow_nan=False),
                    gains_after=None if gains_after is None else json.dumps(gains_after.as_json()),
                    trace=None if trace is None else json.dumps(trace, allow_nan=False),
                    applied_at=None if applied_by is None else at, applied_by=applied_by, **values)

    def intend(self, sid: str, user: str, gains: Gains) -> None:
        """Record, before they are written, that ``user`` has the ``gains`` of session ``sid`` written now."""
        self._write(sid, gains_intent=json.dumps({"gains": gains.as_json(), "by": user, "at": now()}))

    def restored(self, sid: str, state: str, message: str, code: int | None = None) -> None:
        """A ``not_restored`` session whose loop has now been dealt with: its final ``state``, a message that says
        how (appended to the result's message) and, if given, the result's new ``code`` (te stays true)."""
        rows = self._read(sa.select(_SESSIONS.c.result).where(_SESSIONS.c.id == sid))
        result = _result(rows[0]["result"]) if rows else None
        values: dict[str, Any] = {"state": state}
        if result is not None:
            result = replace(result, message=f"{result.message}; {message}", ite=result.ite if code is None else code)
            values["result"] = json.dumps(result.to_json(), allow_nan=False)
        self._write(sid, **values)

    def not_restored(self) -> list[dict[str, Any]]:
        """Sessions whose loops were not handed back (the daemon retries them)."""
        rows = self._read(sa.select(_SESSIONS).where(_SESSIONS.c.state == "not_restored")
                          .order_by(_SESSIONS.c.started_at))
        return [_record(row, with_trace=False) for row in rows]

    def applied(self, sid: str, user: str, gains_after: Gains) -> None:
        """Record that ``user`` had the gains of session ``sid`` written now; ``gains_after``: read back."""
        self._write(sid, applied_at=now(), applied_by=user, gains_after=json.dumps(gains_after.as_json()),
                    gains_intent=None)

    def open_intents(self) -> list[dict[str, Any]]:
        """Sessions whose gains write was intended but whose outcome was never recorded (a crash between)."""
        rows = self._read(sa.select(_SESSIONS).where(_SESSIONS.c.gains_intent.is_not(None))
                          .order_by(_SESSIONS.c.started_at))
        return [_record(row, with_trace=False) for row in rows]

    def resolve_intent(self, sid: str, read_back: Gains, applied: bool) -> None:
        """Close session ``sid``'s open intent with the gains ``read_back`` from the device.

        ``applied``: they are the intended gains, so the write happened: recorded
        as applied by whoever intended it, at the intent's time. Else the
        device never got them: only the gains after are recorded.
        """
        record = self.get(sid)
        intent = None if record is None else record["gains_intent"]
        values: dict[str, Any] = {"gains_after": json.dumps(read_back.as_json()), "gains_intent": None}
        if applied and intent is not None:
            values.update(applied_at=intent["at"], applied_by=intent["by"])
        self._write(sid, **values)

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


def _result(text: str | None) -> ResultRecord | None:
    return None if text is None else ResultRecord.from_json(json.loads(text))


def _record(row: RowMapping, with_trace: bool) -> dict[str, Any]:
    """A session's row as a dict of its columns, decoded (``result``: a :class:`ResultRecord`)."""
    saved = _load(row["saved"])
    result = _result(row["result"])
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
        "outcome": None if result is None else ("success" if not result.te else "failure"),
        "code": None if result is None else result.ite,
        "message": None if result is None else result.message,
        "result": result,
        "applied_at": row["applied_at"],
        "applied_by": row["applied_by"],
        "gains_intent": _load(row["gains_intent"]),
    }
    if with_trace:
        record["trace"] = _load(row["trace"])
    return record
