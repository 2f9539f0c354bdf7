"""The operator page in a real headless browser (Debian's Chromium driven by Playwright) against a real
``autotuner serve``: the built-in demo's loops (the demo plant) (at 12× real time for margin on a busy machine, with a viewer
token and LIC-201/FIC-301 in one exclusion group), the operator's token from $AUTOTUNER_TOKEN.

Between the browser and the daemon sits a small TCP proxy of this module, so a test can cut the network and check
that the page says the live stream is lost and reconnects by itself.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from datetime import datetime

import httpx
import pytest
import yaml

from api.auth import token_hash
from autotuner.service.demo import demo_config
from helpers import CHROMIUM_ARGS, chromium_path, free_port
from playwright.sync_api import sync_playwright

OPERATOR, VIEWER = "browser-operator-secret", "browser-viewer-secret"
SPEED = 12.0
# Generous: the plants run in real time (scaled) on a machine shared with the rest of the suite.
TIMEOUT_MS = 90_000


class Proxy:
    """A TCP proxy 127.0.0.1:port → target; :meth:`down` cuts every connection and refuses new ones until :meth:`up`."""

    def __init__(self, target_port: int) -> None:
        self.target = ("127.0.0.1", target_port)
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.is_up = True
        self.sockets: set[socket.socket] = set()
        self.lock = threading.Lock()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.server.accept()
            except OSError:
                return
            if not self.is_up:
                client.close()
                continue
            try:
                upstream = socket.create_connection(self.target)
            except OSError:
                client.close()
                continue
            with self.lock:
                self.sockets |= {client, upstream}
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                with self.lock:
                    self.sockets.discard(s)
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()

    def down(self) -> None:
        self.is_up = False
        with self.lock:
            sockets = list(self.sockets)
        for s in sockets:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def up(self) -> None:
        self.is_up = True

    def close(self) -> None:
        self.down()
        self.server.close()


class Daemon:
    """A running ``autotuner serve``: its API through httpx (as the operator), the page's URL through the proxy."""

    def __init__(self, port: int, proxy: Proxy) -> None:
        self.api = f"http://127.0.0.1:{port}/api/v1"
        self.url = f"http://127.0.0.1:{proxy.port}/"
        self.proxy = proxy
        self.headers = {"Authorization": f"Bearer {OPERATOR}"}

    def get(self, path: str):
        r = httpx.get(self.api + path, headers=self.headers, timeout=30)
        r.raise_for_status()
        return r.json()

    def post(self, path: str, body: dict | None = None) -> httpx.Response:
        return httpx.post(self.api + path, headers=self.headers, json=body, timeout=30)

    def wait_idle(self, loop_id: str, timeout: float = 90.0) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            status = self.get(f"/loops/{loop_id}")
            if not status["tbsy"]:
                return status
            time.sleep(0.2)
        raise AssertionError(f"{loop_id} still busy after {timeout} s")


@pytest.fixture(scope="module")
def daemon(tmp_path_factory) -> Iterator[Daemon]:
    tmp = tmp_path_factory.mktemp("browser")
    config = demo_config(SPEED).model_dump(mode="json", exclude_defaults=True)
    config["history"] = str(tmp / "history.sqlite")
    config["tokens"] = [{"name": "hmi", "role": "viewer", "sha256": token_hash(VIEWER)}]
    for loop in config["loops"]:
        if loop["id"] in ("LIC-201", "FIC-301"):
            loop["group"] = "utilities"
        if loop["id"] == "FIC-301":
            loop["units"]["pv_range"] = [0.0, 100.0]  # a display range well beyond the PV's (about 50)
    (tmp / "daemon.yaml").write_text(yaml.safe_dump(config))
    port = free_port()
    log = (tmp / "daemon.log").open("w")
    env = {**os.environ, "AUTOTUNER_TOKEN": OPERATOR}
    proc = subprocess.Popen([sys.executable, "-m", "autotuner.cli", "serve", "--config", str(tmp / "daemon.yaml"),
                             "--port", str(port)], env=env, stdout=log, stderr=subprocess.STDOUT)
    proxy = Proxy(port)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/api/v1/health").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert proc.poll() is None and time.monotonic() < deadline, (tmp / "daemon.log").read_text()
            time.sleep(0.1)
        yield Daemon(port, proxy)
    finally:
        proxy.close()
        proc.terminate()
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=chromium_path(), args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture
def page(browser, daemon):
    context = browser.new_context(viewport={"width": 1400, "height": 900})
    page = context.new_page()
    page.set_default_timeout(TIMEOUT_MS)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    page.on("console", lambda msg: errors.append(msg.text) if "Content Security Policy" in msg.text else None)
    yield page
    context.close()
    assert not errors, f"JavaScript or Content-Security-Policy errors on the page: {sorted(set(errors))[:3]}"


def login(page, daemon: Daemon, token: str, role: str) -> None:
    page.goto(daemon.url)
    page.fill("#token", token)
    page.click("#login button[type=submit]")
    page.wait_for_selector(f"#who [data-role={role}]")
    page.wait_for_selector("#loops tbody tr")


