"""The OPC UA interface of the daemon (docs/opcua.md), beside the REST API; needs the ``opcua`` extra (asyncua).

This package's ``__init__`` imports nothing from asyncua, so the rest of the
API (and ``autotuner password-hash``) works without the extra; :func:`require`
turns its absence into one clear message.
"""

from __future__ import annotations

import os
import secrets
from typing import TYPE_CHECKING

from autotuner.service.config import DaemonConfig, OpcUaConfig, OpcUaUser
from autotuner.service.daemon import LoopManager

from .passwords import hash_password

if TYPE_CHECKING:
    from .bridge import OpcUaProcess

# The user whose password is $AUTOTUNER_TOKEN (the OPC UA twin of the REST API's environment token).
ENV_USER = "operator"
# The demo's viewer; its password is $AUTOTUNER_VIEWER_PASSWORD, else generated and printed at start.
DEMO_VIEWER = "viewer"
# The endpoint's path.
PATH = "/autotuner/"
INSTALL_HINT = "OPC UA needs the opcua extra (asyncua): pip install 'relaytune[opcua]'"


class StartError(RuntimeError):
    """The OPC UA server could not start (its port in use, an unusable certificate, …): a one-line message for the
    daemon's log, shown instead of a traceback (:class:`api.app.StartupErrors`)."""


def endpoint_url(host: str, port: int) -> str:
    """The server's ``opc.tcp://`` endpoint."""
    return f"opc.tcp://{host}:{port}{PATH}"


def require() -> None:
    """Raise RuntimeError with :data:`INSTALL_HINT` when asyncua is not installed."""
    try:
        import asyncua  # noqa: F401
    except ImportError:
        raise RuntimeError(INSTALL_HINT) from None


async def start_opcua(manager: LoopManager, config: DaemonConfig, env_token: str | None, host: str) -> OpcUaProcess:
    """Start the OPC UA server of ``config.opcua`` over ``manager``'s loops, in a process of its own
    (:class:`api.opcua.bridge.OpcUaProcess`).

    Its users: the config's, plus ``operator`` (role operator) with the
    password ``env_token`` ($AUTOTUNER_TOKEN) unless the config has a user of
    that name. A generated certificate goes beside the history.
    """
    require()
    from .bridge import OpcUaProcess
    from .security import state_dir

    assert config.opcua is not None
    users = list(config.opcua.users)
    if env_token and all(user.name != ENV_USER for user in users):
        users.append(OpcUaUser(name=ENV_USER, role="operator", password_hash=hash_password(env_token)))
    server = OpcUaProcess(manager, config.opcua, users, host, state_dir(config.history))
    await server.start()
    return server


def with_opcua(config: DaemonConfig, port: int | None, demo: bool) -> tuple[DaemonConfig, list[str]]:
    """``config`` with its OPC UA server enabled (``serve --opcua``), on ``port`` if given; what to print at start.

    The demo (no config file) gets the user :data:`DEMO_VIEWER` with the
    password ``$AUTOTUNER_VIEWER_PASSWORD`` or a generated one (printed).
    RuntimeError with :data:`INSTALL_HINT` without asyncua.
    """
    require()
    section = config.opcua or OpcUaConfig()
    if port is not None:
        section = section.model_copy(update={"port": port})
    notes = []
    if demo and all(user.name != DEMO_VIEWER for user in section.users):
        password = os.environ.get("AUTOTUNER_VIEWER_PASSWORD")
        if not password:
            password = secrets.token_urlsafe(12)
            notes.append(f"OPC UA viewer password (shown once; or set AUTOTUNER_VIEWER_PASSWORD): {password}")
        viewer = OpcUaUser(name=DEMO_VIEWER, role="viewer", password_hash=hash_password(password))
        section = section.model_copy(update={"users": [*section.users, viewer]})
    return config.model_copy(update={"opcua": section}), notes
