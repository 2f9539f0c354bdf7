"""JSON errors: every error response is ``{"code": MACHINE_CODE, "message": HUMAN TEXT}``, never a traceback."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException

from autotuner.service.daemon import Refused

log = logging.getLogger("autotuner.api")

_CODES = {400: "bad_request", 401: "unauthorized", 403: "forbidden", 404: "not_found", 405: "method_not_allowed",
          409: "conflict", 413: "too_large", 422: "invalid", 500: "internal"}


class ErrorBody(BaseModel):
    """An error: ``code`` for programs (not_found, busy, group_busy, idle, invalid, unauthorized, forbidden, ...),
    ``message`` for people."""

    code: str = Field(description="machine code: not_found, busy, group_busy, idle, nothing_to_apply, link, invalid, "
                      "unauthorized, forbidden, bad_request, too_large, internal, ...", examples=["busy"])
    message: str = Field(description="what happened, for people", examples=["loop 'TIC-101' is tuning"])


class ApiError(Exception):
    """An error response with status ``status``."""

    def __init__(self, status: int, code: str, message: str, headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.status, self.code, self.message, self.headers = status, code, message, headers


def error_response(status: int, code: str, message: str, headers: dict[str, str] | None = None) -> JSONResponse:
    """The JSON error response ``{"code": code, "message": message}`` with HTTP status ``status``."""
    return JSONResponse({"code": code, "message": message}, status_code=status, headers=headers)


def _field(loc: tuple[Any, ...]) -> str:
    """``('body', 'amp')`` → ``amp``; ``('path', 'loop_id')`` → ``loop_id``; nested as ``a.b[0]``."""
    text = ""
    for part in loc[1:] if loc and loc[0] in ("body", "query", "path", "header") else loc:
        text += f"[{part}]" if isinstance(part, int) else f".{part}" if text else str(part)
    return text or "body"


def validation_message(errors: list[Any]) -> str:
    """pydantic's errors as one line, each starting with its field: ``amp: Input should be greater than 0``."""
    return "; ".join(f"{_field(e['loc'])}: {e['msg']}" for e in errors) or "invalid request"


def install(app: FastAPI) -> None:
    """Register the handlers that turn every error into an :class:`ErrorBody`."""

    @app.exception_handler(ApiError)
    async def api_error(_: Request, exc: ApiError) -> JSONResponse:
        return error_response(exc.status, exc.code, exc.message, exc.headers)

    @app.exception_handler(Refused)
    async def refused(request: Request, exc: Refused) -> JSONResponse:
        if exc.code == "not_owner" and exc.owner_url:  # the same request, at the daemon that serves the loop
            target = exc.owner_url.rstrip("/") + request.url.path + (f"?{request.url.query}" if request.url.query
                                                                     else "")
            return error_response(307, exc.code, exc.message, {"Location": target})
        status = {"not_found": 404, "invalid": 422, "history_unavailable": 503, "not_owner": 503}.get(exc.code, 409)
        return error_response(status, exc.code, exc.message)

    @app.exception_handler(RequestValidationError)
    async def invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        return error_response(422, "invalid", validation_message(list(exc.errors())))

    @app.exception_handler(HTTPException)
    async def http_error(_: Request, exc: HTTPException) -> JSONResponse:
        return error_response(exc.status_code, _CODES.get(exc.status_code, "error"), str(exc.detail), exc.headers)

    @app.exception_handler(Exception)
    async def internal(_: Request, exc: Exception) -> JSONResponse:
        log.exception("internal error")
        return error_response(500, "internal", f"internal error ({type(exc).__name__}); see the daemon's log")