def number(text: str) -> float:
    return float(text.strip().replace("−", "-"))


def close(shown: float, actual: float) -> bool:
    """``shown`` is ``actual`` to the page's 4 significant digits."""
    return abs(shown - actual) <= 1e-3 * abs(actual) + 1e-12


def wait_attr_above(page, selector: str, attr: str, value: float) -> float:
    page.wait_for_function(
        "([s, a, v]) => { const e = document.querySelector(s); return e && Number(e.getAttribute(a)) > v; }",
        arg=[selector, attr, value])
    return float(page.get_attribute(selector, attr))


# Watches the actions card: every redraw sets TBRK's tooltip (counted in window.redraws), and window.offered
# collects the ids of its buttons that were left enabled at any moment (cleared by the test).
WATCH_ACTIONS = """() => {
  window.redraws = 0;
  window.offered = new Set();
  new MutationObserver((records) => {
    for (const r of records) {
      if (r.attributeName === "title" && r.target.id === "tbrk") window.redraws += 1;
      if (r.attributeName === "disabled" && r.target.id && !r.target.disabled) window.offered.add(r.target.id);
    }
  }).observe(document.querySelector("#actions"), { attributes: true, subtree: true, attributeFilter: ["title", "disabled"] });
}"""


@contextmanager
def held(page, path: str) -> Iterator[list]:
    """While inside: the page's requests to the API's ``path`` are held (the list of their Playwright routes);
    at the exit they go on to the daemon."""
    routes: list = []
    pattern = f"**/api/v1{path}"

    def hold(route) -> None:
        routes.append(route)

    page.route(pattern, hold)
    try:
        yield routes
    finally:
        for route in routes:
            route.continue_()
        page.unroute(pattern)


def arrived(page, routes: list, count: int = 1) -> None:
    """Wait until ``count`` requests are held in ``routes`` (Playwright delivers them while the test waits)."""
    deadline = time.monotonic() + TIMEOUT_MS / 1000
    while len(routes) < count:
        assert time.monotonic() < deadline, f"{count} request(s) expected, {len(routes)} held"
        page.wait_for_timeout(50)


def redrawn_by_a_state_event(page, daemon: Daemon) -> None:
    """The loop page's stream cut and reconnected: the new stream starts with the loop's state, which redraws the
    cards; returns once the actions card has been redrawn (WATCH_ACTIONS installed)."""
    before = page.evaluate("window.redraws")
    daemon.proxy.down()
    try:
        page.locator("[data-banner=stream]").wait_for()
    finally:
        daemon.proxy.up()
    page.locator("[data-banner=stream]").wait_for(state="detached")
    page.wait_for_function("(n) => window.redraws > n", arg=before)


# The pointer events the page receives and its route changes, in window.pointerLog: a click that was lost shows
# as a mousedown and a mouseup with no click after them ("connected" false: the target was out of the document).
POINTER_LOG = """
window.pointerLog = [];
for (const type of ["mousedown", "mouseup", "click"]) {
  document.addEventListener(type, (e) => window.pointerLog.push(
    `${type} ${e.target.id || e.target.tagName} connected=${e.target.isConnected}`), true);
}
window.addEventListener("hashchange", () => window.pointerLog.push(`hashchange ${location.hash}`));
"""


@contextmanager
def evidence_on_failure(page, daemon: Daemon, loop_id: str, directory: Path) -> Iterator[None]:
    """On a failure inside: a screenshot of ``page`` in ``directory``, and in the failure's notes what the page
    showed (URL, heading, alerts), its console, its pointer events (POINTER_LOG, if installed) and the loop's
    newest sessions in the daemon's history."""
    console: list[str] = []
    page.on("console", lambda msg: console.append(f"{msg.type}: {msg.text}"))
    try:
        yield
    except Exception as exc:
        def screenshot() -> str:
            page.screenshot(path=directory / "failure.png", full_page=True, timeout=10_000)
            return str(directory / "failure.png")

        for what, read in (
                ("screenshot", screenshot),
                ("url", lambda: page.url),
                ("page", lambda: page.evaluate("() => [document.querySelector('#main h1, #main h2')?.textContent,"
                                               " ...[...document.querySelectorAll('[role=alert], .banner')]"
                                               ".map((e) => e.textContent)]")),
                ("pointer", lambda: page.evaluate("() => window.pointerLog")),
                ("console", lambda: console[-20:]),
                ("history", lambda: [{k: s.get(k) for k in ("id", "state", "outcome", "applied_at")}
                                     for s in daemon.get(f"/loops/{loop_id}/history?limit=3")])):
            try:
                exc.add_note(f"{what}: {read()}")
            except Exception as why:  # the evidence is best effort: never hide the failure itself
                exc.add_note(f"{what}: not read ({why})")
        raise


