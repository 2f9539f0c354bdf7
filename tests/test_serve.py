"""`autotuner serve` as a process, and the config file's error messages."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
import yaml

from autotuner.service.config import ConfigError, load_config
from drivers.modbus_map import DEFAULT_MAP
from helpers import free_port


def test_demo_serves_the_demo_plants_loops_with_a_generated_token_and_stops_on_sigterm():
    port = free_port()
    env = {k: v for k, v in os.environ.items() if k != "AUTOTUNER_TOKEN"}
    proc = subprocess.Popen([sys.executable, "-m", "autotuner.cli", "serve", "--port", str(port)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        token = proc.stdout.readline().rsplit(" ", 1)[1].strip()
        assert f"http://127.0.0.1:{port}/api/v1" in proc.stdout.readline()
        base = f"http://127.0.0.1:{port}/api/v1"
        deadline = time.monotonic() + 30
        while True:
            try:
                assert httpx.get(f"{base}/health").json()["status"] == "ok"
                break
            except httpx.TransportError:
                assert time.monotonic() < deadline and proc.poll() is None
                time.sleep(0.1)
        headers = {"Authorization": f"Bearer {token}"}
        loops = httpx.get(f"{base}/loops", headers=headers).json()
        # the demo plant's (drivers/data/demo_plant.yaml): its three healthy loops first, then the faulty ones
        assert [loop["id"] for loop in loops] == ["TIC-101", "LIC-201", "FIC-301", "TIC-102", "FIC-302", "TIC-103",
                                                  "LIC-202"]
        assert len({loop["link"] for loop in loops[:3]}) == 3
        assert [loop["mode"] for loop in loops if loop["mode"] is not None] <= ["AUTO"] * 6 + ["MAN"]
        assert httpx.post(f"{base}/loops/LIC-201/tune", headers=headers).status_code == 202
        assert httpx.post(f"{base}/loops/LIC-201/tune").status_code == 401
        proc.send_signal(signal.SIGTERM)
        # The running experiment is aborted and its loop handed back, then the server stops: exit 0 (docs/handback.md).
        assert proc.wait(30) == 0
        assert "Application shutdown complete" in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def write(tmp_path: Path, text: str) -> Path:
    """``text`` as tmp_path/daemon.yaml, next to the register map GOOD names (maps/tic.yaml, the default map)."""
    (tmp_path / "maps").mkdir(exist_ok=True)
    (tmp_path / "maps" / "tic.yaml").write_text(yaml.safe_dump(DEFAULT_MAP.as_dict()))
    path = tmp_path / "daemon.yaml"
    path.write_text(text)
    return path


GOOD = """
history: db/history.sqlite
tokens:
  - {name: hmi, role: viewer, sha256: %s}
loops:
  - id: TIC-101
    description: reactor temperature
    link: modbus://127.0.0.1:5020/1
    map: maps/tic.yaml
    ts: 0.5
    group: reactor
    apply: true
    tuning: {controller: PID, amp: 5, phase: 135, ms: 1.4}
    limits: {pv: [0, 120], mv: [0, 100]}
    units: {pv: "°C", mv: "%%", decimals: 1, pv_range: [20, 120]}
  - id: SIM-1
    sim: {plant: "exp(-s)/(2*s+1)"}
    ts: 0.1
    speed: 20
