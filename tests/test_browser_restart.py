"""After a daemon restart, the loop page still draws the last experiment's trend (from the history, at the resolution
it stores) and shows its result (real Chromium against two `autotuner serve` processes on one history file)."""

from __future__ import annotations

from datetime import datetime

import httpx
import yaml

from autotuner.service.demo import demo_config
from helpers import Daemon, logged_in_page

TOKEN = "restart-operator-token"


def test_a_finished_sessions_trend_and_result_survive_a_daemon_restart(tmp_path):
    config = demo_config(12.0).model_dump(mode="json", exclude_defaults=True)
    config["loops"] = [loop for loop in config["loops"] if loop["id"] == "TIC-101"]
    config["history"] = str(tmp_path / "history.sqlite")
    path = tmp_path / "daemon.yaml"
    path.write_text(yaml.safe_dump(config, allow_unicode=True))
    with Daemon(path, TOKEN) as first:
        sid = httpx.post(f"{first.base}/loops/TIC-101/tune", headers=first.headers, timeout=30).json()["session"]
        first.wait_until(lambda: not httpx.get(f"{first.base}/loops/TIC-101", headers=first.headers,
                                               timeout=30).json()["tbsy"], 120, "the tuning to end")
    with Daemon(path, TOKEN) as second:
        record = httpx.get(f"{second.base}/sessions/{sid}", headers=second.headers, timeout=30).json()
        assert record["outcome"] == "success" and len(record["trace"]["t"]) > 100, record["message"]
        assert httpx.get(f"{second.base}/loops/TIC-101", headers=second.headers, timeout=30).json()["session"] is None
        with logged_in_page(f"http://127.0.0.1:{second.port}/", TOKEN) as page:
            page.goto(f"http://127.0.0.1:{second.port}/#/loop/TIC-101")
            # The experiment, from its first stored sample, with the relay's output; then the new monitor readings.
            page.wait_for_selector("#trend[data-experiment-start]:not([data-experiment-start=''])")
            page.wait_for_selector("#trend path[data-series='relay ±1']")
            started = datetime.fromisoformat(record["started_at"]).timestamp()
            first_sample = float(page.get_attribute("#trend", "data-experiment-start"))
            assert abs(first_sample - (started + record["trace"]["t"][0] / 12.0)) < 1e-3
            assert int(page.get_attribute("#trend", "data-samples")) >= len(record["trace"]["t"])
            # Its result, as before the restart: the session, its gains and the Nyquist plot.
            page.wait_for_selector(f"#result a[href='#/session/{sid}']")
            page.wait_for_selector("#result #nyquist [data-role=point]")
            assert page.locator("#result #gains tr[data-gain=pk]").count() == 1
