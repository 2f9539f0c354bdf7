"""The OPC UA server beside the REST API: the same :class:`~autotuner.service.daemon.LoopManager`, its own thread.

The server (asyncua) runs in a thread of its own with its own event loop,
so OPC UA clients, their subscriptions and the encryption never run on the
daemon's event loop, where the sessions sample. It touches the manager only
through that loop (``run_coroutine_threadsafe``):

- every loop's status is fetched every ``monitor_period`` wall seconds
  (one request per distinct period for all its loops) and written to the
  address space (:mod:`api.opcua.address_space`), the changed values only;
- the methods call :meth:`LoopManager.tune`, ``abort`` and ``apply`` there,
  so a TUNE over OPC UA and one over REST see the same busy state, exclusion
  groups and history.

Methods of each loop (operator role; a viewer's call is refused with
``BadUserAccessDenied`` by :class:`~api.opcua.security.RoleRuleset`):

- ``Tune(controller, amp, hysteresis, phase, ms, apply)``: NaN or "" = the
  loop's default; ``apply`` "", "true" or "false" (a Boolean is taken too);
- ``Break()``, ``Apply()`` (the newest finished session's gains);
- OPC 40083's ``AutoTuningOn()`` (Tune with the loop's defaults) and
  ``AutoTuningOff()`` (Break).

Each returns ``(Session, Message)``. A refused call has a Bad status code —
``BadInvalidArgument`` (invalid, the offending argument marked too),
``BadInvalidState`` (busy, group_busy, idle, nothing_to_apply),
``BadNotFound``, ``BadCommunicationError`` (link) — and still the two
outputs: "" and the REST error's ``code: message``.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import math
import os
import tempfile
import threading
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any, TypeVar

from asyncua import Node, Server, ua
from pydantic import ValidationError

from api.errors import validation_message
from autotuner.service.config import OpcUaConfig, OpcUaUser, TuneRequest
from autotuner.service.daemon import LoopManager, Refused

from . import endpoint_url
from .address_space import FOLDER, NAMESPACE, LoopNodes, event_type, node_id
from .security import (CALLER, NEEDS_OPERATOR, QuietRefusals, RoleRuleset, TrustedClients, Users, ensure_certificate,
                       may_call)

log = logging.getLogger("autotuner.api.opcua")
T = TypeVar("T")

# The server's application URI.
APP_URI = "urn:relaytune:autotuner:server"
# How long start waits for the server to listen, and stop for its thread to end, wall seconds.
START_WAIT, STOP_WAIT = 60.0, 20.0
POLICIES = {"None": ua.SecurityPolicyType.NoSecurity, "Basic256Sha256_Sign": ua.SecurityPolicyType.Basic256Sha256_Sign,
            "Basic256Sha256_SignAndEncrypt": ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt}
TUNE_ARGS = (("controller", ua.VariantType.String, "PI or PID; empty: the loop's default"),
             ("amp", ua.VariantType.Double, "relay amplitude, MV units (> 0); NaN: default"),
             ("hysteresis", ua.VariantType.Double, "relay hysteresis, PV units (>= 0); NaN: default"),
             ("phase", ua.VariantType.Double, "phase lag of the identified point, degrees (90-170); NaN: default"),
             ("ms", ua.VariantType.Double, "maximum sensitivity of the design (1.05-4); NaN: default"),
             ("apply", ua.VariantType.String, "true or false: write the gains on success; empty: default"))
OUTPUTS = (("Session", ua.VariantType.String, "the session's id (REST history); empty when refused"),
           ("Message", ua.VariantType.String, "what happened; when refused the REST error's 'code: message'"))
_STATUS = {"invalid": ua.StatusCodes.BadInvalidArgument, "not_found": ua.StatusCodes.BadNotFound,
           "link": ua.StatusCodes.BadCommunicationError}


def _argument(name: str, kind: ua.VariantType, description: str) -> ua.Argument:
    return ua.Argument(Name=name, DataType=ua.NodeId(kind.value), ValueRank=-1,
                       Description=ua.LocalizedText(description))


def _result(code: int, session: str, message: str, inputs: int = 0, bad_input: int | None = None
            ) -> ua.CallMethodResult:
    arg_results = [ua.StatusCode(ua.StatusCodes.BadInvalidArgument if i == bad_input else ua.StatusCodes.Good)
                   for i in range(inputs)]
    return ua.CallMethodResult(StatusCode=ua.StatusCode(code), InputArgumentResults=arg_results,
                               OutputArguments=[ua.Variant(session, ua.VariantType.String),
                                                ua.Variant(message, ua.VariantType.String)])


def _refused(what: str, code: str, message: str, inputs: int, bad_input: int | None = None) -> ua.CallMethodResult:
    """The result of a call (``what``: loop, method, user) that the manager or the validation refused with the REST
    error ``code: message``, logged as the expected outcome it is: INFO (WARNING when the loop's link failed)."""
    log.log(logging.WARNING if code == "link" else logging.INFO, "%s refused: %s: %s", what, code, message)
    return _result(_STATUS.get(code, ua.StatusCodes.BadInvalidState), "", f"{code}: {message}", inputs, bad_input)


def tune_request(args: list[Any]) -> TuneRequest:
    """The TUNE body of Tune's six arguments (NaN, "" or null: the default); ValidationError like REST's body."""
    if len(args) != len(TUNE_ARGS):
        raise ValueError(f"Tune takes {len(TUNE_ARGS)} arguments ({', '.join(a[0] for a in TUNE_ARGS)}), "
                         f"got {len(args)}")
    body: dict[str, Any] = {}
    for (name, _, _), value in zip(TUNE_ARGS, args, strict=True):
        value = value.Value if isinstance(value, ua.Variant) else value  # asyncua hands the methods Variants
        if value is None or value == "" or (isinstance(value, float) and math.isnan(value)):
            continue
        if name == "apply" and isinstance(value, str):
            value = {"true": True, "false": False}.get(value.strip().lower(), value)
        body[name] = value
    return TuneRequest.model_validate(body)


class OpcUaServer:
    """The OPC UA server of ``manager``'s loops, run in its own thread; :meth:`start` and :meth:`stop` from the
    daemon's event loop.

    ``users``: who may log in (the config's, plus the demo's or
    $AUTOTUNER_TOKEN's operator); ``cert_dir``: where a generated certificate
    is kept when ``config`` names none (None: a temporary folder removed at stop).
    """

    def __init__(self, manager: LoopManager, config: OpcUaConfig, users: list[OpcUaUser], host: str,
                 cert_dir: Path | None) -> None:
        self._scratch = tempfile.TemporaryDirectory(prefix="autotuner-opcua-") if cert_dir is None else None
        self.cert_dir = Path(self._scratch.name) if self._scratch is not None else cert_dir
        self.manager, self.config, self.users = manager, config, users
        self.url = endpoint_url(config.host or host, config.port)
        self._daemon: asyncio.AbstractEventLoop | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._halt: asyncio.Event | None = None
        self._thread: threading.Thread | None = None
        self._nodes: dict[str, LoopNodes] = {}

    # -- life cycle, from the daemon's event loop --------------------------------------------------------------

    async def start(self) -> str:
        """Start the thread and wait until the server listens; its endpoint URL. The server's error (a port in
        use, an unreadable certificate) is raised here."""
        self._daemon = asyncio.get_running_loop()
        ready: concurrent.futures.Future[None] = concurrent.futures.Future()
        self._thread = threading.Thread(target=self._run, args=(ready,), name="opcua", daemon=True)
        self._thread.start()
        try:
            await asyncio.wait_for(asyncio.wrap_future(ready), START_WAIT)
        except BaseException:
            await self.stop()
            raise
        log.info("OPC UA server at %s", self.url)
        return self.url

    async def stop(self) -> None:
        """Stop the server (clients are disconnected) and wait for its thread."""
        loop, halt, thread = self._loop, self._halt, self._thread
        if loop is not None and halt is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # its loop closed meanwhile
                loop.call_soon_threadsafe(halt.set)
        if thread is not None:
            await asyncio.to_thread(thread.join, STOP_WAIT)
        self._thread = None
        if self._scratch is not None:
            self._scratch.cleanup()

    def cpu_time(self) -> float | None:
        """CPU seconds (user + system) the server's thread has used so far; None where /proc is missing."""
        thread = self._thread
        try:
            stat = Path(f"/proc/self/task/{thread.native_id}/stat").read_text()  # type: ignore[union-attr]
        except (AttributeError, OSError):
            return None
        utime, stime = stat.rpartition(")")[2].split()[11:13]  # fields 14 and 15 of proc(5)
        return (int(utime) + int(stime)) / os.sysconf("SC_CLK_TCK")

    # -- the server's thread ----------------------------------------------------------------------------------

    def _run(self, ready: concurrent.futures.Future[None]) -> None:
        try:
            asyncio.run(self._serve(ready))
        except BaseException as exc:  # start failed: the daemon's start() raises it
            if not ready.done():
                ready.set_exception(exc)
            else:
                log.exception("OPC UA server failed")

    async def _serve(self, ready: concurrent.futures.Future[None]) -> None:
        self._loop, self._halt = asyncio.get_running_loop(), asyncio.Event()
        quiet = QuietRefusals()
        for name in QuietRefusals.LOGGERS:
            logging.getLogger(name).addFilter(quiet)
        try:
            await self._run_server(ready)
        finally:
            for name in QuietRefusals.LOGGERS:
                logging.getLogger(name).removeFilter(quiet)

    async def _run_server(self, ready: concurrent.futures.Future[None]) -> None:
        assert self._halt is not None
        server = await self._build()
        async with server:
            pollers = [asyncio.create_task(self._poll(ids, period)) for period, ids in self._periods().items()]
            ready.set_result(None)
            try:
                await self._halt.wait()
            finally:
                for task in pollers:
                    task.cancel()
                await asyncio.gather(*pollers, return_exceptions=True)

    async def _build(self) -> Server:
        trusted = None
        if self.config.trusted_clients is not None:
            trusted = TrustedClients(self.config.trusted_clients)
            await trusted.load()
        server = Server(user_manager=Users(self.users, trusted))
        await server.init()
        if trusted is not None:
            server.set_certificate_validator(trusted)
        server.set_endpoint(self.url)
        server.set_server_name("relaytune autotuner")
        await server.set_application_uri(APP_URI)
        if self.config.certificate is not None:
            cert, key = self.config.certificate, self.config.private_key
        else:
            cert, key = await ensure_certificate(self.cert_dir, APP_URI)
        await server.load_certificate(str(cert))
        await server.load_private_key(str(key))
        server.set_security_policy([POLICIES[p] for p in self.config.security], permission_ruleset=RoleRuleset())
        server.set_identity_tokens([ua.UserNameIdentityToken])  # no anonymous sessions
        idx = await server.register_namespace(NAMESPACE)
        folder = await server.nodes.objects.add_folder(node_id(idx, FOLDER), ua.QualifiedName(FOLDER, idx))
        event_types = {
            "TuningError": await event_type(server, idx, "TuningErrorEventType",
                                            "a tuning ended with TE (ite holds the code)"),
            "LoopNotRestored": await event_type(server, idx, "LoopNotRestoredEventType",
                                                "a loop could not be put back after a session: check it by hand"),
        }
        for status in await self._statuses(list(self.manager.loops)):
            loop_id = status["id"]
            period = self.manager.loops[loop_id].config.monitor_period
            nodes = self._nodes[loop_id] = await LoopNodes.create(server, folder, idx, status, period, event_types)
            await self._methods(nodes.obj, idx, loop_id)
        return server

    async def _methods(self, obj: Node, idx: int, loop_id: str) -> None:
        outputs = [_argument(*a) for a in OUTPUTS]
        tune_inputs = [_argument(*a) for a in TUNE_ARGS]

        def method(name: str, action: str, inputs: int) -> Callable[..., Awaitable[ua.CallMethodResult]]:
            async def callback(_: ua.NodeId, *args: Any) -> ua.CallMethodResult:
                if action == "tune" and not inputs:  # AutoTuningOn: Tune with the loop's defaults
                    args = (None,) * len(TUNE_ARGS)
                return await self._call(loop_id, name, action, list(args), inputs)

            return callback

        for name, action, inputs in (("Tune", "tune", tune_inputs), ("Break", "abort", []), ("Apply", "apply", []),
                                     ("AutoTuningOn", "tune", []), ("AutoTuningOff", "abort", [])):
            await obj.add_method(node_id(idx, loop_id, name), ua.QualifiedName(name, idx),
                                 method(name, action, len(inputs)), inputs, outputs)

    # -- methods ----------------------------------------------------------------------------------------------

    async def _call(self, loop_id: str, method: str, action: str, args: list[Any], inputs: int
                    ) -> ua.CallMethodResult:
        """Run ``action`` (tune, abort, apply) on the daemon's loop for the calling operator; the result of
        ``method`` (its name, for the log), which has ``inputs`` input arguments."""
        user = CALLER.get()
        if not may_call(user):  # the ruleset refuses viewers already; a second check costs nothing
            return _result(ua.StatusCodes.BadUserAccessDenied, "", NEEDS_OPERATOR, inputs)
        who = f"opcua:{user.name}"
        what = f"loop {loop_id}: {method} over OPC UA by {who}"
        try:
            if action == "tune":
                request = tune_request(args)
                sid = await self._on_daemon_async(lambda: self.manager.request_tune(loop_id, request, who))
                message = "tuning"
            elif action == "abort":
                sid = await self._on_daemon(lambda: self.manager.abort(loop_id))
                message = "aborting: the loop is being restored"
            else:
                applied = await self._on_daemon_async(lambda: self.manager.apply(loop_id, None, who))
                sid, message = applied["session"], "applied: " + ", ".join(
                    f"{k}={v:.6g}" for k, v in applied["gains"].items() if v is not None)
        except ValidationError as exc:
            bad = next((i for i, a in enumerate(TUNE_ARGS) if exc.errors() and exc.errors()[0]["loc"][:1] == (a[0],)),
                       None)
            return _refused(what, "invalid", validation_message(exc.errors()), inputs, bad)
        except ValueError as exc:
            return _refused(what, "invalid", str(exc), inputs)
        except Refused as exc:
            return _refused(what, exc.code, exc.message, inputs)
        log.info("%s (session %s)", what, sid)
        await self._refresh([loop_id])  # TBSY rises now, not at the next poll
        return _result(ua.StatusCodes.Good, sid, message, inputs)

    # -- the bridge to the daemon's event loop ---------------------------------------------------------------

    async def _on_daemon(self, fn: Callable[[], T]) -> T:
        """``fn()`` run on the daemon's event loop (where the manager lives), awaited from this thread's."""

        async def run() -> T:
            return fn()

        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(run(), self._daemon))

    async def _on_daemon_async(self, fn: Callable[[], Awaitable[T]]) -> T:
        """The coroutine ``fn()`` run on the daemon's event loop, awaited from this thread's."""

        async def run() -> T:
            return await fn()

        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(run(), self._daemon))

    async def _statuses(self, ids: list[str]) -> list[dict[str, Any]]:
        return await self._on_daemon(lambda: [self.manager.loops[i].as_json() for i in ids])

    def _periods(self) -> dict[float, list[str]]:
        """The loops by monitor period (one poller each)."""
        periods: dict[float, list[str]] = {}
        for loop_id, loop in self.manager.loops.items():
            periods.setdefault(loop.config.monitor_period, []).append(loop_id)
        return periods

    async def _refresh(self, ids: list[str]) -> None:
        for status in await self._statuses(ids):
            await self._nodes[status["id"]].update(status)

    async def _poll(self, ids: list[str], period: float) -> None:
        """Every ``period`` wall seconds: the statuses of ``ids`` into the address space, until cancelled."""
        while True:
            try:
                await self._refresh(ids)
            except (RuntimeError, concurrent.futures.CancelledError):
                return  # the daemon's event loop is closing
            except Exception:  # a bug must not end the publishing of every loop
                log.exception("OPC UA: publishing the loops' status failed")
            await asyncio.sleep(period)