@pytest.mark.parametrize("link,opened", [("#tab-history", "#tab-history.active"), (".loop-head .title a", "#loops")])
def test_a_click_on_the_loop_heads_links_is_not_lost_to_a_redraw_between_press_and_release(
        page, daemon, tmp_path, link, opened):
    """The mouse pressed on the History tab (or "← all loops"), a state event redraws the loop page (the stream cut
    and reconnected starts with the loop's state), the mouse released there: the view opens. Chromium sends no
    click when the pressed element left the document before the release, and the head's redraw took its links out
    for a moment: after an apply (state events coming) the screen-size test waited 90 s for the history."""
    page.add_init_script(POINTER_LOG)
    login(page, daemon, OPERATOR, "operator")
    with evidence_on_failure(page, daemon, "TIC-101", tmp_path):
        page.goto(daemon.url + "#/loop/TIC-101")
        page.wait_for_selector("#tune:enabled")
        page.evaluate(WATCH_ACTIONS)
        box = page.locator(link).bounding_box()
        page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        page.mouse.down()
        redrawn_by_a_state_event(page, daemon)
        page.mouse.up()
        page.wait_for_selector(opened)


def test_login_with_an_unknown_token_is_refused_in_words(page, daemon):
    page.goto(daemon.url)
    page.fill("#token", "not-a-token")
    page.click("#login button[type=submit]")
    assert "not known to the daemon (401)" in page.inner_text("#login-msg .alert")
    assert page.evaluate("sessionStorage.getItem('autotuner.token')") is None


def test_operator_tunes_from_the_page_applies_the_gains_and_finds_the_session_in_history(page, daemon):
    daemon.wait_idle("TIC-101")
    login(page, daemon, OPERATOR, "operator")
    # The overview: every loop, its description and live PV/SP/MV from the monitor.
    rows = page.locator("#loops tbody tr")
    assert rows.count() == len(demo_config(SPEED).loops)  # the demo plant's
    assert "two lags with dead time" in page.inner_text("tr[data-loop=TIC-101]")
    page.wait_for_function("() => /\\d/.test(document.querySelector('tr[data-loop=TIC-101] [data-col=pv]').textContent)")
    # The token stays in the tab's session storage, nowhere else.
    assert page.evaluate("sessionStorage.getItem('autotuner.token')") == OPERATOR
    assert page.evaluate("localStorage.length") == 0

    page.click("tr[data-loop=TIC-101] a.loop-id")
    page.wait_for_selector("#tune:enabled")
    assert page.is_disabled("#tbrk")
    # The TUNE form shows the loop's configured defaults (the demo's amp 5, phase 135°, Ms 1.4).
    assert float(page.input_value("#f-amp")) == 5.0
    assert float(page.input_value("#f-phase")) == 135.0 and float(page.input_value("#f-ms")) == 1.4
    assert page.input_value("#f-controller") == "PI" and page.input_value("#f-apply") == "false"
    page.select_option("#f-controller", "PI")
    page.select_option("#f-apply", "false")
    page.click("#tune")
    # Running: TBSY 1, ite counts down, the stage and progress show, the trend grows.
    page.wait_for_selector("#status [data-flag=tbsy]:has-text('TBSY 1')")
    assert page.inner_text("#badge") == "TUNING"
    assert page.is_disabled("#tune") and page.is_enabled("#tbrk") and page.is_disabled("#apply")
    ite = page.inner_text("#status [data-flag=ite]")
    page.wait_for_function("(v) => { const e = document.querySelector('#status [data-flag=ite]');"
                           " return e && e.textContent !== v && document.querySelector('#badge').textContent === 'TUNING'; }",
                           arg=ite)
    assert "Stage:" in page.inner_text("#stage")
    first = wait_attr_above(page, "#trend", "data-samples", 20)
    points = int(page.get_attribute("#trend path[data-series=PV]", "data-points"))
    wait_attr_above(page, "#trend", "data-samples", first + 20)
    page.wait_for_function("(n) => Number(document.querySelector('#trend path[data-series=PV]')"
                           ".getAttribute('data-points')) > n", arg=points)
    assert page.locator("#trend path[data-series='relay ±1']").count() == 1  # the relay output while running
    # Finished: the Nyquist plot with the identified point and the Ms circle, the gains, the simulated steps.
    page.wait_for_selector("#badge:has-text('OK')")
    assert page.inner_text("#stage") == "code 0 OK"  # once: not "code 0 OK: ok"
    assert page.inner_text("#status [data-flag=tbsy]") == "TBSY 0"
    assert page.inner_text("#status [data-flag=ite]") == "ite 0"
    page.wait_for_selector("#nyquist [data-role=point]")
    assert page.locator("#nyquist [data-role=ms-circle]").count() == 1
    assert page.locator("#nyquist [data-role=critical]").count() == 1
    assert page.locator("#nyquist path[data-series='L new']").count() == 1
    assert page.locator("#nyquist path[data-series='L old']").count() == 1
    for step in ("#step-setpoint", "#step-load"):
        assert page.locator(f"{step} path[data-series='PV new']").count() == 1
        assert page.locator(f"{step} path[data-series='PV old']").count() == 1
    status = daemon.get("/loops/TIC-101")
    assert status["te"] is False and status["pending_gains"] is True
    gains, before = status["gains"], status["current_gains"]
    for key in ("pk", "pti", "pb"):
        assert close(number(page.inner_text(f"#gains tr[data-gain={key}] td.new")), gains[key]), key
        assert close(number(page.inner_text(f"#gains tr[data-gain={key}] td.old")), before[key]), key
    assert "series (interacting)" in page.text_content("#gains") and "parallel" in page.text_content("#gains")

    # The controller's gains now, read from the device, on the loop page.
    assert close(number(page.inner_text("#current-gains [data-current=pk]")), before["pk"])
    assert page.inner_text("#result #applied") == "NOT APPLIED YET"
    # Apply: the dialog lists every parameter that changes, now → new; confirm, then the controller has the new
    # gains, nothing is pending, and the result card says applied.
    page.click("#apply:enabled")
    changed = {k for k in ("pk", "pti", "ptd", "pnd", "pb", "pc")
               if before[k] is None or gains[k] is None or abs(before[k] - gains[k]) > 1e-9 * max(1, abs(gains[k]))}
    assert {"pk", "pti", "pb"} <= changed
    shown = set(page.eval_on_selector_all("#apply-changes tr[data-param]", "rows => rows.map(r => r.dataset.param)"))
    assert shown == changed
    for key in changed:
        row = page.inner_text(f"#apply-changes tr[data-param={key}]")
        assert "→" in row
        assert close(number(page.inner_text(f"#apply-changes tr[data-param={key}] td.new").removesuffix(" s")), gains[key])
    # The apply under way (its request held): "Apply gains…" stays disabled across a redraw from a state event.
    page.evaluate(WATCH_ACTIONS)
    with held(page, "/loops/TIC-101/apply") as applying:
        page.click("#apply-confirm")
        arrived(page, applying)
        assert page.is_disabled("#apply")
        redrawn_by_a_state_event(page, daemon)
        assert page.is_disabled("#apply") and page.locator("#apply-dialog").count() == 0
        assert "apply" not in page.evaluate("[...window.offered]")
    page.wait_for_selector("#apply-done")
    status = daemon.get("/loops/TIC-101")
    assert status["pending_gains"] is False
    assert close(status["current_gains"]["pk"], gains["pk"]) and close(status["current_gains"]["pti"], gains["pti"])
    page.wait_for_selector("#apply:disabled")
    page.wait_for_selector("#result #applied:has-text('applied')")
    assert "by AUTOTUNER_TOKEN" in page.text_content("#result #applied")
    page.wait_for_function("(k) => { const e = document.querySelector('#current-gains [data-current=pk]');"
                           " return e && Math.abs(Number(e.textContent.replace('−', '-')) - k) <= 1e-3 * Math.abs(k); }",
                           arg=gains["pk"])

    # History: the session with who, outcome, point and gains; then in full with its trace.
    sid = status["session"]
    page.click("#tab-history")
    row = page.locator(f"#history tr[data-session='{sid}']")
    row.wait_for()
    text = row.text_content()
    assert "AUTOTUNER_TOKEN" in text and "success" in text and "rad/s" in text and "applied by AUTOTUNER_TOKEN" in text
    assert f"K {gains['pk']:.3g}" in text  # the designed gains
    row.click()
    page.wait_for_selector("#trace path[data-series=PV]")
    assert int(page.get_attribute("#trace path[data-series=PV]", "data-points")) > 50
    # A demo experiment (a few hundred samples) is kept whole, and the title says so.
    assert page.locator("section.card:has(#trace) h2").inner_text() == "Trace (every sample)"
    assert "AUTOTUNER_TOKEN" in page.inner_text("main")
    page.wait_for_selector("#result #nyquist [data-role=point]")


