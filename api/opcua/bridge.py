"""The daemon's side of the OPC UA server: the server's process, fed the loops' statuses, its method calls run here.

asyncua is pure Python: encoding the data changes of every loop's variables
at the monitor's rate is CPU work, and in a thread of the daemon it held the
GIL in bursts that made the sessions' samples late (docs/opcua.md, "Load
benchmark"). So the server runs in a process of its own
(:mod:`api.opcua.server`, ``python -m api.opcua.server FD``) and this end,
on the daemon's event loop, does only the little work of the daemon's side:

- every ``monitor_period`` wall seconds (one task per distinct period) the
  compact status of each loop whose status changed goes to the server
  (:mod:`api.opcua.wire`);
- the server's method calls (Tune, Break, Apply, AutoTuningOn/Off; already
  validated and checked for the role there) run on the same
  :class:`~autotuner.service.daemon.LoopManager` as REST's, so both see the
  same busy state, exclusion groups and history, and get its refusals;
- the server's log records join the daemon's log.

The process ends with the daemon: :meth:`OpcUaProcess.stop` asks it to
(SIGKILL after :data:`STOP_WAIT`), and if the daemon dies without that (a
SIGKILL), the server sees its end of the socket pair close and exits,
releasing its port.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import subprocess
import tempfile
from pathlib import Path
from typing import Any

from autotuner.service.channel import cpu_seconds, log_levels, log_record, start_child
from autotuner.service.config import OpcUaConfig, OpcUaUser, TuneRequest
from autotuner.service.daemon import LoopManager, Refused

from . import StartError, endpoint_url
from .wire import Channel, Init, snapshot

log = logging.getLogger("autotuner.api.opcua")

# How long start waits for the server to listen (it builds the address space first), and stop for it to end,
# wall seconds.
START_WAIT, STOP_WAIT = 60.0, 20.0
# The loggers whose levels the server process takes from the daemon's (its records come back to the daemon's log).
LEVELS = ("", "asyncua", "autotuner")


class OpcUaProcess:
    """The OPC UA server of ``manager``'s loops, run in a process of its own; :meth:`start` and :meth:`stop` from
    the daemon's event loop.

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
        self.process: subprocess.Popen[bytes] | None = None
        self._channel: Channel | None = None
        self._tasks: set[asyncio.Task[Any]] = set()  # the listener and the publishers
        self._calls: set[asyncio.Task[Any]] = set()  # the method calls under way
        self._sent: dict[str, dict[str, Any]] = {}
        self.sessions = 0  # client sessions open (the server says when it changes)

    # -- life cycle ---------------------------------------------------------------------------------------------

    async def start(self) -> str:
        """Start the server process and wait until it listens; its endpoint URL. :class:`StartError` with the
        server's error (a port in use, an unreadable certificate) if it cannot start."""
        self.process, ours = start_child("api.opcua.server")
        self._channel = await Channel.open(ours)
        try:
            await asyncio.wait_for(self._handshake(), START_WAIT)
        except asyncio.TimeoutError:
            await self.stop()
            raise StartError(f"the OPC UA server did not listen within {START_WAIT:g} s") from None
        except BaseException:
            await self.stop()
            raise
        self._spawn(self._listen())
        for period, ids in self._periods().items():
            self._spawn(self._publish(ids, period))
        log.info("OPC UA server at %s (process %d)", self.url, self.process.pid)
        return self.url

    async def _handshake(self) -> None:
        assert self._channel is not None
        statuses = [loop.as_json() for loop in self.manager.loops.values()]
        self._sent = {s["id"]: snapshot(s) for s in statuses}
        levels = log_levels(LEVELS)
        self._channel.send("init", Init(self.config, self.users, self.url, self.cert_dir, levels, [
            (s, self.manager.loops[s["id"]].config.monitor_period) for s in statuses]))
        while True:
            message = await self._channel.receive()
            if message is None:
                raise StartError(f"the OPC UA server process ended (exit code {self._exit_code()}) before it "
                                 "listened")
            if message[0] == "log":
                log_record(*message[1:])
            elif message[0] == "failed":
                raise StartError(f"the OPC UA server could not start: {message[1]}")
            elif message[0] == "ready":
                return

    async def stop(self) -> None:
        """Stop the server (clients are disconnected) and wait for its process to end."""
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        # Calls under way finish (a TUNE cut between its checks and its start would be neither refused nor run).
        await asyncio.gather(*self._calls, return_exceptions=True)
        channel, self._channel = self._channel, None
        if channel is not None:
            # The statuses since the last period first: a stop right after the hand-back of a SIGTERM would
            # otherwise leave the clients with TBSY still set and no TE event of the sessions it aborted.
            self._send_changed(channel, list(self.manager.loops))
            channel.send("stop")
            await channel.close()
        process = self.process
        if process is not None and process.poll() is None:
            try:
                await asyncio.to_thread(process.wait, STOP_WAIT)
            except subprocess.TimeoutExpired:
                log.warning("the OPC UA server process did not stop within %g s: killed", STOP_WAIT)
                process.kill()
                await asyncio.to_thread(process.wait)
        if self._scratch is not None:
            self._scratch.cleanup()

    def cpu_time(self) -> float | None:
        """CPU seconds (user + system) the server's process has used so far; None where /proc is missing."""
        return None if self.process is None else cpu_seconds(self.process.pid)

    def _exit_code(self) -> int | None:
        return None if self.process is None else self.process.poll()

    def _spawn(self, coro: Any, tasks: set[asyncio.Task[Any]] | None = None) -> None:
        tasks = self._tasks if tasks is None else tasks
        task = asyncio.create_task(coro)
        tasks.add(task)
        task.add_done_callback(tasks.discard)

    def _periods(self) -> dict[float, list[str]]:
        """The loops by monitor period (one publisher each)."""
        periods: dict[float, list[str]] = {}
        for loop_id, loop in self.manager.loops.items():
            periods.setdefault(loop.config.monitor_period, []).append(loop_id)
        return periods

    # -- the daemon's event loop ------------------------------------------------------------------------------

    async def _publish(self, ids: list[str], period: float) -> None:
        """Every ``period`` wall seconds: the compact statuses of those of ``ids`` that changed, to the server."""
        for _ in itertools.count():
            await asyncio.sleep(period)
            if self._channel is not None:
                self._send_changed(self._channel, ids)

    def _send_changed(self, channel: Channel, ids: list[str]) -> None:
        """The compact statuses of those of ``ids`` that changed since they were last sent, to the server."""
        try:
            changed = [s for s in (snapshot(self.manager.loops[i].as_json()) for i in ids)
                       if self._sent.get(s["id"]) != s]
        except Exception:  # a bug must not end the publishing of every loop
            log.exception("OPC UA: publishing the loops' status failed")
            return
        if changed:
            self._sent.update((s["id"], s) for s in changed)
            channel.send("status", changed)

    async def _listen(self) -> None:
        """The server's messages until it ends: method calls (each in a task of its own) and log records."""
        assert self._channel is not None
        while (message := await self._channel.receive()) is not None:
            if message[0] == "call":
                self._spawn(self._call(*message[1:]), self._calls)
            elif message[0] == "log":
                log_record(*message[1:])
            elif message[0] == "sessions":
                self.sessions = message[1]
        if self._channel is not None:  # not stopping: it died
            log.error("the OPC UA server process ended (exit code %s); the REST API goes on without it",
                      await asyncio.to_thread(self.process.wait))  # type: ignore[union-attr]

    async def _call(self, call_id: int, loop_id: str, action: str, body: dict[str, Any] | None, user: str) -> None:
        """Run ``action`` (tune, abort, apply) for ``user`` and reply: ("ok", session, message, the loop's
        compact status), ("refused", code, message), or ("error", text) for a bug."""
        try:
            if action == "tune":
                sid = await self.manager.request_tune(loop_id, TuneRequest.model_validate(body or {}), user)
                message = "tuning"
            elif action == "abort":
                sid, message = self.manager.abort(loop_id), "aborting: the loop is being restored"
            else:
                applied = await self.manager.apply(loop_id, None, user)
                sid, message = applied["session"], "applied: " + ", ".join(
                    f"{k}={v:.6g}" for k, v in applied["gains"].items() if v is not None)
            status = snapshot(self.manager.loops[loop_id].as_json())
            self._sent[loop_id] = status
            reply: tuple[Any, ...] = ("ok", sid, message, status)
        except Refused as exc:
            reply = ("refused", exc.code, exc.message)
        except ValueError as exc:
            reply = ("refused", "invalid", str(exc))
        except Exception as exc:  # a bug: the server answers BadInternalError, the daemon logs it
            log.exception("OPC UA: %s of loop %s failed", action, loop_id)
            reply = ("error", f"{type(exc).__name__}: {exc}")
        if self._channel is not None:
            self._channel.send("reply", call_id, reply)
