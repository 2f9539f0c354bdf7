"""The daemon's records and config as a plant engineer meets them: timestamped log lines (text or JSON), damaged
or empty history files refused at start (exit 2, no traceback), duplicate YAML keys and non-UTF-8 configs refused,
the history URL's password never printed. Real ``autotuner serve`` processes."""

from __future__ import annotations

import json
import re
import sqlite3
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from autotuner.service.config import ConfigError, load_config
from helpers import Daemon

LOOP = {"id": "A", "sim": {"plant": "exp(-s)/(2*s+1)"}, "ts": 0.2, "monitor_period": 0.2}


def config_file(tmp_path: Path, history: str) -> Path:
    path = tmp_path / "daemon.yaml"
    path.write_text(yaml.safe_dump({"history": history, "loops": [LOOP]}))
    return path


def serve(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "autotuner.cli", "serve", *args], capture_output=True, text=True,
                          timeout=120)


def test_log_lines_have_utc_timestamps_as_text_and_as_json(tmp_path: Path):
    with Daemon(config_file(tmp_path, "h.db"), args=("--log-level", "debug")) as daemon:
        daemon.wait_until(lambda: "Application startup complete" in daemon.log(), 30, "uvicorn's startup line")
    line = next(x for x in daemon.log().splitlines() if "Application startup complete" in x)
    assert re.match(r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z INFO uvicorn\.error: Application startup", line), line
    with Daemon(config_file(tmp_path, "h.db"), args=("--log-format", "json")) as daemon:
        daemon.wait_until(lambda: "Application startup complete" in daemon.log(), 30, "uvicorn's startup line")
    records = [json.loads(x) for x in daemon.log().splitlines() if x.startswith("{")]
    assert {"time", "level", "logger", "message"} <= records[0].keys()
    assert any(r["message"] == "Application startup complete." and r["level"] == "INFO" for r in records)


def test_a_zero_byte_history_is_refused_unless_init_history_is_given(tmp_path: Path):
    db = tmp_path / "h.db"
    db.write_bytes(b"")
    refused = serve("--config", str(config_file(tmp_path, str(db))))
    assert refused.returncode == 2 and "empty file (0 bytes)" in refused.stderr and "--init-history" in refused.stderr
    assert db.stat().st_size == 0 and "Traceback" not in refused.stderr
    with Daemon(config_file(tmp_path, str(db)), args=("--init-history",)):
        pass
    assert sqlite3.connect(db).execute("SELECT count(*) FROM sessions").fetchone() == (0,)


def test_a_history_file_with_a_zeroed_page_is_refused_with_a_clear_message(tmp_path: Path):
    db = tmp_path / "h.db"
    with sqlite3.connect(db) as conn:
        conn.execute("CREATE TABLE filler (x TEXT)")
        conn.executemany("INSERT INTO filler VALUES (?)", [("x" * 500,) for _ in range(200)])
    # The header page: not a database at all; a page of the table: its integrity check (or the schema read) fails.
    for offset, what in ((0, ("file is not a database",)), (4096 * 3, ("is damaged", "disk image is malformed"))):
        data = bytearray(db.read_bytes())
        data[offset:offset + 4096] = bytes(4096)
        damaged = tmp_path / f"damaged-{offset}.db"
        damaged.write_bytes(data)
        result = serve("--config", str(config_file(tmp_path, str(damaged))))
        assert result.returncode == 2, result.stderr
        assert any(w in result.stderr for w in what) and "restore it from a backup" in result.stderr
        assert "Traceback" not in result.stderr and len(result.stderr.splitlines()) <= 3


def test_a_history_urls_password_is_never_printed(tmp_path: Path):
    for url in ("postgresql+psycopg://bob:s3cr3t-pw@127.0.0.1:1/db", "postgresql+psycopg://bob:s3cr3t-pw@[bad/db"):
        result = serve("--config", str(config_file(tmp_path, url)))
        assert result.returncode == 2
        assert "s3cr3t-pw" not in result.stderr + result.stdout and "Traceback" not in result.stderr


def test_a_key_given_twice_is_refused_naming_the_key_and_its_lines(tmp_path: Path):
    path = tmp_path / "daemon.yaml"
    path.write_text("loops:\n  - id: A\n    sim: {plant: '1/(s+1)'}\n    ts: 0.1\n    ts: 0.2\n")
    with pytest.raises(ConfigError, match=r"daemon.yaml:5: key 'ts' given twice in one mapping \(first on line 4\)"):
        load_config(path)
    result = serve("--config", str(path))
    assert result.returncode == 2 and "key 'ts' given twice" in result.stderr


def test_a_config_that_is_not_utf8_is_refused_cleanly(tmp_path: Path):
    path = tmp_path / "daemon.yaml"
    path.write_bytes("loops:\n  - id: Régulateur\n".encode("latin-1"))
    result = serve("--config", str(path))
    assert result.returncode == 2 and "not UTF-8 text (byte 0xe9" in result.stderr
    assert "Traceback" not in result.stderr
