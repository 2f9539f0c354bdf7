"""Exactly one owner per loop: with an SQLite history, one daemon per history file.

A daemon on an SQLite history holds an exclusive lock (``flock``) on
``FILE.lock`` beside it for as long as it runs, with its process id written
in it: a second ``autotuner serve`` on the same file finds it taken and
exits 2 naming the file and the other process, before it opens the history
or touches a loop — its start-up recovery would otherwise take the first
daemon's running sessions for crashed ones. The lock is the kernel's: a
daemon that dies, even by SIGKILL, releases it. (Several daemons share a
plant through PostgreSQL and leases: docs/fleet.md.)
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path
from typing import IO

from autotuner.service.history import database_url, sqlite_file


class HistoryInUse(RuntimeError):
    """Another daemon runs on this history file."""


class HistoryLock:
    """The lock of a history file, held until :meth:`release` or the process's end."""

    def __init__(self, path: Path, handle: IO[str]) -> None:
        self.path, self._handle = path, handle

    def release(self) -> None:
        """Let another daemon start on the file."""
        self._handle.close()


def claim_history(history: str) -> HistoryLock | None:
    """Lock the SQLite file of a config's ``history`` for this daemon (None: not an SQLite file, nothing to lock).

    Raises HistoryInUse naming the file and the process that holds it.
    """
    file = sqlite_file(database_url(history))
    if file is None:
        return None
    path = Path(f"{file}.lock")
    handle = path.open("a+")  # not truncated before the lock is ours: the holder's pid stays readable
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.seek(0)
        holder = handle.read().strip() or "unknown"
        handle.close()
        raise HistoryInUse(f"{file}: another daemon (process {holder}) runs on this history; one daemon per "
                           "SQLite history file (several daemons share a plant through PostgreSQL: "
                           "docs/fleet.md)") from None
    handle.seek(0)
    handle.truncate()
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    return HistoryLock(path, handle)