def test_every_value_shows_the_loops_engineering_units(page, daemon):
    """The demo's units (TIC-101 °C and %, 2 decimals; FIC-301 m³/h with a PV display range 0–100) on the overview,
    the loop page's readouts, form, trend axes and gains, and the session page."""
    login(page, daemon, VIEWER, "viewer")
    cell = "tr[data-loop=TIC-101] [data-col={}]"
    page.wait_for_function("(s) => /^\\d+\\.\\d\\d °C$/.test(document.querySelector(s).textContent)", arg=cell.format("pv"))
    assert page.inner_text(cell.format("sp")).endswith(" °C")
    assert page.inner_text(cell.format("mv")).endswith(" %")
    assert page.inner_text("tr[data-loop=FIC-301] [data-col=pv]").endswith(" m³/h")
    assert "%/°C" in page.inner_text(cell.format("gains"))  # K is MV units per PV unit
    page.click("tr[data-loop=TIC-101] a.loop-id")
    page.wait_for_selector("#trend[data-samples]")
    assert page.inner_text("[data-readout=pv]").endswith(" °C") and page.inner_text("[data-readout=mv]").endswith(" %")
    assert page.inner_text("[data-unit=amp]") == "%" and page.inner_text("[data-unit=hysteresis]") == "°C"
    assert "K (%/°C)" in page.inner_text("#current-gains")
    labels = page.eval_on_selector_all("#trend .axis-label", "els => els.map(e => e.textContent)")
    assert "PV, SP (°C)" in labels and "MV (%)" in labels
    # A finished session of the loop: its gains table and the session page in the loop's units.
    daemon.wait_idle("TIC-101")
    if daemon.get("/loops/TIC-101")["session"] is None:
        assert daemon.post("/loops/TIC-101/tune", {"apply": False}).status_code == 202
    sid = daemon.wait_idle("TIC-101")["session"]
    page.goto(daemon.url + f"#/session/{sid}")
    page.wait_for_selector("#trace path[data-series=PV]")
    page.wait_for_selector("#result #gains")
    assert page.inner_text("#gains tr[data-gain=pk] td.unit") == "%/°C"
    assert "SP " in page.inner_text("main") and " °C · MV " in page.inner_text("main")
    labels = page.eval_on_selector_all("#trace .axis-label", "els => els.map(e => e.textContent)")
    assert "PV (°C)" in labels and "MV (%)" in labels
    page.goto(daemon.url + "#/loop/TIC-101/history")
    row = page.locator(f"#history tr[data-session='{sid}']")
    row.wait_for()
    assert "°C/%" in row.text_content() and "%/°C" in row.text_content()  # |F| PV/MV; the gains' K MV/PV
    # FIC-301's PV axis covers its display range 0–100 although the PV stays near 50.
    page.goto(daemon.url + "#/loop/FIC-301")
    page.wait_for_selector("#trend[data-samples]")
    ticks = page.eval_on_selector_all("#trend [data-panel='PV, SP (m³/h)'] .tick",
                                      "els => els.map(e => Number(e.textContent.replace('−', '-')))")
    assert min(ticks) <= 0 and max(ticks) >= 100, ticks


