"""Serving the daemon's app with uvicorn so that a stop hands every loop back *first* (docs/handback.md).

uvicorn on its own, on SIGTERM or SIGINT, stops accepting connections and
then waits for the open ones before it runs the application's shutdown; an
event stream (the operator page always has one) never ends by itself, so the
experiments kept running, and a second Ctrl-C skipped the shutdown (and with
it the hand-back) altogether. Here the signals are the daemon's own: the
first one starts :meth:`~autotuner.service.daemon.LoopManager.shutdown`
(abort every experiment, hand every loop back within ``handback.shutdown``
seconds, end the event streams) and only then tells uvicorn to exit; a
second one is logged and changes nothing. The exit status is 0 when every
loop was handed back, :data:`NOT_RESTORED_EXIT` otherwise (and uvicorn's 3
when the server could not start).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import urllib.parse
from collections.abc import Generator
from typing import Any

import uvicorn
from fastapi import FastAPI

# Exit status of a daemon that stopped with loops it could not hand back (recorded; the next start resumes them).
NOT_RESTORED_EXIT = 4
# Exit status of a server that could not start (uvicorn's own).
STARTUP_FAILURE = 3
# uvicorn's own wait for requests still open once the loops are handed back and the streams ended, seconds.
GRACEFUL_WAIT = 3.0

log = logging.getLogger("autotuner.api.server")


def redacted(target: str) -> str:
    """A request target with every query value masked (``/loops?access_token=***&limit=***``): a client may put a
    secret there (a token, refused 401 all the same), and the access log must not keep it."""
    path, sep, query = target.partition("?")
    if not sep:
        return target
    parts = (part.partition("=") for part in query.split("&"))  # a part without "=" may be the secret itself
    return path + "?" + "&".join(f"{urllib.parse.quote(urllib.parse.unquote_plus(name)[:64])}=***" if eq and name
                                 else "***" for name, eq, _ in parts)


class RedactQuery(logging.Filter):
    """uvicorn's access log (``client - "METHOD TARGET HTTP/x" status``) with the target's query values masked."""

    def filter(self, record: logging.LogRecord) -> bool:
        args = record.args
        if isinstance(args, tuple) and len(args) == 5 and isinstance(args[2], str):
            record.args = (*args[:2], redacted(args[2]), *args[3:])
        return True


class DaemonServer(uvicorn.Server):
    """A uvicorn server whose SIGTERM/SIGINT hand the loops back before anything else stops."""

    def __init__(self, config: uvicorn.Config, app: FastAPI) -> None:
        super().__init__(config)
        self.app = app
        self.unrestored: list[str] = []
        self._stopping: asyncio.Task[None] | None = None

    @contextlib.contextmanager
    def capture_signals(self) -> Generator[None, None, None]:
        """SIGTERM and SIGINT call :meth:`stop_signal` on the event loop while serving (uvicorn's handlers, which
        also re-raise the signal after the shutdown and so end the process by it, are not installed)."""
        loop = asyncio.get_running_loop()
        installed = []
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):  # not in the main thread
                loop.add_signal_handler(sig, self.stop_signal, sig)
                installed.append(sig)
        try:
            yield
        finally:
            for sig in installed:
                loop.remove_signal_handler(sig)

    def stop_signal(self, sig: int) -> None:
        """First signal: hand every loop back, then let uvicorn exit. Later ones: only logged."""
        name = signal.Signals(sig).name
        if self._stopping is not None:
            log.warning("%s again: the hand-back of every loop goes on (it is bounded); not stopping sooner", name)
            return
        log.warning("%s: aborting every experiment and handing every loop back before exiting", name)
        self._stopping = asyncio.get_running_loop().create_task(self._hand_back())

    async def _hand_back(self) -> None:
        manager = getattr(self.app.state, "manager", None)
        try:
            if manager is not None:  # None: a signal before the start finished; the lifespan's stop does it
                self.unrestored = await manager.shutdown()
        except Exception:  # a bug must not keep the server from exiting
            log.exception("the hand-back at shutdown failed")
            self.unrestored = ["?"]
        finally:
            self.should_exit = True

    @property
    def exit_status(self) -> int:
        """0 when every loop was handed back, :data:`NOT_RESTORED_EXIT` when one was not."""
        state_unrestored = getattr(self.app.state, "unrestored", None) or []
        return NOT_RESTORED_EXIT if self.unrestored or state_unrestored else 0


def serve(app: FastAPI, **options: Any) -> int:
    """Serve ``app`` (uvicorn ``options``: host, port, ssl files, ...) until SIGTERM/SIGINT; the exit status."""
    config = uvicorn.Config(app, timeout_graceful_shutdown=GRACEFUL_WAIT, **options)
    access = logging.getLogger("uvicorn.access")
    if not any(isinstance(f, RedactQuery) for f in access.filters):
        access.addFilter(RedactQuery())
    server = DaemonServer(config, app)
    server.run()
    if not server.started:  # the lifespan's start failed (uvicorn.run would exit 3 too)
        return STARTUP_FAILURE
    return server.exit_status
