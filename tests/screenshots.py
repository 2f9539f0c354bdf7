"""Screenshots of the operator page for the docs: ``python -m tests.screenshots [OUTDIR]`` (default: docs/).

Starts the real built-in demo (``autotuner serve``, 20× real time) with a known operator token, drives the page in
headless Chromium (Playwright): tunes TIC-101 from its loop page and saves ``loop-page.png`` when it has finished;
saves the same page at every viewport of :data:`VIEWPORTS` (``screens/loop-WxH.png``, a phone of 360 px to a
4K wall screen); then aborts a tuning of FIC-301 (TBRK), starts one of LIC-201 and saves ``overview.png`` (and
``screens/overview-WxH.png``) while it runs; then, once the daemon has assessed the demo plant's loops (a health
window of 1200 plant seconds here, instead of the hour of the default), the overview sorted by health
(``health-overview.png``) and the sticky valve's health card (``health-card.png``, and ``screens/health-card-390x844.png``).
About 2 min. Needs Chromium (Debian: ``apt-get install chromium``; elsewhere set AUTOTUNER_CHROMIUM).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import yaml
from playwright.sync_api import sync_playwright

from autotuner.service.demo import demo_config
from tests.helpers import CHROMIUM_ARGS, chromium_path, free_port

TOKEN = "screenshot-operator"
# The screens of docs/operator-page.md: phones, a tablet, a desktop, a 4K wall screen (CSS pixels).
VIEWPORTS = ((360, 640), (390, 844), (820, 1180), (1920, 1080), (3840, 2160))


def at_viewport(page, width: int, height: int) -> None:
    """Resize the page and wait until its trend (if shown) has been drawn again at its new width."""
    page.set_viewport_size({"width": width, "height": height})
    page.wait_for_function("() => { const t = document.querySelector('#trend');"
                           " return !t || !t.dataset.width"
                           " || Number(t.dataset.width) === Math.round(t.getBoundingClientRect().width / (t.currentCSSZoom || 1)); }")


def demo_with_short_health_window(path: Path) -> Path:
    """The built-in demo's config (20×) with a health window of 1200 plant s, assessed every 100 plant s."""
    config = demo_config(20.0).model_dump(mode="json", exclude_defaults=True)
    for loop in config["loops"]:
        loop["health"] = {"window": 1200.0, "every": 100.0}
    path.write_text(yaml.safe_dump(config))
    return path


def health_shots(page, base: str, api: httpx.Client, outdir: Path) -> None:
    """The overview sorted by health and the sticky valve's (TIC-102's) health card, once it is assessed."""
    deadline = time.monotonic() + 300
    while not ((h := api.get("/loops/TIC-102/health").json())["state"] == "ok"
               and "stiction" in h["assessment"]["flags"]):
        if time.monotonic() > deadline:
            raise SystemExit(f"TIC-102 not assessed with stiction: {h}")
        time.sleep(1)
    page.set_viewport_size({"width": 1360, "height": 700})
    page.goto(f"{base}/#/")
    page.wait_for_selector("tr[data-loop=TIC-102] [data-hflag=stiction]")
    page.click("#sort-health")
    # (while the window fills, the sticky valve's verdict can change from one assessment to the next: each shot
    # waits for the stiction to show)
    page.wait_for_selector("tr[data-loop=TIC-102] [data-hflag=stiction]")
    page.screenshot(path=outdir / "health-overview.png", full_page=True)
    page.goto(f"{base}/#/loop/TIC-102")
    page.wait_for_selector("#health-mvpv path[data-series='PV(MV)']")
    page.locator("#health").screenshot(path=outdir / "health-card.png")
    at_viewport(page, 390, 844)
    page.wait_for_selector("#health-mvpv path[data-series='PV(MV)']")
    page.locator("#health").screenshot(path=outdir / "screens" / "health-card-390x844.png")


def main(outdir: Path) -> None:
    port = free_port()
    config = demo_with_short_health_window(Path(tempfile.mkdtemp(prefix="screenshots-")) / "demo.yaml")
    proc = subprocess.Popen([sys.executable, "-m", "autotuner.cli", "serve", "--config", str(config),
                             "--port", str(port)],
                            env={**os.environ, "AUTOTUNER_TOKEN": TOKEN}, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    base = f"http://127.0.0.1:{port}"
    api = httpx.Client(base_url=f"{base}/api/v1", headers={"Authorization": f"Bearer {TOKEN}"}, timeout=30)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if api.get("/health").status_code == 200:
                    break
            except httpx.TransportError:
                time.sleep(0.1)
            if time.monotonic() > deadline or proc.poll() is not None:
                raise SystemExit("autotuner serve did not start")
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium_path(), args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1360, "height": 860})
            page.set_default_timeout(120_000)
            page.on("pageerror", lambda exc: print(f"page error: {exc}", file=sys.stderr))
            page.goto(base)
            page.fill("#token", TOKEN)
            page.click("#login button[type=submit]")
            page.wait_for_selector("#loops tbody tr")
            time.sleep(3)  # a few monitor samples before the experiment
            page.goto(f"{base}/#/loop/TIC-101")
            page.select_option("#f-apply", "false")
            page.click("#tune:enabled")
            page.wait_for_selector("#badge:has-text('OK')")
            page.wait_for_selector("#step-load path[data-series='PV new']")
            time.sleep(4)  # the loop settling back after the experiment
            page.screenshot(path=outdir / "loop-page.png", full_page=True)
            (outdir / "screens").mkdir(exist_ok=True)
            for width, height in VIEWPORTS:
                at_viewport(page, width, height)
                page.screenshot(path=outdir / "screens" / f"loop-{width}x{height}.png", full_page=width < 1000)

            api.post("/loops/FIC-301/tune").raise_for_status()
            time.sleep(2)
            api.post("/loops/FIC-301/break").raise_for_status()
            while api.get("/loops/FIC-301").json()["tbsy"]:
                time.sleep(0.2)
            api.post("/loops/LIC-201/tune", json={"controller": "PID"}).raise_for_status()
            page.set_viewport_size({"width": 1360, "height": 400})
            page.goto(f"{base}/#/")
            page.wait_for_function("() => { const r = document.querySelector('tr[data-loop=LIC-201] .progress');"
                                   " return r && Number(r.getAttribute('aria-valuenow')) >= 30; }")
            page.screenshot(path=outdir / "overview.png", full_page=False)
            for width, height in VIEWPORTS:
                at_viewport(page, width, height)
                page.screenshot(path=outdir / "screens" / f"overview-{width}x{height}.png", full_page=False)
            health_shots(page, base, api, outdir)
            browser.close()
    finally:
        api.close()
        proc.terminate()
        proc.wait(60)
    print(f"wrote {outdir / 'overview.png'}, {outdir / 'loop-page.png'}, {outdir / 'health-overview.png'}, "
          f"{outdir / 'health-card.png'} and {outdir / 'screens'}/")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent.parent / "docs")
