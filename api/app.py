"""The FastAPI application of the daemon: the REST API of design.md under ``/api/v1``.

``create_app(config)`` builds it; its lifespan opens the history, starts the
:class:`~autotuner.service.daemon.LoopManager` (simulated plants, crash recovery) and
on shutdown aborts running experiments and hands their loops back. Served by
:func:`api.server.serve`, SIGTERM/SIGINT do that *before* uvicorn waits for
open connections (docs/handback.md). Reads need a viewer token, TUNE/TBRK/apply an operator;
``GET /api/v1/health`` needs none. The OpenAPI description is at
``/api/v1/openapi.json`` (interactive: ``/api/v1/docs``).
"""

from __future__ import annotations

import asyncio
import os
import pathlib
import socket
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, FastAPI, Path, Query, Request
from fastapi.responses import Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from starlette.datastructures import MutableHeaders
from starlette.routing import Match, Mount
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from autotuner import __version__
from autotuner.engine.design.analysis import analyse
from autotuner.engine.outcome import MESSAGES, WARNINGS, Code
from autotuner.service import heap
from autotuner.service.config import DaemonConfig, FleetConfig, Tuning, TuneRequest
from autotuner.service.daemon import LoopManager, Refused
from autotuner.service.daemon.recorder import HISTORY_WAIT, LATE_GRACE
from autotuner.service.daemon.sampler import SamplerField
from autotuner.service.daemon.fleet import Fleet
from autotuner.service.history import History, Unavailable, database_url
from autotuner.service.leases import Leases

from . import docs, errors
from .auth import Principal, Tokens, require
from .events import LIVE_PERIOD, OpenStreams, Overview, overview, stream
from .metrics import CONTENT_TYPE, exposition, registry_of
from .gate import RequestGate
from .models import (Accepted, Analysis, Applied, ApplyRequest, CodeOut, DrainRequest, FleetStatus, Health,
                     HealthHistoryItem, LoopHealthDetail, LoopHealthRow, LoopStatus, Session, SessionSummary, Whoami)
from .opcua import StartError, start_opcua

PREFIX = "/api/v1"
# The operator page (issue 7): static files using only the public API below.
STATIC = pathlib.Path(__file__).parent / "static"
# The page loads only its own files and talks only to this API; nobody may frame it (clickjacking of TUNE).
PAGE_POLICY = ("default-src 'self'; img-src 'self' data:; connect-src 'self'; frame-ancestors 'none'; "
               "base-uri 'none'; form-action 'self'; object-src 'none'")
# The error answers each endpoint can give, with their machine codes (ErrorBody.code), for the OpenAPI document.
_ERROR_TEXT = {
    400: "bad_request: the body is not JSON (or the client went away before sending it)",
    401: "unauthorized: no token, or a token the daemon does not know",
    403: "forbidden: the token's role is too low (viewer) for this operator action",
    404: "not_found: no loop (or session) with this id",
    413: "too_large: the request body is too large",
    422: "invalid: a field is out of range or unknown; the message names the field",
    503: "history_unavailable: the history did not answer within a few seconds (locked, its disk full, its server "
         "gone: the loops' history_error says why); retry later",
}