def test_the_overview_updates_from_one_event_stream_without_polling(page, daemon):
    """The overview opens one stream (GET /events) and nothing else: a tuning started elsewhere shows as TUNING with
    its PV moving, then its end, with no request to /loops at all."""
    daemon.wait_idle("FIC-301")
    daemon.wait_idle("LIC-201")
    requests: list[str] = []
    page.on("request", lambda r: requests.append(r.url))
    login(page, daemon, VIEWER, "viewer")
    pv = "tr[data-loop=LIC-201] [data-col=pv]"
    page.wait_for_function("(s) => /\\d/.test(document.querySelector(s).textContent)", arg=pv)
    opened = len(requests)
    sid = daemon.post("/loops/LIC-201/tune").json()["session"]
    try:
        page.wait_for_selector("tr[data-loop=LIC-201] .badge.tuning")
        page.wait_for_selector("tr[data-loop=LIC-201] .progress")
        # The PV the row shows moves with the experiment: several different values (polled in the page).
        page.wait_for_function("(s) => { const seen = window.pvSeen = window.pvSeen || new Set();"
                               " seen.add(document.querySelector(s).textContent); return seen.size >= 5; }", arg=pv)
    finally:
        daemon.post("/loops/LIC-201/break")
    page.wait_for_selector("tr[data-loop=LIC-201] .badge.failed")
    assert "code 1" in page.inner_text("tr[data-loop=LIC-201] [data-col=status]")
    assert daemon.wait_idle("LIC-201")["session"] == sid
    api = [url.split("/api/v1", 1)[1] for url in requests if "/api/v1/" in url]
    assert [u for u in api if u.startswith("/loops")] == [], api  # no polling of GET /loops (or of a loop)
    assert api.count("/events") == 1, api  # one stream, never reconnected
    assert all("/api/v1/" not in url or url.endswith("/events") for url in requests[opened:]), requests[opened:]


def test_viewer_sees_everything_and_can_press_nothing(page, daemon):
    login(page, daemon, VIEWER, "viewer")
    assert page.locator("#loops tbody tr").count() == len(demo_config(SPEED).loops)
    page.click("tr[data-loop=LIC-201] a.loop-id")
    page.wait_for_selector("#trend[data-samples]")  # live values stream to a viewer too
    for button in ("#tune", "#tbrk", "#apply"):
        assert page.is_disabled(button), button
    assert page.is_disabled("#f-amp")
    assert "you can watch, not act" in page.inner_text("#role-note")
    # Even a button forced on gets the daemon's refusal, in words.
    page.eval_on_selector("#tune", "b => { b.disabled = false; }")
    page.click("#tune")
    assert "Not allowed (403)" in page.inner_text("#action-msg .alert")
    assert "viewer" in page.inner_text("#action-msg .alert")
    assert daemon.get("/loops/LIC-201")["tbsy"] is False


