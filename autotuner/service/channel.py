"""The daemon and its child processes (samplers, the OPC UA server): framed messages over a socket pair.

Each message is a tuple ``(kind, ...)``, pickled, behind its length (4 bytes,
big-endian). Both ends are this project's code over an unnamed socket pair
the daemon made, so pickle's trust in its input is the daemon's trust in
itself. :class:`Channel` carries the messages; :func:`start_child` starts
``python -m MODULE FD`` with the other end; :class:`Forward` sends a child's
log records to the daemon, where :func:`log_record` logs them as if logged
there; :class:`Peer` makes calls with replies and notifications of a channel.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import pickle
import socket
import struct
import subprocess
import sys
import threading
import traceback
from collections.abc import Awaitable
from pathlib import Path
from typing import Any

_LENGTH = struct.Struct("!I")
# The folder holding the project's packages (a child imports them from there, as the daemon did).
_SOURCE = Path(__file__).resolve().parents[2]


class Channel:
    """One end of the socket pair as asyncio streams: :meth:`send` a message, :meth:`receive` the next one."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._reader, self._writer = reader, writer

    @classmethod
    async def open(cls, sock: Any) -> Channel:
        """The channel over the connected socket ``sock`` (on the running event loop)."""
        reader, writer = await asyncio.open_connection(sock=sock, limit=2 ** 24)
        return cls(reader, writer)

    def send(self, *message: Any) -> None:
        """Queue ``message`` for sending (never blocks; the transport buffers it). Nothing when the peer left."""
        if self._writer.is_closing():
            return
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        self._writer.write(_LENGTH.pack(len(data)) + data)

    @property
    def buffered(self) -> int:
        """Bytes queued for sending and not sent yet (a peer that does not read lets them grow)."""
        return self._writer.transport.get_write_buffer_size()

    async def receive(self) -> tuple[Any, ...] | None:
        """The next message; None when the peer closed its end (or died)."""
        try:
            size = _LENGTH.unpack(await self._reader.readexactly(_LENGTH.size))[0]
            return pickle.loads(await self._reader.readexactly(size))  # noqa: S301 - our own process' messages
        except (asyncio.IncompleteReadError, ConnectionError):
            return None

    async def close(self) -> None:
        """Close this end (the peer's :meth:`receive` returns None)."""
        self._writer.close()
        try:
            await self._writer.wait_closed()
        except (ConnectionError, OSError):
            pass


def start_child(module: str) -> tuple[subprocess.Popen[bytes], socket.socket]:
    """Start ``python -m module FD`` with one end of a new socket pair (``FD``); the process and our end.

    Popen, not an asyncio subprocess: it works from any thread's event loop
    (tests run the app in one).
    """
    ours, theirs = socket.socketpair()
    try:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (str(_SOURCE),
                                                                      os.environ.get("PYTHONPATH"))))}
        process = subprocess.Popen([sys.executable, "-m", module, str(theirs.fileno())], pass_fds=(theirs.fileno(),),
                                   stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, env=env)
    except BaseException:
        ours.close()
        raise
    finally:
        theirs.close()
    return process, ours


def cpu_seconds(pid: int) -> float | None:
    """CPU seconds (user + system) process ``pid`` has used so far; None where /proc is missing or it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    utime, stime = stat.rpartition(")")[2].split()[11:13]  # fields 14 and 15 of proc(5)
    return (int(utime) + int(stime)) / os.sysconf("SC_CLK_TCK")


def descendants(pid: int) -> list[int]:
    """The processes running now that ``pid`` started, and those they started (none where /proc is missing)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            parent = int(stat.read_text().rpartition(")")[2].split()[1])  # field 4 of proc(5)
        except (OSError, IndexError, ValueError):
            continue  # gone meanwhile
        children.setdefault(parent, []).append(int(stat.parent.name))
    found, todo = [], list(children.get(pid, []))
    while todo:
        found.append(current := todo.pop())
        todo.extend(children.get(current, []))
    return found


def tree_cpu_seconds(pid: int) -> float | None:
    """CPU seconds process ``pid`` and its :func:`descendants` have used so far; None where /proc is missing or
    ``pid`` is gone. (A sampler's analysis workers count as the sampler's.)"""
    own = cpu_seconds(pid)
    return None if own is None else own + sum(cpu_seconds(child) or 0.0 for child in descendants(pid))


class Forward(logging.Handler):
    """Sends every record to the daemon's log over ``channel`` (the traceback, if any, in the message)."""

    def __init__(self, channel: Channel) -> None:
        super().__init__()
        self.channel = channel
        self._loop = asyncio.get_running_loop()

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = record.getMessage()
            if record.exc_info:
                message += "\n" + "".join(traceback.format_exception(*record.exc_info)).rstrip()
            item = ("log", record.name, record.levelno, message)
            if threading.get_ident() == self._loop._thread_id:  # type: ignore[attr-defined]
                self.channel.send(*item)
            else:  # libraries log from their threads too; the transport is the event loop's only
                self._loop.call_soon_threadsafe(self.channel.send, *item)
        except Exception:  # the channel is gone: nobody to tell
            self.handleError(record)


