"""Bearer-token authentication with roles: viewer reads, operator tunes and aborts, admin may do everything.

Tokens are configured by their SHA-256 (hex), never in clear; the
``AUTOTUNER_TOKEN`` environment variable adds one operator token (for quick
starts and the demo). A request without a known token is 401, one whose role
is too low 403.
"""

from __future__ import annotations

import hashlib
import secrets
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from autotuner.service.config import Role, Token

from .errors import ApiError

RANKS: dict[str, int] = {"viewer": 0, "operator": 1, "admin": 2}
# Name under which the environment's token appears in the history.
ENV_TOKEN_NAME = "AUTOTUNER_TOKEN"


def token_hash(token: str) -> str:
    """SHA-256 of ``token``, hex: what a config file stores."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def new_token() -> str:
    """A fresh random token (256 bits, URL-safe)."""
    return secrets.token_urlsafe(32)


@dataclass(frozen=True)
class Principal:
    """Who made a request: the token's name and role."""

    name: str
    role: Role


class Tokens:
    """The known tokens, by hash."""

    def __init__(self, tokens: Iterable[Token], env_token: str | None = None) -> None:
        self._by_hash = {t.sha256.lower(): Principal(t.name, t.role) for t in tokens}
        if env_token:
            self._by_hash[token_hash(env_token)] = Principal(ENV_TOKEN_NAME, "operator")

    def __len__(self) -> int:
        return len(self._by_hash)

    def find(self, token: str) -> Principal | None:
        """The principal of ``token``, or None."""
        return self._by_hash.get(token_hash(token))


def authorize(tokens: Tokens, token: str | None, role: Role) -> Principal:
    """The principal of ``token`` (None: none given), who must hold at least ``role``; ApiError 401 or 403."""
    principal = None if token is None else tokens.find(token)
    if principal is None:
        raise ApiError(401, "unauthorized", "a valid bearer token is required (Authorization: Bearer TOKEN)",
                       headers={"WWW-Authenticate": "Bearer"})
    if RANKS[principal.role] < RANKS[role]:
        raise ApiError(403, "forbidden", f"this needs the {role} role; token {principal.name!r} is a "
                       f"{principal.role}")
    return principal


def bearer_token(authorization: str | None) -> str | None:
    """The token of an ``Authorization: Bearer TOKEN`` header value, None for anything else."""
    scheme, _, token = (authorization or "").partition(" ")
    return token.strip() or None if scheme.lower() == "bearer" else None


_bearer = HTTPBearer(auto_error=False, description="API token (docs/daemon.md): viewer, operator or admin")


def require(role: Role) -> Callable[..., Principal]:
    """A FastAPI dependency: the caller, who must hold at least ``role``."""

    def check(request: Request,
              credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> Principal:
        return authorize(request.app.state.tokens, None if credentials is None else credentials.credentials, role)

    return check