def test_tbrk_from_the_page_restores_the_loop(page, daemon):
    daemon.wait_idle("FIC-301")
    daemon.wait_idle("LIC-201")
    login(page, daemon, OPERATOR, "operator")
    page.goto(daemon.url + "#/loop/FIC-301")
    page.click("#tune:enabled")
    page.wait_for_selector("#status [data-flag=tbsy]:has-text('TBSY 1')")
    page.wait_for_selector("[data-readout=mode]:has-text('MAN')")  # the experiment drives the MV
    page.click("#tbrk:enabled")
    page.wait_for_selector("#badge:has-text('FAILED')")
    assert "code 1" in page.inner_text("#stage") and "aborted" in page.inner_text("#stage")
    assert page.inner_text("#status [data-flag=te]") == "TE 1"
    # A failed session shows what it identified (nothing here) and why; no success colour, no progress bar.
    page.wait_for_selector("#result.failed #why")
    assert "code 1" in page.inner_text("#result #why")
    assert page.locator("#result [data-identified]").count() == 1
    assert page.locator("#status .progress, #status .badge.ok, #result .badge.ok").count() == 0
    assert "FAILURE" in page.inner_text("#result .summary").upper()
    status = daemon.get("/loops/FIC-301")
    assert status["tbsy"] is False and status["te"] is True and status["ite"] == 1
    saved = daemon.get("/loops/FIC-301/history?limit=1")[0]["saved"]
    assert status["mode"] == saved["mode"] == "AUTO"
    page.wait_for_selector("[data-readout=mode]:has-text('AUTO')")
    assert page.is_enabled("#tune") and page.is_disabled("#tbrk")


def test_a_command_under_way_keeps_its_button_disabled_across_redraws(page, daemon):
    """TUNE and TBRK pressed, their requests held: a state event meanwhile (the stream cut and reconnected starts
    with the loop's state) redraws the card and the pressed button stays disabled — the page never offers the
    command twice (it re-enabled TUNE, and the daemon answered the second 409 busy). Released, it is done once."""
    daemon.wait_idle("LIC-201")
    daemon.wait_idle("FIC-301")
    login(page, daemon, OPERATOR, "operator")
    page.goto(daemon.url + "#/loop/FIC-301")
    page.wait_for_selector("#tune:enabled")
    page.evaluate(WATCH_ACTIONS)
    before = daemon.get("/loops/FIC-301/history?limit=200")
    with held(page, "/loops/FIC-301/tune") as tuning:
        page.click("#tune")
        arrived(page, tuning)
        assert page.is_disabled("#tune")
        redrawn_by_a_state_event(page, daemon)
        assert page.is_disabled("#tune"), page.get_attribute("#tune", "title")
        # Neither Enter in a field nor "Tune now" (both submit the form) sends it again.
        page.evaluate("document.querySelector('#tune-form').requestSubmit()")
        page.wait_for_timeout(300)  # lets Playwright deliver a second request to the route, were there one
        assert len(tuning) == 1
    page.wait_for_selector("#status [data-flag=tbsy]:has-text('TBSY 1')")
    assert "tune" not in page.evaluate("[...window.offered]")  # not once between the press and TBSY
    after = daemon.get("/loops/FIC-301/history?limit=200")
    assert len(after) == len(before) + 1 and page.locator("[role=alert]").count() == 0
    with held(page, "/loops/FIC-301/break") as breaking:
        page.click("#tbrk:enabled")
        arrived(page, breaking)
        page.evaluate("window.offered.clear()")
        assert page.is_disabled("#tbrk")
        redrawn_by_a_state_event(page, daemon)
        assert page.is_disabled("#tbrk"), page.get_attribute("#tbrk", "title")
        assert "tbrk" not in page.evaluate("[...window.offered]")
    page.wait_for_selector("#status [data-flag=tbsy]:has-text('TBSY 0')")
    page.wait_for_selector("#tune:enabled")
    assert page.is_disabled("#tbrk") and page.locator("[role=alert]").count() == 0
    assert daemon.get(f"/sessions/{after[0]['id']}")["code"] == 1  # aborted: the one TBRK


def test_api_errors_in_words_and_a_lost_stream_reconnects(page, daemon):
    daemon.wait_idle("FIC-301")
    daemon.wait_idle("LIC-201")
    login(page, daemon, OPERATOR, "operator")
    page.goto(daemon.url + "#/loop/LIC-201")
    page.wait_for_selector("#tune:enabled")
    # 422: the field is named and marked.
    page.fill("#f-amp", "-1")
    page.click("#tune")
    message = page.inner_text("#action-msg .alert")
    assert message.startswith("Invalid input (422): amp:")
    assert page.locator(".field.invalid[data-field=amp]").count() == 1
    assert daemon.get("/loops/LIC-201")["tbsy"] is False
    page.fill("#f-amp", "")
    # 409: another loop of the exclusion group tunes.
    assert daemon.post("/loops/FIC-301/tune").status_code == 202
    try:
        page.click("#tune")
        message = page.inner_text("#action-msg .alert")
        assert "Refused (409)" in message and "exclusion group" in message and "FIC-301" in message
    finally:
        daemon.post("/loops/FIC-301/break")
    daemon.wait_idle("FIC-301")
    # The network goes away: the page says so and reconnects by itself when it is back.
    page.wait_for_selector("#trend[data-samples]")
    daemon.proxy.down()
    try:
        banner = page.locator("[data-banner=stream]")
        banner.wait_for()
        assert "Live stream lost — reconnecting" in banner.inner_text()
    finally:
        daemon.proxy.up()
    banner.wait_for(state="detached")
    samples = float(page.get_attribute("#trend", "data-samples"))
    wait_attr_above(page, "#trend", "data-samples", samples)  # samples flow again