def _errors(*statuses: int, **more: str) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` for ``statuses`` (texts of :data:`_ERROR_TEXT`) and ``more`` (``e409="..."``)."""
    out: dict[int | str, dict[str, Any]] = {
        status: {"model": errors.ErrorBody, "description": _ERROR_TEXT[status]} for status in statuses}
    for key, text in more.items():
        out[int(key[1:])] = {"model": errors.ErrorBody, "description": text}
    return out


# Every endpoint but health answers 401 without a valid token; writes also 403, 400, 413 and 422.
_WRITE = (400, 403, 404, 413, 422)
LoopId = Annotated[str, Path(description="loop id from the config")]
# Analyses kept per app (a finished session's analysis never changes).
ANALYSES_KEPT = 64

router = APIRouter(prefix=PREFIX)
Viewer = Annotated[Principal, Depends(require("viewer"))]
Operator = Annotated[Principal, Depends(require("operator"))]
Admin = Annotated[Principal, Depends(require("admin"))]


def _manager(request: Request) -> LoopManager:
    return request.app.state.manager


Manager = Annotated[LoopManager, Depends(_manager)]


@router.get("/health", response_model=Health, tags=["health"])
async def health(manager: Manager) -> dict[str, Any]:
    """Liveness (no token needed)."""
    return {"status": "ok", "loops": len(manager.loops)}


@router.get("/codes", response_model=list[CodeOut], tags=["health"], responses=_errors(401))
async def codes(_: Viewer) -> list[dict[str, Any]]:
    """Every outcome code ``ite`` can show once a session has ended (a read like any other: viewer token)."""
    return [{"value": int(c), "name": c.name, "message": MESSAGES[c], "warning": c in WARNINGS} for c in Code]


@router.get("/whoami", response_model=Whoami, tags=["health"], responses=_errors(401))
async def whoami(who: Viewer) -> dict[str, str]:
    """The caller's token: its name and role (what the operator page enables)."""
    return {"name": who.name, "role": who.role}


@router.get("/loops", response_model=list[LoopStatus], tags=["loops"], responses=_errors(401))
async def loops(manager: Manager, _: Viewer) -> list[dict[str, Any]]:
    """All configured loops with their status."""
    return [loop.as_json() for loop in manager.loops.values()]


@router.get("/loops/{loop_id}", response_model=LoopStatus, tags=["loops"], responses=_errors(401, 404))
async def loop_status(loop_id: LoopId, manager: Manager, _: Viewer) -> dict[str, Any]:
    """One loop: tbsy, te, ite, stage, progress, last point and gains."""
    return manager.get(loop_id).as_json()


@router.post("/loops/{loop_id}/tune", response_model=Accepted, status_code=202, tags=["loops"],
             responses=_errors(401, *_WRITE, e409="busy, group_busy: the loop or its exclusion group is tuning; on a "
                               "fresh read of the loop, before it is touched: pv_out_of_limits, pv_invalid (not finite "
                               "or stale), link_unhealthy, device_busy (the device shows TBSY)"))
async def tune(loop_id: LoopId, manager: Manager, who: Operator,
               body: Annotated[TuneRequest, Body()] = TuneRequest()) -> dict[str, str]:
    """TUNE: start an experiment; fields left out take the loop's configured defaults."""
    return {"loop": loop_id, "session": await manager.request_tune(loop_id, body, who.name)}


@router.post("/loops/{loop_id}/break", response_model=Accepted, status_code=202, tags=["loops"],
             responses=_errors(401, 403, 404, e409="idle: the loop is not tuning (nothing to abort)"))
async def abort(loop_id: LoopId, manager: Manager, _: Operator) -> dict[str, str]:
    """TBRK: abort the running experiment; the loop is restored to its previous mode and MV."""
    return {"loop": loop_id, "session": manager.abort(loop_id)}


@router.post("/loops/{loop_id}/apply", response_model=Applied, tags=["loops"], responses={
    **_errors(401, *_WRITE),
    409: {"model": errors.ErrorBody,
          "description": "busy: the loop tunes (or is being written); nothing_to_apply: the session failed, has no "
                         "gains, or the loop has no finished session"},
    502: {"model": errors.ErrorBody, "description": "link: the gains could not be written to the controller"},
    503: {"model": errors.ErrorBody, "description": "history_unavailable: the history did not answer within a few "
                                                    "seconds (which session to write, or the intent to write its "
                                                    "gains, which must be recorded first): nothing was written, and "
                                                    "nothing of the request is recorded later"}})
async def apply(loop_id: LoopId, manager: Manager, who: Operator,
                body: Annotated[ApplyRequest, Body()] = ApplyRequest()) -> dict[str, Any]:
    """Write a session's designed gains to the controller (default: the loop's newest session) and read them back.

    Recorded in the history (``applied_at``, ``applied_by``, ``gains_after``).
    Writing the gains of an already applied session again is allowed.
    """
    try:
        return await manager.apply(loop_id, body.session, who.name)
    except Refused as refused:
        if refused.code == "link":
            raise errors.ApiError(502, "link", refused.message) from None
        raise


class EventStream(StreamingResponse):
    """A Server-Sent Events response (declared as ``text/event-stream`` in the OpenAPI document)."""

    media_type = "text/event-stream"


_EVENTS_DOC = """Server-Sent Events of the loop (`text/event-stream`), one JSON object per event:

- `state` (first, then on every change: start, stage, end, mode, gains, link error, apply): the loop's status,
  as `GET /loops/{id}`.
- `replay` (second, once): the trend the daemon keeps, as columns, oldest first: `session` (id or null), `time`
  (unix s), `t` (plant s since the session started; null for monitor readings), `pv`, `sp` (PV units), `mv`
  (MV units), `relay` (±1; null for monitor readings) — the running or last session's samples from its start,
  then the monitor's.
- `sample`: while tuning one per experiment sample: `t` (plant s), `time` (unix s), `pv`, `sp`, `mv`, `relay`,
  `filter_phase_deg` (degrees), `stage`, `progress` (0–1), `ite` (plant s left), `periods`; while idle one per
  monitor reading (every `monitor_period` wall seconds): `time`, `pv`, `sp`, `mv`, `mode`.
- `health`: the loop's health summary changed (as on `/events`).

A comment line (`: keep-alive`) every 15 s keeps an idle stream open. Non-finite numbers are sent as null."""

_EVENTS_EXAMPLE = ('event: state\ndata: {"id": "TIC-101", "tbsy": false, "te": false, "ite": 0, ...}\n\n'
                   'event: replay\ndata: {"session": null, "time": [1796161110.8], "t": [null], "pv": [50.0], '
                   '"sp": [50.0], "mv": [50.0], "relay": [null]}\n\n'
                   'event: sample\ndata: {"time": 1796161111.1, "pv": 50.0, "sp": 50.0, "mv": 50.0, "mode": "AUTO"}\n\n')


# One event of the stream: its type and its data (a JSON object, fields in the description above).
_EVENT_SCHEMA = {"type": "object", "required": ["event", "data"], "properties": {
    "event": {"type": "string", "enum": ["state", "replay", "sample", "health"], "description": "the event's type"},
    "data": {"type": "string", "description": "the event's JSON object"}}}


@router.get("/loops/{loop_id}/events", tags=["loops"], response_class=EventStream, description=_EVENTS_DOC,
            responses={200: {"content": {"text/event-stream": {"schema": _EVENT_SCHEMA,
                                                              "example": _EVENTS_EXAMPLE}},
                             "description": "state, replay and sample events"},
                       # JSON errors: declared by content type (a model here would take the route's event-stream type)
                       **{status: {"description": _ERROR_TEXT[status], "content": {"application/json": {
                           "schema": {"$ref": "#/components/schemas/ErrorBody"}}}} for status in (401, 404)}})
async def events(loop_id: LoopId, request: Request, manager: Manager, _: Viewer) -> StreamingResponse:
    """Server-Sent Events: ``state``, ``replay``, ``sample`` (the description lists their fields)."""
    manager.get(loop_id)  # 404 before the stream starts
    return EventStream(stream(manager, loop_id, request.app.state.streams), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


_OVERVIEW_DOC = f"""Server-Sent Events of every loop at once (`text/event-stream`), for an overview of all loops on one
connection (the operator page's; a browser opens at most 6 connections per server), one JSON object per event:

- `state`: first one for every loop (in the config's order), then on every change of any loop (as on
  `/loops/{{id}}/events`): the loop's status, as `GET /loops/{{id}}` (its `id` says which loop).
- `live`: a loop's newest `sample` (the fields of `/loops/{{id}}/events`' sample: an experiment sample while the
  loop tunes, a monitor reading while idle) with `loop`, its id — at most one per loop every {LIVE_PERIOD:g} s
  (the samples between are dropped; a `state` event carries the live values too).
- `health`: a loop's health summary changed (a new assessment; pending again when a tuning starts): `loop`, its
  id, and the summary's fields (`state`, `severity`, `rank`, `flags`, `recommendation`, `reason`, `time`), as the
  status's `health` and `GET /loop-health` (docs/health.md, "Online").

No `replay`: the trend is the loop's own stream. A comment line (`: keep-alive`) every 15 s keeps an idle stream
open. Non-finite numbers are sent as null. The stream ends when the daemon stops, after every loop's last state."""

_OVERVIEW_EXAMPLE = ('event: state\ndata: {"id": "TIC-101", "tbsy": false, "te": false, "ite": 0, ...}\n\n'
                     'event: state\ndata: {"id": "LIC-201", "tbsy": true, "te": false, "ite": 84.2, ...}\n\n'
                     'event: live\ndata: {"loop": "TIC-101", "time": 1796161111.1, "pv": 50.0, "sp": 50.0, '
                     '"mv": 50.0, "mode": "AUTO"}\n\n')

_OVERVIEW_SCHEMA = {**_EVENT_SCHEMA, "properties": {
    **_EVENT_SCHEMA["properties"],
    "event": {"type": "string", "enum": ["state", "live", "health"], "description": "the event's type"}}}


@router.get("/events", tags=["loops"], response_class=EventStream, description=_OVERVIEW_DOC,
            responses={200: {"content": {"text/event-stream": {"schema": _OVERVIEW_SCHEMA,
                                                              "example": _OVERVIEW_EXAMPLE}},
                             "description": "state, live and health events of every loop"},
                       401: {"description": _ERROR_TEXT[401], "content": {"application/json": {
                           "schema": {"$ref": "#/components/schemas/ErrorBody"}}}}})
async def all_events(request: Request, manager: Manager, _: Viewer) -> StreamingResponse:
    """Server-Sent Events of every loop: ``state``, ``live`` and ``health`` (the description lists their fields)."""
    return EventStream(overview(manager, request.app.state.overview, request.app.state.streams),
                       media_type="text/event-stream",
                       headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


async def _read_history(method: Any, *args: Any) -> Any:
    """``method(*args)`` of the history in a thread (never on the event loop), within ``HISTORY_WAIT`` +
    ``LATE_GRACE`` seconds; 503 history_unavailable if the database does not answer by then."""
    try:
        return await asyncio.wait_for(asyncio.to_thread(method, *args), HISTORY_WAIT + LATE_GRACE)
    except (TimeoutError, Unavailable) as exc:
        reason = str(exc) or f"no answer within {HISTORY_WAIT + LATE_GRACE:g} s"
        raise errors.ApiError(503, "history_unavailable", f"the history cannot be read now: {reason}") from None


@router.get("/loops/{loop_id}/history", response_model=list[SessionSummary], tags=["history"],
            responses=_errors(401, 404, 422, 503))
async def history(loop_id: LoopId, manager: Manager, _: Viewer,
                  limit: Annotated[int, Query(ge=1, le=1000, description="most sessions returned")] = 100,
                  ) -> list[dict[str, Any]]:
    """Past sessions of the loop, newest first (without traces)."""
    manager.get(loop_id)
    return await _read_history(manager.history.of_loop, loop_id, limit)


@router.get("/loop-health", response_model=list[LoopHealthRow], tags=["health"], responses=_errors(401))
async def loop_health(manager: Manager, _: Viewer) -> list[dict[str, Any]]:
    """Every configured loop's health summary, worst first (rank descending, then loop id): what the overview's
    health column shows (docs/health.md, "Online"). ``GET /health`` is the daemon's liveness."""
    rows = [{"loop": loop_id, "description": loop.config.description, **loop.health.summary()}
            for loop_id, loop in manager.loops.items()]
    return sorted(rows, key=lambda row: (-row["rank"], row["loop"]))


@router.get("/loops/{loop_id}/health", response_model=LoopHealthDetail, tags=["health"],
            responses=_errors(401, 404))
async def loop_health_detail(loop_id: LoopId, manager: Manager, _: Viewer) -> dict[str, Any]:
    """One loop's health in full: the newest assessment for its current gains (indices, flags, reasons,
    recommendation, window), the one before its newest tuning, and the evidence (the assessed window's samples,
    downsampled, with the oscillation's crossings) the page draws."""
    return manager.get(loop_id).health.detail()


@router.get("/loops/{loop_id}/health/history", response_model=list[HealthHistoryItem], tags=["health"],
            responses=_errors(401, 404, 422, 503))
async def loop_health_history(loop_id: LoopId, manager: Manager, _: Viewer,
                              limit: Annotated[int, Query(ge=1, le=1000, description="most assessments returned")]
                              = 100) -> list[dict[str, Any]]:
    """The loop's stored health assessments, newest first (the history keeps the newest 1000 per loop)."""
    manager.get(loop_id)
    rows = await _read_history(manager.history.health_of, loop_id, limit)
    return [{key: row[key] for key in ("time", "state", "severity", "flags", "recommendation", "session")}
            for row in rows]


@router.get("/sessions/{sid}", response_model=Session, tags=["history"], responses=_errors(401, 404, 503))
async def session(sid: str, manager: Manager, _: Viewer) -> dict[str, Any]:
    """One session in full, with its downsampled trace."""
    record = await _read_history(manager.history.get, sid)
    if record is None:
        raise errors.ApiError(404, "not_found", f"no session {sid!r}")
    return record


@router.get("/sessions/{sid}/analysis", response_model=Analysis, tags=["history"], responses={
    **_errors(401, 404, 503),
    409: {"model": errors.ErrorBody, "description": "no_result: the session has no identified point or no design"}})
async def analysis(sid: str, request: Request, manager: Manager, _: Viewer) -> dict[str, Any]:
    """What the session's gains (new) and the controller's gains before it (old) do on the identified model:
    Ms, Nyquist curve, unit set-point and load step responses (autotuner/engine/design/analysis.py)."""
    cache: dict[str, dict[str, Any]] = request.app.state.analyses
    if sid in cache:
        return cache[sid]
    record = await _read_history(manager.history.get, sid)
    if record is None:
        raise errors.ApiError(404, "not_found", f"no session {sid!r}")
    result = record["result"]
    if result is None or result.point is None or result.gains is None:
        raise errors.ApiError(409, "no_result", f"session {sid} has no identified point and design")
    ms = record["request"].get("ms", Tuning().ms)
    try:  # about 0.1 s of CPU: in a thread, so the live loops keep sampling on time
        body = await asyncio.to_thread(analyse, result, ms, record["gains_before"])
    except ValueError as exc:
        raise errors.ApiError(409, "no_result", f"session {sid}: no model from its result ({exc})") from None
    if len(cache) >= ANALYSES_KEPT:
        cache.pop(next(iter(cache)))
    cache[sid] = body = {"session": sid, "loop": record["loop"], **body}
    return body


metrics_router = APIRouter()


@metrics_router.get("/metrics", tags=["health"], response_class=Response, responses={
    200: {"content": {CONTENT_TYPE: {"example": "autotuner_loops_tuning 3.0\n"}},
          "description": "the daemon's metrics in the Prometheus text format (docs/daemon.md, \"Metrics\")"},
    **_errors(401)})
async def metrics(request: Request, _: Viewer) -> Response:
    """The daemon's own health in numbers (Prometheus text format): sampling lateness, analysis CPU, sessions by
    code, link errors, event streams, OPC UA sessions, the history's queue (viewer token)."""
    return Response(exposition(request.app.state.metrics), media_type=CONTENT_TYPE)


def fleet_of(config: DaemonConfig, host: str, port: int) -> Fleet | None:
    """This daemon's fleet on a PostgreSQL history (None: an SQLite one, one daemon): its leases' store, its name
    and URL (the config's, else host:port)."""
    if not config.leased:
        return None
    section = config.fleet or FleetConfig()
    shown = "127.0.0.1" if host in ("0.0.0.0", "::", "") else host
    name = section.name or f"{socket.gethostname()}:{port}"
    url = section.url or f"http://{shown}:{port}"
    leases = Leases(database_url(config.history), name, url, section.lease)
    return Fleet(leases, [loop.id for loop in config.loops], section.renew_period, draining=section.drain)


fleet_router = APIRouter(prefix=PREFIX)


@fleet_router.get("/fleet", response_model=FleetStatus, tags=["fleet"], responses=_errors(401))
async def fleet_status(manager: Manager, _: Viewer) -> dict[str, Any]:
    """The daemons of the fleet alive now and who serves each loop (docs/fleet.md); without a fleet (an SQLite
    history) this daemon alone."""
    fleet = manager.fleet
    if fleet is None:
        return {"daemon": None, "draining": False, "members": [], "loops": {}}
    return {"daemon": fleet.name, "draining": fleet.draining,
            "members": [{"name": m.name, "url": m.url, "draining": m.draining} for m in fleet.members],
            "loops": {loop_id: loop.owner for loop_id, loop in manager.loops.items()}}


@fleet_router.post("/fleet/drain", response_model=FleetStatus, tags=["fleet"], responses=_errors(
    401, 403, 400, 413, 422, e409="no_fleet: this daemon has no fleet (an SQLite history)"))
async def drain(manager: Manager, _: Admin, body: Annotated[DrainRequest, Body()]) -> dict[str, Any]:
    """Drain this daemon (``drain`` true: its idle loops go to the others within a renewal, the tuning ones once
    done; it takes none) or take it back into service (false). Admin only."""
    if manager.fleet is None:
        raise errors.ApiError(409, "no_fleet", "this daemon has no fleet: its history is not PostgreSQL")
    manager.fleet.draining = body.drain
    return await fleet_status(manager, None)  # type: ignore[arg-type]


class _Page(Mount):
    """The operator page's static files at ``/``, except under the API's prefix.

    A mount at ``/`` matches every path, so an API path asked with a method
    it does not have (``GET /api/v1/loops/X/tune``) would reach the static
    files (404) instead of the router's 405; API paths are left to the router.
    """

    def matches(self, scope: Scope) -> tuple[Match, Scope]:
        path = scope.get("path", "")
        if path == PREFIX or path.startswith(PREFIX + "/"):
            return Match.NONE, {}
        return super().matches(scope)


class StartupErrors:
    """ASGI middleware: a start that failed for a known reason (:class:`api.opcua.StartError`, e.g. the OPC UA port
    in use) is reported to the server by its one-line message, not by Starlette's traceback of it (uvicorn logs
    that message, then exits 3, as when the REST port is in use)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "lifespan":
            await self.app(scope, receive, send)
            return

        async def send_reason(message: Message) -> None:
            reason = getattr(scope["app"].state, "startup_error", None)
            if message["type"] == "lifespan.startup.failed" and reason:
                message = {**message, "message": reason}
            await send(message)

        await self.app(scope, receive, send_reason)


class SecurityHeaders:
    """ASGI middleware adding security headers to every response; the page's also get :data:`PAGE_POLICY`.

    Plain ASGI rather than ``@app.middleware``: the event streams pass through untouched.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = scope["path"]
        # The operator page's policy; the API docs' own (Swagger UI and ReDoc need inline styles); none for JSON.
        policy = docs.policy_of(path, PREFIX) or (None if path.startswith(PREFIX) else PAGE_POLICY)

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                headers["X-Content-Type-Options"] = "nosniff"
                headers["Referrer-Policy"] = "no-referrer"
                if policy is not None:
                    headers["Content-Security-Policy"] = policy
                    headers["X-Frame-Options"] = "DENY"
            await send(message)

        await self.app(scope, receive, send_with_headers)


def create_app(config: DaemonConfig, env_token: str | None = None, host: str = "127.0.0.1",
               port: int = 8000) -> FastAPI:
    """The API over the loops of ``config``; ``env_token`` (default: $AUTOTUNER_TOKEN) is an extra operator token.

    With ``config.opcua`` the OPC UA server (docs/opcua.md) runs beside it over
    the same loops, on ``config.opcua.host`` or else ``host``;
    ``app.state.opcua_url`` is its endpoint. On a PostgreSQL history the
    daemon serves only the loops whose leases it holds (docs/fleet.md); its
    default name and URL in the fleet are ``host:port`` and ``http://host:port``.
    """
    env = os.environ.get("AUTOTUNER_TOKEN") if env_token is None else env_token

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        store = History(config.history)
        fleet = fleet_of(config, host, port)
        manager = LoopManager(config, store, None if config.samplers == 0 else SamplerField(config.loops,
                                                                                              config.samplers),
                              fleet)
        heap.settle()  # before the loops run: its one full collection delays none of their samples
        try:
            await manager.start()
        except BaseException:
            heap.release()
            if fleet is not None:
                fleet.leases.close()
            raise
        app.state.manager = manager
        app.state.metrics = registry_of(manager, app.state)
        opcua = None
        try:
            if config.opcua is not None:
                try:
                    opcua = await start_opcua(manager, config, env, host)
                except StartError as exc:
                    app.state.startup_error = str(exc)
                    raise
                app.state.opcua, app.state.opcua_url = opcua, opcua.url
            yield
        finally:
            if opcua is not None:  # first: no TUNE from OPC UA while the sessions are being aborted
                await opcua.stop()
            app.state.unrestored = await manager.shutdown()
            await manager.stop()
            heap.release()
            store.close()
            if fleet is not None:
                fleet.leases.close()

    app = FastAPI(title="autotuner", version=__version__, lifespan=lifespan,
                  description="Relay-feedback PID autotuner daemon: TUNE / TBRK / TBSY / TE over HTTP (docs/daemon.md).",
                  openapi_url=f"{PREFIX}/openapi.json", docs_url=None, redoc_url=None)
    app.state.analyses = {}
    app.state.streams = OpenStreams()
    app.state.overview = Overview()
    app.state.tokens = Tokens(config.tokens, env)
    errors.install(app)

    # Inside SecurityHeaders (its answers get the headers too), in front of everything that reads a body.
    app.add_middleware(RequestGate, prefix=PREFIX)
    app.add_middleware(SecurityHeaders)
    app.add_middleware(StartupErrors)
    app.include_router(router)
    app.include_router(fleet_router)
    app.include_router(metrics_router)
    docs.install(app, PREFIX)  # Swagger UI and ReDoc from the daemon itself (no CDN)
    app.router.routes.append(_Page("/", StaticFiles(directory=STATIC, html=True), name="page"))
    return app
