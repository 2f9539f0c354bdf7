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

A write that fails (an SQLite file locked by another process, a full disk,
a database server gone) is retried with growing pauses until it is written
(``retry_for``: ``tune --config`` gives up sooner) — a session's record given
up would lose the session. The outage is logged once when it starts and once
when it ends, and :attr:`History.error` says it meanwhile (the daemon shows it
in every loop's status). A record that must be durable *before* a write it
guards (the saved state before the loop is touched, a gains intent before
the gains) carries a deadline, its caller's: past it, it is dropped, never
written late (:class:`Late`). The daemon calls these methods from a worker
thread, never from its event loop.

Sessions are ordered by ``seq``, a number the database assigns when the
session is recorded (one more than the largest), never by a clock: a wall
clock stepped back does not make a new session older. Records are plain
JSON-able dicts; times are UTC ISO 8601 strings, for display. JSON is stored
as text, so the one table works on every database SQLAlchemy Core speaks.
"""

from __future__ import annotations

import json
import logging
import math
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
from autotuner.service.schema import create_tables
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
    # The history's order: assigned by the database when the session is recorded (one more than the largest so
    # far), never read from a clock — a wall clock stepped back must not make a new session older than an old one.
    sa.Column("seq", sa.BigInteger),
    sa.Index("sessions_by_loop", "loop", "started_at"),
)
# Each loop's health assessments (docs/health.md, "Online"), the newest HEALTH_KEPT per loop: when (unix s), the
# summary's fields, the newest tuning session before it and the assessment's JSON (Assessment.to_json()).
_HEALTH = sa.Table(
    "health", _META,
    sa.Column("id", sa.BigInteger().with_variant(sa.Integer, "sqlite"), primary_key=True, autoincrement=True),
    sa.Column("loop", sa.String(64), nullable=False),
    sa.Column("time", sa.Float, nullable=False),
    sa.Column("severity", sa.String(8), nullable=False),
    sa.Column("recommendation", sa.String(16), nullable=False),
    sa.Column("flags", sa.Text, nullable=False),
    sa.Column("session", sa.String(64)),
    sa.Column("assessment", sa.Text, nullable=False),
    sa.Index("health_by_loop", "loop", "id"),
)
HEALTH_KEPT = 1000
# Indexes of the order, created on an older database too (create_all makes a table's indexes only with the table).
_SEQ_INDEXES = (sa.Index("sessions_seq", _SESSIONS.c.seq, unique=True),
                sa.Index("sessions_by_loop_seq", _SESSIONS.c.loop, _SESSIONS.c.seq))
# Columns added since the first schema, added to an older database when it is opened.
_ADDED = ("applied_at", "applied_by", "gains_intent", "seq")
# How long a write that fails on a busy database is retried, seconds (each try waits SQLite's busy timeout): the
# daemon's until it is written — a session's record given up would lose the session; what may not be written late
# carries a deadline instead (History._retried).
WRITE_RETRY_FOR = math.inf
# Longest pause between two tries of a failing write, seconds.
RETRY_PAUSE_MAX = 5.0
# SQLite's own wait for a lock per try, seconds (its default, 5 s, is what stalled every loop when run inline).
SQLITE_BUSY_TIMEOUT = 1.0

log = logging.getLogger("autotuner.service.history")
# Newest first: by the order the database assigned (timestamps are for display only).
_NEWEST_FIRST = (_SESSIONS.c.seq.desc(),)
_OLDEST_FIRST = (_SESSIONS.c.seq.asc(),)
# The next place in the order, computed by the database in the session's INSERT.
_NEXT_SEQ = sa.select(sa.func.coalesce(sa.func.max(_SESSIONS.c.seq), 0) + 1).scalar_subquery()


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


def _upgrade(db: sa.Connection) -> None:
    """Bring an older database's table up to this schema: the columns added since, and the order (``seq``) of
    sessions recorded without one, given in the order they started (their ``started_at``, then id)."""
    columns = {c["name"] for c in sa.inspect(db).get_columns("sessions")}
    for name in _ADDED:
        if name not in columns:
            type_ = _SESSIONS.c[name].type.compile(db.dialect)
            db.execute(sa.text(f"ALTER TABLE sessions ADD COLUMN {name} {type_}"))
    unordered = db.execute(sa.select(_SESSIONS.c.id).where(_SESSIONS.c.seq.is_(None))
                           .order_by(_SESSIONS.c.started_at, _SESSIONS.c.id)).scalars().all()
    if unordered:
        last = db.execute(sa.select(sa.func.coalesce(sa.func.max(_SESSIONS.c.seq), 0))).scalar_one()
        db.execute(_SESSIONS.update().where(_SESSIONS.c.id == sa.bindparam("sid")).values(seq=sa.bindparam("n")),
                   [{"sid": sid, "n": last + i} for i, sid in enumerate(unordered, start=1)])
    for index in _SEQ_INDEXES:
        index.create(db, checkfirst=True)


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
        self.on_error: Callable[[str | None], None] | None = None
        self._error: str | None = None
        self._outage = 0.0
        self._stopping = False
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
                create_tables(db, _META)
                _upgrade(db)
        except sa.exc.DatabaseError as exc:
            reason = mask(str(exc.orig) if exc.orig is not None else str(exc), url)
            hint = ("" if file is None else
                    # (a backup or another tool holding it: the file is sound, moving it away would lose the history)
                    ": another process holds it locked; start again once that process lets go" if "locked" in reason
                    else ": restore it from a backup, or move it away to start a new one")
            raise ValueError(f"history database {self.shown}: {reason}{hint}") from None
        except (sa.exc.SQLAlchemyError, ImportError) as exc:
            raise ValueError(f"history database {self.shown}: {mask(str(exc), url)}") from None
        self._lock = threading.Lock()

    def close(self) -> None:
        """Close the database connections."""
        with self._lock:
            self._engine.dispose()

    def stop_retrying(self) -> None:
        """A write that fails from now on is given up at once (the daemon exits: a write retried until the
        database is back would keep the process from ending); each one given up is logged."""
        self._stopping = True

    def _retried(self, what: str, write: Callable[[sa.Connection], None], deadline: float | None = None) -> None:
        """Run ``write`` in a transaction; on a database error (locked, disk full, server gone) try again with
        growing pauses until it is written, or ``retry_for`` s have passed (then raise).

        ``deadline`` (monotonic seconds): the write is for a caller that gives
        up then (a record that must be durable before the write it guards):
        past it no try starts and no transaction commits — it raises
        :class:`Late`, logged — so a write refused to its caller is never
        written afterwards. The first failure of an outage is logged once, with
        the database and the reason, and so is the first success after it
        (:attr:`error` says meanwhile).
        """
        give_up = time.monotonic() + self.retry_for
        pause, failures = 0.05, 0
        while True:
            try:
                with self._lock:
                    if deadline is not None and time.monotonic() > deadline:
                        raise Late(f"{what}: its deadline passed before it could be written")
                    with self._engine.begin() as db:
                        write(db)
                        if deadline is not None and time.monotonic() > deadline:  # rolled back, never committed
                            raise Late(f"{what}: its deadline passed before it was committed")
            except Late as late:
                log.warning("history %s: %s; dropped, never to be written (its caller was told so)", self.shown,
                            late)
                raise
            except (sa.exc.OperationalError, _Contended) as exc:
                failures += 1
                self._failed(what, _reason(exc))
                if self._stopping or time.monotonic() + pause > give_up:
                    log.error("history %s: %s failed %d times; given up%s: NOT RECORDED", self.shown, what, failures,
                              " (the daemon stops)" if self._stopping else "")
                    raise
                log.debug("history %s: %s failed (%s); retrying in %.1f s", self.shown, what, _reason(exc), pause)
                time.sleep(pause)
                pause = min(2.0 * pause, RETRY_PAUSE_MAX)
            else:
                self._succeeded(what, failures)
                return

    def _failed(self, what: str, reason: str) -> None:
        """A write failed: the first failure of an outage is logged and reported (:attr:`error`)."""
        if self._error is None:
            self._error = f"history {self.shown}: writes fail since {now()}: {reason}"
            self._outage = time.monotonic()
            log.error("history %s: %s failed (%s); every write is retrying until it succeeds (logged again once "
                      "they do)", self.shown, what, reason)
            self._report(self._error)

    def _succeeded(self, what: str, failures: int) -> None:
        """A write went through: the end of an outage is logged and reported."""
        if self._error is not None:
            log.warning("history %s: writes succeed again after %.0f s (%s written after %d failed tries)",
                        self.shown, time.monotonic() - self._outage, what, failures)
            self._error = None
            self._report(None)

    def _report(self, error: str | None) -> None:
        if self.on_error is not None:
            self.on_error(error)

    @property
    def error(self) -> str | None:
        """Why the history cannot write now (its path or masked URL, since when, the database's reason: ``database
        or disk is full``, ``database is locked``, ...); None while writes go through."""
        return self._error

    def _write(self, sid: str, deadline: float | None = None, **values: Any) -> None:
        def write(db: sa.Connection) -> None:
            if db.execute(_SESSIONS.update().where(_SESSIONS.c.id == sid).values(**values)).rowcount == 0:
                raise LookupError(f"session {sid} is not in the history (its begin was not recorded)")

        self._retried(f"session {sid}: {', '.join(values)}", write, deadline)

    def _read(self, query: sa.Select[Any]) -> list[RowMapping]:
        """The rows of ``query``; :class:`Unavailable` if the database cannot answer (locked, gone)."""
        try:
            with self._lock, self._engine.connect() as db:
                return list(db.execute(query).mappings())
        except sa.exc.OperationalError as exc:
            raise Unavailable(f"history {self.shown}: {_reason(exc)}") from None

    def begin(self, sid: str, loop: str, user: str, request: dict[str, Any]) -> None:
        """Record a session that starts now on ``loop``, asked by ``user`` with ``request`` (settings in force)."""
        started = now()

        def write(db: sa.Connection) -> None:
            try:
                db.execute(_SESSIONS.insert().values(id=sid, loop=loop, user=user, started_at=started,
                                                     state="running", request=json.dumps(request), seq=_NEXT_SEQ))
            except sa.exc.IntegrityError:
                # Another writer (``tune --config`` beside the daemon, on PostgreSQL) took the same place in the
                # order at the same time: its unique index refused ours; a new try takes the next one. (A try
                # whose commit went through although it reported an error finds its row there.)
                with self._engine.connect() as other:
                    if other.execute(sa.select(_SESSIONS.c.id).where(_SESSIONS.c.id == sid)).first() is None:
                        raise _Contended("another writer took the same place in the order") from None

        self._retried(f"session {sid}: begin", write)

    def saved(self, sid: str, saved: LoopState, relay_levels: tuple[float, ...] = (),
              mv_range: tuple[float, float] | None = None, deadline: float | None = None) -> None:
        """Record the loop's state before session ``sid`` touches it (what a restart after a crash restores), the
        MV levels the experiment will hold it at (``relay_levels``) and the range (low, high) of every MV the
        session may write (``mv_range``, MV units; recorded again, wider, before an MV outside it is written):
        how a restart tells the loop as the session left it from one an operator changed. ``deadline``: see
        :meth:`_retried` (the session touches the loop only once this is recorded; past it, never recorded)."""
        record = {**state_json(saved), "relay_levels": [float(x) for x in relay_levels]}
        if mv_range is not None:
            record["mv_range"] = [float(mv_range[0]), float(mv_range[1])]
        self._write(sid, deadline, saved=json.dumps(record))

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

    def intend(self, sid: str, user: str, gains: Gains, deadline: float | None = None) -> None:
        """Record, before they are written, that ``user`` has the ``gains`` of session ``sid`` written now.
        ``deadline``: see :meth:`_retried` (the gains are written only once this is recorded; past it, never
        recorded)."""
        self._write(sid, deadline, gains_intent=json.dumps({"gains": gains.as_json(), "by": user, "at": now()}))

    def withdraw(self, sid: str, gains: Gains) -> None:
        """Close session ``sid``'s intent to write ``gains`` (if it is still open) without a write: the intent
        came in after its caller had given up on it, so the gains were never written."""
        intent = json.dumps({"gains": gains.as_json()})[:-1]  # the start of the intent's JSON: {"gains": {...}

        def write(db: sa.Connection) -> None:
            still_open = _SESSIONS.c.gains_intent.startswith(intent, autoescape=True)
            db.execute(_SESSIONS.update().where(_SESSIONS.c.id == sid, still_open).values(gains_intent=None))

        self._retried(f"session {sid}: intent withdrawn", write)

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
                          .order_by(*_OLDEST_FIRST))
        return [_record(row, with_trace=False) for row in rows]

    def applied(self, sid: str, user: str, gains_after: Gains) -> None:
        """Record that ``user`` had the gains of session ``sid`` written now; ``gains_after``: read back."""
        self._write(sid, applied_at=now(), applied_by=user, gains_after=json.dumps(gains_after.as_json()),
                    gains_intent=None)

    def open_intents(self) -> list[dict[str, Any]]:
        """Sessions whose gains write was intended but whose outcome was never recorded (a crash between)."""
        rows = self._read(sa.select(_SESSIONS).where(_SESSIONS.c.gains_intent.is_not(None))
                          .order_by(*_OLDEST_FIRST))
        return [_record(row, with_trace=False) for row in rows]

    def resolve_intent(self, sid: str, read_back: Gains, applied: bool) -> None:
        """Close session ``sid``'s open intent with the gains ``read_back`` from the device.

        ``applied``: they are the intended gains, so the write happened: recorded
        as applied by whoever intended it, at the intent's time, with them as the
        gains after. Else the device never got them: the intent is closed, and the
        gains after are recorded only if the session had none (it died before its
        end) — a write that never happened does not rewrite a session's gains after.
        """
        record = self.get(sid)
        intent = None if record is None else record["gains_intent"]
        values: dict[str, Any] = {"gains_intent": None}
        if applied and intent is not None:
            values.update(applied_at=intent["at"], applied_by=intent["by"])
        if applied or record is None or record["gains_after"] is None:
            values["gains_after"] = json.dumps(read_back.as_json())
        self._write(sid, **values)

    def latest(self, loop: str) -> dict[str, Any] | None:
        """The newest finished (or interrupted) session of ``loop``, without its trace, or None."""
        rows = self._read(sa.select(_SESSIONS).where(_SESSIONS.c.loop == loop, _SESSIONS.c.finished_at.is_not(None))
                          .order_by(*_NEWEST_FIRST).limit(1))
        return _record(rows[0], with_trace=False) if rows else None

    def running(self) -> list[dict[str, Any]]:
        """Sessions recorded as running (after a crash: the ones whose loops must be put back)."""
        rows = self._read(sa.select(_SESSIONS).where(_SESSIONS.c.state == "running")
                          .order_by(*_OLDEST_FIRST))
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


    def add_health(self, loop: str, assessment: dict[str, Any], severity: str, session: str | None) -> None:
        """Record an assessment of ``loop`` (its JSON with ``time``, unix s), its worst ``severity`` and the
        newest tuning ``session`` before it; the loop's assessments beyond the newest :data:`HEALTH_KEPT` go."""
        def write(db: sa.Connection) -> None:
            db.execute(_HEALTH.insert().values(
                loop=loop, time=assessment["time"], severity=severity, recommendation=assessment["recommendation"],
                flags=json.dumps(assessment["flags"]), session=session,
                assessment=json.dumps(assessment, allow_nan=False)))
            oldest_kept = (sa.select(_HEALTH.c.id).where(_HEALTH.c.loop == loop).order_by(_HEALTH.c.id.desc())
                           .offset(HEALTH_KEPT - 1).limit(1).scalar_subquery())
            db.execute(_HEALTH.delete().where(_HEALTH.c.loop == loop, _HEALTH.c.id < oldest_kept))

        self._retried(f"loop {loop}: health", write)

    def health_of(self, loop: str, limit: int = 100, before: float | None = None) -> list[dict[str, Any]]:
        """The newest ``limit`` assessments of ``loop`` (made before unix time ``before``, if given), newest
        first: ``{"time", "state", "severity", "flags", "recommendation", "session", "assessment"}``."""
        query = sa.select(_HEALTH).where(_HEALTH.c.loop == loop)
        if before is not None:
            query = query.where(_HEALTH.c.time < before)
        rows = self._read(query.order_by(_HEALTH.c.id.desc()).limit(limit))
        return [{"time": row["time"], "state": "ok", "severity": row["severity"], "flags": json.loads(row["flags"]),
                 "recommendation": row["recommendation"], "session": row["session"],
                 "assessment": json.loads(row["assessment"])} for row in rows]


class Unavailable(Exception):
    """A read the database could not answer (an SQLite file locked by another process, a server gone)."""


class Late(Exception):
    """A write dropped because its deadline passed (its caller had given up on it): it is never written."""


class _Contended(Exception):
    """A session's INSERT lost its place in the order to another writer's at the same time (tried again)."""


def _reason(exc: Exception) -> str:
    """What a failed write says: the database driver's message when there is one."""
    orig = getattr(exc, "orig", None)
    return str(orig) if orig is not None else str(exc)


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
        "seq": row["seq"],
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