def no_horizontal_scroll(page) -> None:
    width, client, wide = page.evaluate(
        "() => { const W = document.documentElement.clientWidth; const wide = [];"
        " for (const e of document.querySelectorAll('body *')) { const r = e.getBoundingClientRect();"
        "  if (r.right > W + 0.5 && r.width > 0) wide.push(`${e.tagName}#${e.id}.${e.className.baseVal ?? e.className}"
        " ${Math.round(r.right)}: ${(e.textContent || '').slice(0, 60)}`); }"
        " return [document.documentElement.scrollWidth, W, wide.slice(0, 5)]; }")
    assert width <= client, f"the page is {width} px wide in a {client} px viewport: {wide}"


def usable(page, selector: str, min_width: float) -> None:
    """``selector`` is on screen (inside the viewport's width), at least ``min_width`` × 28 CSS px, not covered."""
    box = page.locator(selector).bounding_box()
    assert box is not None, selector
    viewport = page.viewport_size["width"]
    assert box["x"] >= 0 and box["x"] + box["width"] <= viewport + 0.5, (selector, box)
    assert box["width"] >= min_width and box["height"] >= 28, (selector, box)
    page.locator(selector).scroll_into_view_if_needed()
    hit = page.evaluate("(s) => { const e = document.querySelector(s); const r = e.getBoundingClientRect();"
                        " const top = document.elementFromPoint(r.x + r.width / 2, r.y + r.height / 2);"
                        " return e === top || e.contains(top); }", selector)
    assert hit, f"{selector} is covered by another element"


def legible(page, selector: str) -> None:
    """The plot's tick labels are drawn at 10 CSS px or more (the SVG is not shrunk below its drawing size)."""
    size = page.evaluate("(s) => { const svg = document.querySelector(s); const t = svg.querySelector('.tick');"
                         " const scale = svg.getBoundingClientRect().width / (svg.currentCSSZoom || 1)"
                         " / svg.viewBox.baseVal.width;"
                         " return parseFloat(getComputedStyle(t).fontSize) * scale; }", selector)
    assert size >= 10, f"{selector}: tick labels {size:.1f} px"


def test_an_open_history_shows_a_session_that_ends_meanwhile(browser, daemon):
    """The history view refreshes while open: a session started and ended after it rendered shows up, finished."""
    daemon.wait_idle("TIC-101")
    context = browser.new_context()
    page = context.new_page()
    page.set_default_timeout(TIMEOUT_MS)
    try:
        login(page, daemon, OPERATOR, "operator")
        page.goto(daemon.url + "#/loop/TIC-101/history")
        page.wait_for_selector(".card-head h2")
        response = daemon.post("/loops/TIC-101/tune", {"apply": False})
        assert response.status_code == 202, response.text
        sid = response.json()["session"]
        daemon.wait_idle("TIC-101")
        page.wait_for_selector(f"#history tr[data-session='{sid}'] .badge:not(.tuning)")
    finally:
        context.close()


@pytest.mark.parametrize("width,height", [(390, 844), (820, 1180), (1920, 1080)])
def test_every_screen_size_tune_result_apply(browser, daemon, width, height, tmp_path):
    context = browser.new_context(viewport={"width": width, "height": height})
    context.add_init_script(POINTER_LOG)
    page = context.new_page()
    page.set_default_timeout(TIMEOUT_MS)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    try:
        with evidence_on_failure(page, daemon, "TIC-101", tmp_path):
            daemon.wait_idle("TIC-101")
            login(page, daemon, OPERATOR, "operator")
            no_horizontal_scroll(page)
            usable(page, "tr[data-loop=TIC-101] a.loop-id", 40)
            page.click("tr[data-loop=TIC-101] a.loop-id")
            page.wait_for_selector("#tune:enabled")
            page.wait_for_selector("#trend[data-samples]")
            no_horizontal_scroll(page)
            for field in ("#f-controller", "#f-amp", "#f-hysteresis", "#f-phase", "#f-ms", "#f-apply"):
                usable(page, field, 90)  # wide enough to read "0.001" or "auto (3σ of noise)"
            for button in ("#tune", "#tbrk", "#apply", "#tab-history"):
                usable(page, button, 44)
            legible(page, "#trend")
            page.select_option("#f-apply", "false")
            page.click("#tune")
            page.wait_for_selector("#badge:has-text('TUNING')")
            no_horizontal_scroll(page)
            page.wait_for_selector("#badge:not(:has-text('TUNING'))")
            assert page.inner_text("#badge") == "OK", daemon.get("/loops/TIC-101")["message"]
            page.wait_for_selector("#nyquist [data-role=point]")
            page.wait_for_selector("#step-load path[data-series='PV new']")
            no_horizontal_scroll(page)
            for plot in ("#trend", "#nyquist", "#step-setpoint", "#step-load"):
                legible(page, plot)
            usable(page, "#apply:enabled", 44)
            page.click("#apply")
            usable(page, "#apply-confirm", 44)
            assert page.locator("#apply-changes tr[data-param=pk]").count() == 1
            no_horizontal_scroll(page)
            page.click("#apply-confirm")
            page.wait_for_selector("#result #applied:has-text('applied')")
            page.click("#tab-history")
            page.wait_for_selector("#history tbody tr")
            no_horizontal_scroll(page)
    finally:
        context.close()
    assert not errors, errors


