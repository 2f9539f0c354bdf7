"""Small helpers shared by the tests (and tests/screenshots.py): a free localhost port, waiting for a
condition, the distribution's Chromium."""

from __future__ import annotations

import asyncio
import os
import shutil
import socket
import time
from collections.abc import Callable
from pathlib import Path

import pytest

# Headless Chromium as root, without its background connections (this machine's network is closed).
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run", "--disable-quic"]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


async def until(predicate: Callable[[], bool], timeout: float, what: str) -> None:
    """Wait (polling every 20 ms) until ``predicate()``; AssertionError naming ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.02)


def chromium_path() -> str:
    """The distribution's Chromium ($AUTOTUNER_CHROMIUM, else ``chromium`` on PATH); a clear failure without it."""
    path = os.environ.get("AUTOTUNER_CHROMIUM") or shutil.which("chromium")
    if path is None or not Path(path).exists():
        pytest.fail("the browser tests need Chromium: apt-get install chromium (Debian), or set AUTOTUNER_CHROMIUM "
                    "to its executable", pytrace=False)
    return path