def log_record(name: str, level: int, message: str) -> None:
    """A child's record into the daemon's log, as if logged here."""
    logger = logging.getLogger(name)
    if logger.isEnabledFor(level):
        with contextlib.suppress(Exception):  # a broken handler must not end the caller
            logger.log(level, "%s", message)


def log_levels(names: tuple[str, ...]) -> dict[str, int]:
    """The effective levels of the loggers ``names`` ("" the root), for a child to take."""
    return {name: logging.getLogger(name).getEffectiveLevel() for name in names}


def forward_logs(channel: Channel, levels: dict[str, int]) -> None:
    """In a child: every record to the daemon over ``channel``, the loggers at the daemon's ``levels``."""
    logging.getLogger().handlers[:] = [Forward(channel)]
    for name, level in levels.items():
        logging.getLogger(name or None).setLevel(level)


async def child_start(fd: int) -> tuple[Channel, Any] | None:
    """In a child process: its channel to the daemon over the socket ``fd`` and the daemon's ``("init", init)``
    (its log records forwarded from now on, the loggers at ``init.levels``); None if the daemon sends no init."""
    channel = await Channel.open(socket.socket(fileno=fd))
    message = await channel.receive()
    if message is None or message[0] != "init":
        await channel.close()
        return None
    forward_logs(channel, message[1].levels)
    return channel, message[1]


class PeerLost(ConnectionError):
    """The process at the other end of a channel ended (or closed it) before it answered."""


class Peer:
    """Calls with replies and one-way notifications over ``channel``, in both directions.

    ``("call", id, op, args)`` runs ``handler.<op>(*args)`` at the other end
    (a coroutine function: each call in a task of its own) and comes back as
    ``("reply", id, ok, value)`` — the value, or the exception raised there.
    ``("note", op, args)`` runs ``handler.<op>(*args)`` (a plain function) and
    answers nothing. ``("log", …)`` records go to the log. Only the names in
    ``calls`` and ``notes`` are served.
    """

    def __init__(self, channel: Channel, handler: object, calls: frozenset[str], notes: frozenset[str]) -> None:
        self.channel, self.handler, self.calls, self.notes = channel, handler, calls, notes
        self._ids = itertools.count()
        self._waiting: dict[int, asyncio.Future[Any]] = {}
        self._tasks: set[asyncio.Task[Any]] = set()
        self.lost: str | None = None  # why the peer is gone (None: it is there)

    async def call(self, op: str, *args: Any) -> Any:
        """``op(*args)`` at the other end: its value, or its exception raised here; PeerLost if it ends first."""
        if self.lost is not None:
            raise PeerLost(self.lost)
        call_id = next(self._ids)
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._waiting[call_id] = future
        try:
            self.channel.send("call", call_id, op, args)
            return await future
        finally:
            self._waiting.pop(call_id, None)

    def note(self, op: str, *args: Any) -> None:
        """``op(*args)`` at the other end, no answer."""
        self.channel.send("note", op, args)

    async def serve(self, close: bool = True) -> None:
        """Receive until the channel closes; then (with ``close``) every call waiting fails with PeerLost — the
        owner may instead :meth:`close` with a better reason."""
        while (message := await self.channel.receive()) is not None:
            kind = message[0]
            if kind == "reply":
                self._replied(*message[1:])
            elif kind == "call":
                self._spawn(self._answer(*message[1:]))
            elif kind == "note":
                self._notified(*message[1:])
            elif kind == "log":
                log_record(*message[1:])
        if close:
            self.close("the other end closed the channel")

    async def drain(self, timeout: float) -> None:
        """Wait (at most ``timeout`` seconds) for the calls this end is answering."""
        if self._tasks:
            await asyncio.wait(set(self._tasks), timeout=timeout)

    def close(self, why: str) -> None:
        """The peer is gone (``why``): the calls waiting for it fail with PeerLost."""
        self.lost = why
        for future in self._waiting.values():
            if not future.done():
                future.set_exception(PeerLost(why))

    def _replied(self, call_id: int, ok: bool, value: Any) -> None:
        future = self._waiting.get(call_id)
        if future is not None and not future.done():
            if ok:
                future.set_result(value)
            else:
                future.set_exception(value)

    async def _answer(self, call_id: int, op: str, args: tuple[Any, ...]) -> None:
        try:
            if op not in self.calls:
                raise ValueError(f"no call {op!r}")
            value = await getattr(self.handler, op)(*args)
        except asyncio.CancelledError:
            self.channel.send("reply", call_id, False, PeerLost("the call was cancelled"))
            raise
        except Exception as exc:
            self.channel.send("reply", call_id, False, _sendable(exc))
            return
        self.channel.send("reply", call_id, True, value)

    def _notified(self, op: str, args: tuple[Any, ...]) -> None:
        if op not in self.notes:
            logging.getLogger("autotuner.service.channel").error("no notification %r", op)
            return
        try:
            getattr(self.handler, op)(*args)
        except Exception:  # one bad notification must not end the channel
            logging.getLogger("autotuner.service.channel").exception("notification %s failed", op)

    def _spawn(self, coro: Awaitable[Any]) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)


def _sendable(exc: Exception) -> Exception:
    """``exc`` if it pickles, else a RuntimeError naming it."""
    try:
        pickle.dumps(exc)
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")
    return exc
