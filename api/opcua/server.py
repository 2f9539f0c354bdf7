"""The OPC UA server beside the REST API, in a process of its own: ``python -m api.opcua.server FD``.

The daemon (:mod:`api.opcua.bridge`) starts this process with one end of a
socket pair (file descriptor ``FD``, :mod:`api.opcua.wire`), so OPC UA
clients, their subscriptions, the encryption and the encoding of every data
change never take the daemon's CPU time or its GIL, where the sessions
sample. Over that channel:

- the daemon sends the loops' compact statuses at the monitor's rate (the
  changed loops only); they are written to the address space
  (:mod:`api.opcua.address_space`), the changed values only;
- the methods are validated and checked for the role here and run by the
  daemon on its :class:`~autotuner.service.daemon.LoopManager` (the one
  behind REST), so a TUNE over OPC UA and one over REST see the same busy
  state, exclusion groups and history;
- the log records go to the daemon's log.

The process ends when the daemon says stop, when its end of the socket pair
closes (the daemon died, even by SIGKILL) or when it is orphaned.

Methods of each loop (operator role; a viewer's call is refused with
``BadUserAccessDenied`` and the message ``forbidden: this needs the operator role``):

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
import errno
import itertools
import logging
import math
import os
import signal
import socket
import sys
from collections.abc import Awaitable, Callable
from typing import Any
from urllib.parse import urlsplit

from asyncua import Node, Server, ua
from pydantic import ValidationError

from api.errors import validation_message
from autotuner.service.channel import forward_logs
from autotuner.service.config import TuneRequest

from .address_space import FOLDER, NAMESPACE, LoopNodes, event_type, node_id
from .security import (CALLER, NEEDS_OPERATOR, QuietRefusals, RoleRuleset, TrustedClients, Users, ensure_certificate,
                       may_call)
from .wire import Channel, Init

log = logging.getLogger("autotuner.api.opcua")

# The server's application URI.
APP_URI = "urn:relaytune:autotuner:server"
# How often the process checks that the daemon that started it is still its parent, wall seconds.
ORPHAN_CHECK = 0.5
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
           "link": ua.StatusCodes.BadCommunicationError, "history_unavailable": ua.StatusCodes.BadResourceUnavailable}


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


def _refused(what: str, code: str, message: str, inputs: int, bad_input: int | None = None,
             status: int | None = None) -> ua.CallMethodResult:
    """The result of a call (``what``: loop, method, user) that the manager or the validation refused with the REST
    error ``code: message`` (``status``: its status code if not the code's own), logged as the expected outcome it
    is: INFO (WARNING when the loop's link failed)."""
    log.log(logging.WARNING if code == "link" else logging.INFO, "%s refused: %s: %s", what, code, message)
    status = _STATUS.get(code, ua.StatusCodes.BadInvalidState) if status is None else status
    return _result(status, "", f"{code}: {message}", inputs, bad_input)


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
    """The OPC UA server of the daemon's loops (``init``), fed and served by the daemon over ``channel``."""

    def __init__(self, init: Init, channel: Channel) -> None:
        self.init, self.config, self.channel = init, init.config, channel
        self._nodes: dict[str, LoopNodes] = {}
        self._calls: dict[int, asyncio.Future[tuple[Any, ...]]] = {}
        self._ids = itertools.count()

    async def run(self) -> None:
        """Build and start the server, say ready (or failed), then serve until the daemon says stop or is gone."""
        quiet = QuietRefusals()
        for name in QuietRefusals.LOGGERS:
            logging.getLogger(name).addFilter(quiet)
        # asyncua logs a failed start with a traceback; the daemon logs our one line instead.
        logging.getLogger("asyncua.server.server").addFilter(_StartFailure())
        address = urlsplit(self.init.url)
        try:
            check_listen(address.hostname or "", address.port or 0)  # in ms, not after building the address space
            server = await self._build()
            await server.start()
        except Exception as exc:
            log.debug("OPC UA server start failed", exc_info=True)
            self.channel.send("failed", start_error(exc, address.hostname or "", address.port or 0))
            return
        try:
            self.channel.send("ready")
            orphan = asyncio.create_task(_orphaned(os.getppid()))
            listen = asyncio.create_task(self._listen())
            await asyncio.wait([orphan, listen], return_when=asyncio.FIRST_COMPLETED)
            orphan.cancel()
            listen.cancel()
            for call in self._calls.values():
                call.cancel()
            if listen.done() and not listen.cancelled():  # told to stop: the last statuses reach the clients
                await _publish_now(server)
        finally:
            await server.stop()

    def _count_sessions(self, server: Server) -> None:
        """Tell the daemon how many client sessions are open whenever one opens or closes (its metrics)."""
        iserver = server.iserver
        sessions: set[Any] = set()
        register, unregister = iserver.register_external_session, iserver.unregister_external_session

        def registered(session: Any) -> None:
            register(session)
            sessions.add(session.auth_token)
            self.channel.send("sessions", len(sessions))

        def unregistered(session: Any) -> None:
            unregister(session)
            sessions.discard(session.auth_token)
            self.channel.send("sessions", len(sessions))

        iserver.register_external_session, iserver.unregister_external_session = registered, unregistered

    async def _build(self) -> Server:
        trusted = None
        if self.config.trusted_clients is not None:
            trusted = TrustedClients(self.config.trusted_clients)
            await trusted.load()
        server = Server(user_manager=Users(self.init.users, trusted))
        await server.init()
        self._count_sessions(server)
        if trusted is not None:
            server.set_certificate_validator(trusted)
        server.set_endpoint(self.init.url)
        server.set_server_name("relaytune autotuner")
        await server.set_application_uri(APP_URI)
        if self.config.certificate is not None:
            cert, key = self.config.certificate, self.config.private_key
        else:
            cert, key = await ensure_certificate(self.init.cert_dir, APP_URI)
        for what, path, load in (("certificate", cert, server.load_certificate),
                                 ("private_key", key, server.load_private_key)):
            try:
                await load(str(path))
            except Exception as exc:  # the field to fix, not only the parser's complaint
                raise ValueError(f"opcua.{what}: {path} is not a usable {what.replace('_', ' ')} (DER or PEM): "
                                 f"{type(exc).__name__}: {exc}") from exc
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
        for status, period in self.init.loops:
            loop_id = status["id"]
            nodes = self._nodes[loop_id] = await LoopNodes.create(server, folder, idx, status, period, event_types)
            await self._methods(nodes.obj, idx, loop_id)
        return server

    async def _methods(self, obj: Node, idx: int, loop_id: str) -> None:
        outputs = [_argument(*a) for a in OUTPUTS]
        tune_inputs = [_argument(*a) for a in TUNE_ARGS]

        def method(name: str, action: str, inputs: int) -> Callable[..., Awaitable[ua.CallMethodResult]]:
            async def callback(parent: ua.NodeId, *args: Any) -> ua.CallMethodResult:
                if parent != obj.nodeid:  # asyncua runs a method for any object named: not a TUNE of another loop
                    log.info("loop %s: %s called on %s refused: not a method of that object", loop_id, name,
                             parent.to_string())
                    return _result(ua.StatusCodes.BadMethodInvalid, "", f"invalid: {name} is a method of loop "
                                   f"{loop_id}, not of {parent.to_string()}")
                return await self._call(loop_id, name, action, list(args), inputs)

            return callback

        for name, action, inputs in (("Tune", "tune", tune_inputs), ("Break", "abort", []), ("Apply", "apply", []),
                                     ("AutoTuningOn", "tune", []), ("AutoTuningOff", "abort", [])):
            await obj.add_method(node_id(idx, loop_id, name), ua.QualifiedName(name, idx),
                                 method(name, action, len(inputs)), inputs, outputs)

    # -- the daemon's messages --------------------------------------------------------------------------------

    async def _listen(self) -> None:
        """The daemon's messages until it says stop or its end closes: statuses into the address space, replies
        to the waiting calls."""
        while (message := await self.channel.receive()) is not None:
            kind = message[0]
            if kind == "status":
                for status in message[1]:
                    try:
                        await self._nodes[status["id"]].update(status)
                    except Exception:  # a bug must not end the publishing of every loop
                        log.exception("OPC UA: publishing the status of loop %s failed", status.get("id"))
            elif kind == "reply":
                outcome = message[2]
                if outcome[0] == "ok":  # here, in the order of the statuses: TBSY rises now, not at the next period
                    await self._nodes[outcome[3]["id"]].update(outcome[3])
                call = self._calls.pop(message[1], None)
                if call is not None and not call.done():
                    call.set_result(outcome)
            elif kind == "stop":
                return

    # -- methods ----------------------------------------------------------------------------------------------

    async def _call(self, loop_id: str, method: str, action: str, args: list[Any], inputs: int
                    ) -> ua.CallMethodResult:
        """Run ``action`` (tune, abort, apply) in the daemon for the calling operator; the result of ``method``
        (its name, for the log), which has ``inputs`` input arguments."""
        user = CALLER.get()
        if not may_call(user):  # a viewer: refused as REST's 403, with the message, logged as the expected outcome
            log.warning("loop %s: %s over OPC UA by opcua:%s (%s) refused: %s", loop_id, method,
                        getattr(user, "name", "?"), getattr(user, "api_role", "?"), NEEDS_OPERATOR)
            return _result(ua.StatusCodes.BadUserAccessDenied, "", NEEDS_OPERATOR, inputs)
        who = f"opcua:{user.name}"
        what = f"loop {loop_id}: {method} over OPC UA by {who}"
        if len(args) != inputs:  # asyncua does not check the count; OPC 10000-4 §5.11.2 has a code for each case
            names = f" ({', '.join(a[0] for a in TUNE_ARGS)})" if inputs else ""
            return _refused(what, "invalid", f"{method} takes {inputs} arguments{names}, got {len(args)}", 0,
                            status=ua.StatusCodes.BadArgumentsMissing if len(args) < inputs else
                            ua.StatusCodes.BadTooManyArguments)
        body = None
        try:
            if action == "tune":  # AutoTuningOn (no inputs): Tune with the loop's defaults
                body = tune_request(args if inputs else [None] * len(TUNE_ARGS)).model_dump(exclude_none=True)
        except ValidationError as exc:
            bad = next((i for i, a in enumerate(TUNE_ARGS) if exc.errors() and exc.errors()[0]["loc"][:1] == (a[0],)),
                       None)
            return _refused(what, "invalid", validation_message(exc.errors()), inputs, bad)
        except ValueError as exc:
            return _refused(what, "invalid", str(exc), inputs)
        call_id = next(self._ids)
        reply = self._calls[call_id] = asyncio.get_running_loop().create_future()
        self.channel.send("call", call_id, loop_id, action, body, who)
        outcome = await reply
        if outcome[0] == "refused":
            return _refused(what, outcome[1], outcome[2], inputs)
        if outcome[0] != "ok":
            raise RuntimeError(f"{what} failed in the daemon: {outcome[1]}")  # asyncua answers BadInternalError
        _, sid, message, _ = outcome
        log.info("%s (session %s)", what, sid)
        return _result(ua.StatusCodes.Good, sid, message, inputs)


class ListenError(OSError):
    """The server cannot listen on its endpoint's address and port (``strerror`` says why)."""


def check_listen(host: str, port: int) -> None:
    """ListenError unless a server can listen on ``host``:``port`` now, on every address the host names (as
    asyncio binds them, with SO_REUSEADDR: another listener there fails, a closed connection's TIME_WAIT does not)."""
    try:
        addresses = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise ListenError(exc.errno, f"{host!r} is not an address of this machine ({exc.strerror})") from None
    for family, kind, proto, _, sockaddr in addresses:
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind(sockaddr)
            except OSError as exc:
                raise ListenError(exc.errno, exc.strerror) from None


def start_error(exc: BaseException, host: str, port: int) -> str:
    """The one-line reason of a failed start: which address cannot be listened on and why (a port in use: what
    to change), else the exception's type and message."""
    if isinstance(exc, ListenError) or (isinstance(exc, OSError) and "bind" in str(exc)):
        why = (exc.strerror or str(exc)).lower()
        hint = (" (another program listens there, another daemon's OPC UA server perhaps: choose another port "
                "with opcua.port or --opcua-port)") if exc.errno == errno.EADDRINUSE else ""
        return f"cannot listen on {host}:{port}: {why}{hint}"
    return f"{type(exc).__name__}: {exc}"


class _StartFailure(logging.Filter):
    """Drops asyncua's record of a failed start (with its traceback): the daemon logs the reason in one line."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).endswith("error starting server")


async def _publish_now(server: Server) -> None:
    """Send every subscription's queued data changes and events now, not at its next publishing interval (which
    the stop would not wait for): to each that has a publish request of its client at hand, as clients keep one."""
    for subscription in list(server.iserver.subscription_service.subscriptions.values()):
        try:
            await subscription.publish_results()
        except Exception:  # a client gone meanwhile: the others still get theirs
            log.debug("OPC UA: the last publish of a subscription failed", exc_info=True)


async def _orphaned(parent: int) -> None:
    """Return once the process is no longer the child of ``parent`` (the daemon died, its child was adopted)."""
    while os.getppid() == parent:
        await asyncio.sleep(ORPHAN_CHECK)


async def serve(fd: int) -> None:
    """The process' work: the daemon's init over the socket ``fd``, then the server until told to stop."""
    channel = await Channel.open(socket.socket(fileno=fd))
    message = await channel.receive()
    if message is None or message[0] != "init":
        return
    init: Init = message[1]
    forward_logs(channel, init.levels)
    try:
        await OpcUaServer(init, channel).run()
    finally:
        await channel.close()


def main(argv: list[str]) -> int:
    """``python -m api.opcua.server FD``: the daemon's OPC UA server over the socket ``FD``."""
    # Ctrl-C in a terminal signals the whole process group: the daemon stops this process itself, after its loops.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    asyncio.run(serve(int(argv[1])))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
