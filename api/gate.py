"""What every request passes before the application reads its body: the operator's token, then a size limit.

FastAPI reads and parses a request's JSON body before it runs the route's
dependencies, so the token check of :mod:`api.auth` alone would let anyone
make the daemon read and parse an unbounded body. :class:`RequestGate` is plain
ASGI middleware in front of the application:

* a request that carries a body (POST, PUT, PATCH) to a route of the API needs
  an operator token (every such route does); without one it is answered 401 or
  403 before a byte of the body is read (a method or path no route has is left to
  the application, which answers 404 or 405 without reading the body);
* every body is limited to ``max_body`` bytes: a larger ``Content-Length`` is
  answered 413 without reading; a body without one (chunked) is read only up to
  the limit, then 413. A body within the limit is passed on unchanged.

Errors are the API's JSON ``{"code", "message"}``.
"""

from __future__ import annotations

from starlette.routing import Match, Mount
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .auth import authorize, bearer_token
from .errors import ApiError, error_response

# Largest request body, bytes: a TUNE or apply body is well under 1 KiB.
MAX_BODY = 64 * 1024
# Methods whose requests carry a body the API reads.
_WITH_BODY = frozenset({"POST", "PUT", "PATCH"})


class RequestGate:
    """ASGI middleware: operator token for body-carrying API requests (paths under ``prefix``), then ``max_body``."""

    def __init__(self, app: ASGIApp, prefix: str, max_body: int = MAX_BODY) -> None:
        self.app = app
        self.prefix = prefix
        self.max_body = max_body

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] not in _WITH_BODY or not _routed(scope):
            await self.app(scope, receive, send)  # no route reads a body here: 404/405 unread
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        path = scope["path"]
        try:
            if path == self.prefix or path.startswith(self.prefix + "/"):
                authorize(scope["app"].state.tokens, bearer_token(headers.get("authorization")), "operator")
            length = headers.get("content-length")
            if length is not None and (not length.isdigit() or int(length) > self.max_body):
                raise self._too_large()
            body = await self._read(receive)
        except ApiError as exc:
            await error_response(exc.status, exc.code, exc.message, exc.headers)(scope, receive, send)
            return
        await self.app(scope, _replay(body, receive), send)

    def _too_large(self) -> ApiError:
        return ApiError(413, "too_large", f"request body larger than {self.max_body} bytes")

    async def _read(self, receive: Receive) -> bytes:
        """The whole body, read only up to ``max_body`` bytes (ApiError 413 beyond)."""
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":  # the client went away: let the app see it
                raise ApiError(400, "bad_request", "the client disconnected before sending the body")
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_body:
                raise self._too_large()
            chunks.append(chunk)
            if not message.get("more_body", False):
                return b"".join(chunks)


def _routed(scope: Scope) -> bool:
    """True when an API route takes this method at this path (mounts — the page, the docs' assets — read no body)."""
    return any(not isinstance(route, Mount) and route.matches(scope)[0] is Match.FULL
               for route in scope["app"].router.routes)


def _replay(body: bytes, receive: Receive) -> Receive:
    """A ``receive`` that gives ``body`` once, then what the server sends (a disconnect)."""
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay
