"""Small helpers shared by the tests (and tests/screenshots.py): a free localhost port, waiting for a
condition, the distribution's Chromium."""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import socket
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from drivers.link import Mode
from drivers.simplc import SimulatedPlc

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


def libfaketime() -> str:
    """The distribution's libfaketime (a wall clock shifted for one process; $AUTOTUNER_FAKETIME, else Debian's);
    a clear failure without it."""
    if os.environ.get("AUTOTUNER_FAKETIME"):
        return os.environ["AUTOTUNER_FAKETIME"]
    found = sorted(Path("/usr/lib").glob("*/faketime/libfaketime.so.1")) + sorted(
        Path("/usr/lib/faketime").glob("libfaketime.so.1"))
    if not found:
        pytest.fail("the clock-step test needs libfaketime: apt-get install faketime (Debian), or set "
                    "AUTOTUNER_FAKETIME to its libfaketime.so.1", pytrace=False)
    return str(found[0])


def chromium_path() -> str:
    """The distribution's Chromium ($AUTOTUNER_CHROMIUM, else ``chromium`` on PATH); a clear failure without it."""
    path = os.environ.get("AUTOTUNER_CHROMIUM") or shutil.which("chromium")
    if path is None or not Path(path).exists():
        pytest.fail("the browser tests need Chromium: apt-get install chromium (Debian), or set AUTOTUNER_CHROMIUM "
                    "to its executable", pytrace=False)
    return path


@contextlib.contextmanager
def logged_in_page(url: str, token: str, timeout_ms: float = 90_000) -> Iterator[Any]:
    """A Playwright page of headless Chromium (1400×900) on the operator page at ``url``, logged in with ``token``
    (the overview shown); at the exit, an AssertionError if the page had a JavaScript error."""
    with chromium() as browser, logged_in(browser, url, token, timeout_ms) as page:
        yield page


@contextlib.contextmanager
def chromium() -> Iterator[Any]:
    """A headless Chromium (Playwright's Browser), closed at the exit; for a module's tests to share."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium_path(), args=CHROMIUM_ARGS)
        try:
            yield browser
        finally:
            browser.close()


@contextlib.contextmanager
def logged_in(browser: Any, url: str, token: str, timeout_ms: float = 90_000) -> Iterator[Any]:
    """A page of its own (a fresh browser context: no cookies or storage of another test) of ``browser``
    (1400×900) on the operator page at ``url``, logged in with ``token`` (the overview shown), waiting at most
    ``timeout_ms`` ms for anything; at the exit, an AssertionError if the page had a JavaScript error."""
    errors: list[str] = []
    context = browser.new_context(viewport={"width": 1400, "height": 900})
    try:
        page = context.new_page()
        page.set_default_timeout(timeout_ms)
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(url)
        page.fill("#token", token)
        page.click("#login button[type=submit]")
        page.wait_for_selector("#loops tbody tr")
        yield page
    finally:
        context.close()
    assert not errors, f"JavaScript errors on the page: {errors[:3]}"


class Daemon:
    """``autotuner serve --config CONFIG`` as a real process on a free port, with ``token`` as $AUTOTUNER_TOKEN.

    Its stdout and stderr go to files (a full pipe must never stall the daemon); :meth:`log` reads them.
    ``env``: more environment variables for it (a preloaded library, say). Use as a context manager: it waits until ``/health`` answers (``timeout`` s) and, on exit, stops the
    daemon with SIGTERM (SIGKILL if it does not exit within 60 s). It runs in a session of its own, so that
    :meth:`kill` ends the whole tuner — the daemon and its sampler processes — as a lost machine would.
    """

    def __init__(self, config: Path, token: str = "test-operator-token", args: tuple[str, ...] = (),
                 timeout: float = 120.0, env: dict[str, str] | None = None) -> None:
        import subprocess
        import sys

        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}/api/v1"
        self.headers = {"Authorization": f"Bearer {token}"}
        self._out = config.parent / f"daemon-{self.port}.log"
        env = {**os.environ, **(env or {}), "AUTOTUNER_TOKEN": token}
        with open(self._out, "w") as out:
            self.proc = subprocess.Popen([sys.executable, "-m", "autotuner.cli", "serve", "--config", str(config),
                                          "--port", str(self.port), *args], env=env, stdout=out, stderr=out,
                                         start_new_session=True)
        self._timeout = timeout

    def log(self) -> str:
        """Everything the daemon printed so far."""
        return self._out.read_text(errors="replace")

    def wait_until(self, predicate: Callable[[], bool], timeout: float, what: str) -> None:
        """Poll ``predicate`` every 50 ms; AssertionError naming ``what`` (and the log) after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what}; daemon log:\n{self.log()}")
            if self.proc.poll() is not None:
                raise AssertionError(f"the daemon exited ({self.proc.returncode}) while waiting for {what}:\n"
                                     f"{self.log()}")
            time.sleep(0.05)

    def __enter__(self) -> Daemon:
        import httpx

        def up() -> bool:
            try:
                return httpx.get(f"{self.base}/health", timeout=5).status_code == 200
            except httpx.TransportError:
                return False

        try:
            self.wait_until(up, self._timeout, "the daemon's /health")
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> int:
        """SIGTERM, then SIGKILL after 60 s; the exit status."""
        import signal
        import subprocess

        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.kill()
        return self.proc.returncode

    def kill(self) -> None:
        """SIGKILL to the whole tuner (the daemon and its samplers), and wait for the daemon's end."""
        import signal

        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait()

    def __exit__(self, *exc: object) -> None:
        self.stop()
        import signal

        with contextlib.suppress(ProcessLookupError):  # nothing of the tuner left behind
            os.killpg(self.proc.pid, signal.SIGKILL)


def record_ticks(plc: SimulatedPlc, ticks: list[tuple[Mode, float]]) -> None:
    """Record (mode, actual MV) after every tick of ``plc``."""
    tick = plc.tick

    def recorded() -> None:
        tick()
        ticks.append((plc.mode, plc.mv))

    plc.tick = recorded


def first_auto(ticks: list[tuple[Mode, float]]) -> int:
    """Index of the first AUTO tick after a MAN one (the hand-back's first sample)."""
    return next(i for i in range(1, len(ticks)) if ticks[i][0] is Mode.AUTO and ticks[i - 1][0] is Mode.MAN)


class TimedLink:
    """A link whose ``read_sample`` calls (a session's PV readings) are time-stamped at completion (``done``,
    monotonic); everything else forwarded. ``session``: it has written an MV (the monitor's links only read)."""

    def __init__(self, link: Any) -> None:
        self._link = link
        self.done: list[float] = []
        self.session = False

    async def read_sample(self) -> Any:
        sample = await self._link.read_sample()
        self.done.append(time.monotonic())
        return sample

    async def write_mv(self, mv: float) -> None:
        self.session = True
        await self._link.write_mv(mv)

    @property
    def pv_age(self) -> float | None:
        return self._link.pv_age

    def __getattr__(self, name: str) -> Any:
        return getattr(self._link, name)


def stamp_reads(loop: Any, links: list[TimedLink]) -> None:
    """Make every link ``loop`` (a loop of a local field) opens from now on a :class:`TimedLink` in ``links``."""
    connect = loop.connect

    def timed() -> TimedLink:
        links.append(TimedLink(connect()))
        return links[-1]

    loop.connect = timed