""" % ("ab" * 32)


def test_a_good_config_resolves_paths_next_to_the_file(tmp_path):
    config = load_config(write(tmp_path, GOOD))
    tic = config.loop("TIC-101")
    assert tic.map == tmp_path / "maps/tic.yaml" and tic.tuning.controller == "PID" and tic.limits.pv == (0, 120)
    assert config.history == str(tmp_path / "db/history.sqlite")
    assert config.loop("SIM-1").speed == 20 and config.loop("nope") is None
    assert tic.units.pv == "°C" and tic.units.mv == "%" and tic.units.decimals == 1
    assert tic.units.pv_range == (20, 120) and tic.units.mv_range is None
    # Without a units section (every config before it): no unit, 4 significant digits, axes fit the data.
    assert config.loop("SIM-1").units.as_json() == {"pv": "", "mv": "", "decimals": None, "pv_range": None,
                                                    "mv_range": None}


@pytest.mark.parametrize("change, where, what", [
    (("amp: 5", "amp: -5"), "loops[0].tuning.amp", "greater than 0"),
    (("pv: [0, 120]", "pv: [120, 0]"), "loops[0].limits.pv", "low < high"),
    (("    ts: 0.5\n", "    ts: 0.5\n    tss: 1\n"), "loops[0].tss", "Extra inputs"),
    (("id: SIM-1", "id: TIC-101"), "(top level)", "used twice"),
    (("role: viewer", "role: boss"), "tokens[0].role", "viewer"),
    (("exp(-s)/(2*s+1)", "exp(-s)/(2*s+"), "loops[1].sim", "plant: unexpected end"),
    (("    link: modbus", "    sim: {plant: 1/(s+1)}\n    link: modbus"), "loops[0]", "exactly one of"),
    (("link: modbus://", "link: http://"), "loops[0]", "must be modbus://"),
    # Links and maps are opened (not connected) at load: what can never work stops the daemon at start.
    (("127.0.0.1:5020/1", "127.0.0.1:99999/1"), "loops[0].link", "port is not a number in 0..65535"),
    (("127.0.0.1:5020/1", "127.0.0.1:abc/1"), "loops[0].link", "port is not a number in 0..65535"),
    (("127.0.0.1:5020/1", "127.0.0.1:5020/999"), "loops[0].link", "unit id 999 is outside 0..255"),
    (("link: modbus://127.0.0.1:5020/1\n    map: maps/tic.yaml", "link: 'can://'"), "loops[0].link",
     "can://INTERFACE/CHANNEL"),
    (("maps/tic.yaml", "maps/missing.yaml"), "loops[0].map", "missing.yaml: cannot read the map"),
    (("maps/tic.yaml", "daemon.yaml"), "loops[0].map", "unknown top-level key"),
    (("    map: maps/tic.yaml", "    dbc: my.dbc"), "loops[0].dbc", "a DBC is for a CAN link"),
    (("link: modbus://127.0.0.1:5020/1\n    map: maps/tic.yaml", "link: can://virtual/x\n    dbc: no.dbc"),
     "loops[0].dbc", "cannot load DBC"),
    (("link: modbus://127.0.0.1:5020/1\n    map: maps/tic.yaml", "link: can://virtual/x\n    speed: 1000"),
     "loops[0].speed", "is more than the DBC's WdTime can carry (6553.5 s)"),
    (("    ts: 0.1\n", ""), "loops[1].ts", "Field required"),
    (("sim: {plant: ", "sim: {faults: {stiction: {s: 3}}, plant: "), "loops[1].sim",
     "faults.stiction: missing key 'j'"),
    (("    ts: 0.1\n", "    ts: 0.1\n    health: {window: 30}\n"), "loops[1].health.window", "greater than or equal to 60"),
    (("    ts: 0.1\n", "    ts: 0.1\n    health: {window: 600, every: 900}\n"), "loops[1].health",
     "must not exceed the window"),
    (("decimals: 1", "decimals: 7"), "loops[0].units.decimals", "less than or equal to 6"),
    (("decimals: 1", "decimals: 1.5"), "loops[0].units.decimals", "valid integer"),
    (("decimals: 1", "decimals: '1'"), "loops[0].units.decimals", "valid integer"),
    (("pv_range: [20, 120]", "pv_range: [120, 20]"), "loops[0].units.pv_range", "low < high"),
    (("pv_range: [20, 120]", "mv_range: [0, .inf]"), "loops[0].units.mv_range", "finite"),
    (('pv: "°C"', 'pv: "degrees Celsius above zero"'), "loops[0].units.pv", "at most 16 characters"),
    (('mv: "%"', 'mv: "%\\n"'), "loops[0].units.mv", "should match pattern"),
    (('mv: "%"', 'mw: "%"'), "loops[0].units.mw", "Extra inputs"),
    (("history: db/history.sqlite", "history: db/history.sqlite\nrecord_wait: 0.5"), "record_wait",
     "greater than or equal to 1"),
    (("history: db/history.sqlite", "history: db/history.sqlite\nrecord_wait: 601"), "record_wait",
     "less than or equal to 600"),
])
def test_every_error_names_the_file_the_path_and_what_is_wrong(tmp_path, change, where, what):
    path = write(tmp_path, GOOD.replace(*change))
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert str(exc.value).startswith(f"{path}: {where}: ")
    assert what in str(exc.value) and "Traceback" not in str(exc.value)


def test_yaml_syntax_errors_and_missing_files(tmp_path):
    with pytest.raises(ConfigError, match=r"daemon.yaml:4:1: not valid YAML: expected ',' or ']'"):
        load_config(write(tmp_path, "loops:\n  - id: a\n  - [unclosed\n"))
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="must be a mapping"):
        load_config(write(tmp_path, "- a\n"))


def test_serve_with_a_bad_config_exits_2_with_the_message(tmp_path):
    path = write(tmp_path, GOOD.replace("amp: 5", "amp: -5"))
    proc = subprocess.run([sys.executable, "-m", "autotuner.cli", "serve", "--config", str(path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "loops[0].tuning.amp" in proc.stderr and "Traceback" not in proc.stderr

