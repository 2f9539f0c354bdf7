"""The private channel between the daemon and its OPC UA server process: framed messages over a socket pair.

Each message is a tuple ``(kind, ...)``, pickled, behind its length (4 bytes,
big-endian). Both ends are this package's code over an unnamed socket pair
the daemon made, so pickle's trust in its input is the daemon's trust in
itself. The kinds (docs/opcua.md, "Off the sampling path"):

daemon → server
    ``("init", Init)`` first; ``("status", [status, …])`` the changed loops'
    compact statuses (:data:`SNAPSHOT_KEYS`) at the monitor's rate;
    ``("reply", call_id, reply)`` a method call's outcome; ``("stop",)``.
server → daemon
    ``("ready",)`` or ``("failed", message)`` once, after the init;
    ``("call", call_id, loop_id, action, body, user)`` a method (action tune,
    abort or apply; body the validated TUNE body for tune, else None);
    ``("log", logger, level, message)`` a log record for the daemon's log.
"""

from __future__ import annotations

import asyncio
import pickle
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from autotuner.service.config import OpcUaConfig, OpcUaUser

_LENGTH = struct.Struct("!I")
# The members of a loop's REST status (Loop.as_json) the address space reads after the first one (which is whole:
# description and units too); the rest never change while the daemon runs or are not published.
SNAPSHOT_KEYS = ("id", "pv", "sp", "mv", "mode", "current_gains", "tbsy", "te", "ite", "stage", "progress", "message",
                 "session", "controller", "point", "static_gain", "gains", "pending_gains", "monitor_error")


@dataclass(frozen=True)
class Init:
    """What the server process needs to start: its settings, users, endpoint and certificate folder, the log
    levels of the daemon (``levels``: logger name → level; "" the root), and every loop's whole status with its
    monitor period (wall seconds), in the config's order."""

    config: OpcUaConfig
    users: list[OpcUaUser]
    url: str
    cert_dir: Path
    levels: dict[str, int]
    loops: list[tuple[dict[str, Any], float]]


def snapshot(status: dict[str, Any]) -> dict[str, Any]:
    """The compact status of a loop sent at the monitor's rate: :data:`SNAPSHOT_KEYS` of its REST status."""
    return {key: status[key] for key in SNAPSHOT_KEYS}


class Channel:
    """One end of the socket pair as asyncio streams: :meth:`send` a message, :meth:`receive` the next one."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._reader, self._writer = reader, writer

    @classmethod
    async def open(cls, sock: Any) -> Channel:
        """The channel over the connected socket ``sock`` (on the running event loop)."""
        reader, writer = await asyncio.open_connection(sock=sock)
        return cls(reader, writer)

    def send(self, *message: Any) -> None:
        """Queue ``message`` for sending (never blocks; the transport buffers it). Nothing when the peer left."""
        if self._writer.is_closing():
            return
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        self._writer.write(_LENGTH.pack(len(data)) + data)

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