def test_a_page_opened_mid_experiment_shows_the_whole_trend_from_the_start(page, daemon):
    daemon.wait_idle("FIC-301")
    daemon.wait_idle("LIC-201")
    login(page, daemon, VIEWER, "viewer")
    posted = time.monotonic()
    sid = daemon.post("/loops/FIC-301/tune").json()["session"]
    try:
        deadline = posted + 90
        # Well into the relay experiment (at least 2 wall seconds of it) before the page is opened.
        while (status := daemon.get("/loops/FIC-301"))["tbsy"] and (
                status["stage"] != "relay" or status["progress"] < 0.2 or time.monotonic() < posted + 2):
            assert time.monotonic() < deadline, "FIC-301 made no progress"
            time.sleep(0.1)
        assert status["tbsy"], status["message"]
        opened = time.time()
        page.goto(daemon.url + "#/loop/FIC-301")
        page.wait_for_selector("#trend[data-experiment-start]:not([data-experiment-start=''])")
        page.wait_for_selector("#trend path[data-series='relay ±1']")
        started = datetime.fromisoformat(daemon.get(f"/sessions/{sid}")["started_at"]).timestamp()
        first = float(page.get_attribute("#trend", "data-experiment-start"))
        # The experiment's first sample comes right after the loop's state is saved: within a few seconds of the
        # session's start (the two are stamped by separate clock reads, microseconds apart in either order),
        # long before the page was opened.
        assert abs(first - started) < 5 and first < opened - 0.5, (started, first, opened)
        assert int(page.get_attribute("#trend", "data-samples")) > 20
    finally:
        daemon.post("/loops/FIC-301/break")
    daemon.wait_idle("FIC-301")


def block_the_network(page) -> list[str]:
    """Every request of ``page`` to a host other than localhost is aborted; the list of them fills as they come."""
    blocked: list[str] = []

    def route(r):
        host = r.request.url.split("/")[2].split(":")[0]
        if host in ("127.0.0.1", "localhost"):
            r.continue_()
        else:
            blocked.append(r.request.url)
            r.abort()

    page.route("**/*", route)
    return blocked


def test_api_docs_render_with_every_non_localhost_request_blocked(page, daemon):
    """Swagger UI comes from the daemon itself: with the network beyond localhost cut, the docs page still renders
    every endpoint, with no Content-Security-Policy violation (the page fixture fails on one)."""
    blocked = block_the_network(page)
    page.goto(daemon.url + "api/v1/docs")
    page.wait_for_selector(".swagger-ui .opblock-summary-path")
    paths = page.eval_on_selector_all(".opblock-summary-path", "els => els.map(e => e.textContent)")
    assert "/api/v1/loops/{loop_id}/tune" in " ".join(paths) and "/api/v1/loops/{loop_id}/events" in " ".join(paths)
    assert not blocked, blocked
    spec = httpx.get(daemon.api + "/openapi.json").json()
    assert list(spec["paths"]["/api/v1/loops/{loop_id}/events"]["get"]["responses"]["200"]["content"]) == [
        "text/event-stream"]
    assert "400" not in spec["paths"]["/api/v1/loops"]["get"]["responses"]
    props = [(name, key, prop) for name, schema in spec["components"]["schemas"].items()
             if name not in ("HTTPValidationError", "ValidationError") for key, prop in schema.get("properties", {}).items()]
    assert props and [(n, k) for n, k, p in props if not p.get("description")] == []


def test_redoc_renders_with_every_non_localhost_request_blocked(page, daemon):
    """ReDoc too comes from the daemon (fastapi-offline's bundle): with the network beyond localhost cut, it renders
    every operation with its fields, asks for nothing outside (not even its CDN logo), and violates no
    Content-Security-Policy (the page fixture fails on one)."""
    spec = httpx.get(daemon.api + "/openapi.json").json()
    blocked = block_the_network(page)
    page.goto(daemon.url + "api/v1/redoc")
    page.wait_for_selector("#redoc [data-section-id='tag/loops']")
    operations = {op["operationId"] for methods in spec["paths"].values() for op in methods.values()}
    shown = set(page.eval_on_selector_all("#redoc [data-section-id^='operation/']",
                                          "els => els.map(e => e.getAttribute('data-section-id').slice(10))"))
    assert operations == shown, operations ^ shown
    # A schema's field descriptions (with units) are rendered, not only the operations' names.
    page.click("#redoc [data-section-id='tag/loops/operation/loop_status_api_v1_loops__loop_id__get']")
    page.wait_for_selector("#redoc :text('process value now, PV units')")
    assert page.title() == "autotuner · API reference"
    assert not blocked, blocked
    assert page.evaluate("() => [...document.images].filter(i => !i.src.startsWith(location.origin)"
                         " && !i.src.startsWith('data:')).map(i => i.src)") == []
