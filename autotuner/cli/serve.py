"""``autotuner serve``: the daemon with the REST API, the event stream and the operator page."""

from __future__ import annotations

import os
from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from autotuner.cli.app import app, bad_input, stderr


class LogLevel(str, Enum):
    DEBUG = "debug"
    INFO = "info"
    WARNING = "warning"
    ERROR = "error"
    CRITICAL = "critical"


class LogFormat(str, Enum):
    TEXT = "text"
    JSON = "json"


@app.command("serve")
def serve_command(
    config: Annotated[Path | None, typer.Option(help="Daemon config (YAML, docs/daemon.md). Default: a built-in "
                                                "demo of 3 simulated loops, 20× real time.")] = None,
    host: Annotated[str, typer.Option(help="Address to listen on.")] = "127.0.0.1",
    port: Annotated[int, typer.Option(min=1, max=65535, help="TCP port.")] = 8000,
    ssl_certfile: Annotated[Path | None, typer.Option(help="TLS certificate (PEM); with --ssl-keyfile serves "
                                                      "HTTPS.")] = None,
    ssl_keyfile: Annotated[Path | None, typer.Option(help="TLS private key (PEM).")] = None,
    opcua: Annotated[bool, typer.Option("--opcua", help="Also run the OPC UA server (docs/opcua.md; the config's "
                                        "opcua: section, else its defaults). Needs the opcua extra.")] = False,
    opcua_port: Annotated[int | None, typer.Option(min=1, max=65535, help="OPC UA port (implies --opcua). "
                                                   "Default: the config's, else 4840.")] = None,
    log_level: Annotated[LogLevel, typer.Option(case_sensitive=False, help="Least severe log records printed "
                                                "(stderr).")] = LogLevel.INFO,
    log_format: Annotated[LogFormat, typer.Option(case_sensitive=False, help="Log lines as text (UTC timestamp, "
                                                  "level, logger, message) or one JSON object each.")]
    = LogFormat.TEXT,
    init_history: Annotated[bool, typer.Option("--init-history", help="Initialise a history file that exists but is "
                                               "empty (0 bytes, as a bind mount pre-creates it); without it such a "
                                               "file is refused.")] = False,
) -> None:
    """Run the daemon: the REST API of design.md under /api/v1 over the configured loops (and OPC UA with --opcua).

    Tokens come from the config (hashed) and from $AUTOTUNER_TOKEN (an operator). The demo without
    --config generates an operator token and prints it once when $AUTOTUNER_TOKEN is unset.
    SIGTERM/SIGINT abort running experiments and hand every loop back first, within handback.shutdown seconds
    (docs/handback.md), then the daemon exits 0; 4 if a loop could not be handed back (recorded; the next
    start resumes its restore).
    """
    from api.app import PREFIX, create_app
    from api.server import NOT_RESTORED_EXIT, serve
    from api.auth import new_token
    from api.opcua import ENV_USER, endpoint_url, require, with_opcua

    from autotuner.cli import logs
    from autotuner.service.config import ConfigError, load_config
    from autotuner.service.demo import demo_config
    from autotuner.service.history import History, database_password
    from autotuner.service.ownership import HistoryInUse, claim_history

    if (ssl_certfile is None) != (ssl_keyfile is None):
        bad_input("--ssl-certfile and --ssl-keyfile go together")
    try:
        daemon_config = demo_config() if config is None else load_config(config)
    except ConfigError as exc:
        bad_input(str(exc))
    logs.setup(log_level.value, log_format.value, secrets=[database_password(daemon_config.history) or ""])
    try:  # before the history is opened: a second daemon must not recover the first one's sessions
        lock = claim_history(daemon_config.history)
    except HistoryInUse as exc:
        bad_input(str(exc))
    try:  # a database that cannot be opened or is damaged is a clear error now, not a failed start inside uvicorn
        History(daemon_config.history, init_empty=init_history).close()
    except ValueError as exc:
        bad_input(str(exc))
    token = os.environ.get("AUTOTUNER_TOKEN") or None
    if config is None and token is None:
        token = new_token()
        print(f"operator token (shown once; or set AUTOTUNER_TOKEN): {token}", flush=True)
    elif not daemon_config.tokens and token is None:
        stderr.print("warning: no tokens in the config and AUTOTUNER_TOKEN unset: every request except "
                     f"{PREFIX}/health will be refused", highlight=False)
    notes: list[str] = []
    try:
        if opcua or opcua_port is not None:
            daemon_config, notes = with_opcua(daemon_config, opcua_port, demo=config is None)
        elif daemon_config.opcua is not None:
            require()
    except RuntimeError as exc:  # no asyncua
        bad_input(str(exc))
    for note in notes:
        print(note, flush=True)
    if daemon_config.opcua is not None:
        users = [user.name for user in daemon_config.opcua.users]
        if token and ENV_USER not in users:
            users.insert(0, f"{ENV_USER} (password: the operator token)")
        print(f"autotuner OPC UA at {endpoint_url(daemon_config.opcua.host or host, daemon_config.opcua.port)}  "
              f"(users: {', '.join(users) or 'none'}; docs/opcua.md)", flush=True)
    scheme = "http" if ssl_certfile is None else "https"
    print(f"autotuner API at {scheme}://{host}:{port}{PREFIX}  (OpenAPI: {PREFIX}/docs; operator page: "
          f"{scheme}://{host}:{port}/); {len(daemon_config.loops)} loops: "
          f"{', '.join(loop.id for loop in daemon_config.loops)}", flush=True)
    # log_config=None: uvicorn's loggers go to the handler of logs.setup (same format, timestamps, masking).
    status = serve(create_app(daemon_config, env_token=token or "", host=host), host=host, port=port,
                   log_level=log_level.value, log_config=None,
                   ssl_certfile=None if ssl_certfile is None else str(ssl_certfile),
                   ssl_keyfile=None if ssl_keyfile is None else str(ssl_keyfile))
    if lock is not None:
        lock.release()
    if status == NOT_RESTORED_EXIT:
        stderr.print(f"LOOP NOT RESTORED at shutdown: see the log; the next start resumes the restore "
                     f"(exit {status})", highlight=False)
    if status:
        raise typer.Exit(status)


@app.command("password-hash")
def password_hash_command(
    password: Annotated[str, typer.Option(prompt=True, hide_input=True, confirmation_prompt=True,
                                          help="The password (asked for when not given; read from stdin if piped).")],
) -> None:
    """Print the scrypt hash of an OPC UA user's password: the password_hash of the config's opcua.users."""
    from api.opcua.passwords import hash_password

    print(hash_password(password))
