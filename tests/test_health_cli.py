"""``autotuner health FILE.csv``: historian exports written here, good and bad; the table, the JSON object as
the last line, exit 2 with the line and column named for a bad file, never a traceback."""

from __future__ import annotations

import json
import subprocess
import sys
from datetime import datetime, timedelta, timezone
from pathlib import Path

import pytest
from typer.testing import CliRunner

from autotuner.cli import app
from autotuner.engine.health.scales import ultimate_period
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.faults import Faults
from drivers.link import Mode
from drivers.sim_record import record_plc
from drivers.simplc import SimulatedPlc

runner = CliRunner()
PLANT = "1.5*exp(-0.7*s)/(4*s+1)^2"


def _write(path: Path, faults: Faults, stamps: bool = False, man: bool = False) -> Path:
    """An hour-long export of a simulated loop: t (seconds, or ISO-8601 stamps), sp, pv, mv, mode and a
    column the command ignores."""
    process = parse_process(PLANT)
    plc = SimulatedPlc(process, ts=ultimate_period(process) / 20, noise_std=0.05, seed=1, faults=faults)
    if man:
        plc.mode = Mode.MAN
    rec = record_plc(plc, 3600)
    start = datetime(2026, 3, 1, 8, 0, tzinfo=timezone.utc)
    lines = ["Tag,t,sp,pv,mv,mode"]
    for k in range(len(rec)):
        t = (start + timedelta(seconds=float(rec.t[k]))).isoformat() if stamps else f"{rec.t[k]:.6f}"
        lines.append(f"TIC-102,{t},{rec.sp[k]:.6g},{rec.pv[k]:.6g},{rec.mv[k]:.6g},"
                     f"{'AUTO' if rec.auto[k] else 'MAN'}")
    path.write_text("\n".join(lines) + "\n")
    return path


STICKY = Faults(stiction_s=4.5, stiction_j=1.5, load_std=0.2, load_tau=20.0)


def _json(stdout: str) -> dict:
    return json.loads(stdout.strip().splitlines()[-1])


def test_a_sticky_valve_from_a_csv_export(tmp_path: Path) -> None:
    path = _write(tmp_path / "tic102.csv", STICKY)
    result = runner.invoke(app, ["health", str(path), "--json", "--model", PLANT, "--pv-range", "0:100"])
    assert result.exit_code == 0, result.output
    out = _json(result.stdout)
    assert {"oscillating", "stiction"} <= set(out["flags"]) and out["recommendation"] == "check_valve"
    assert set(out["reasons"]) == set(out["flags"])
    assert all(v is None or isinstance(v, (int, float)) for v in out["indices"].values())
    assert out["dead_time_source"] == "model" and out["indices"]["dead_time"] == 0.7
    table = runner.invoke(app, ["health", str(path), "--model", PLANT, "--pv-range", "0:100"])
    assert table.exit_code == 0 and "recommendation: check_valve" in table.stdout and "stiction" in table.stdout


def test_timestamps_read_as_seconds(tmp_path: Path) -> None:
    seconds = _json(runner.invoke(app, ["health", str(_write(tmp_path / "a.csv", STICKY)), "--json"]).stdout)
    stamped = _json(runner.invoke(app, ["health", str(_write(tmp_path / "b.csv", STICKY, stamps=True)),
                                        "--json"]).stdout)
    assert stamped["flags"] == seconds["flags"]
    assert stamped["indices"]["oscillation_period"] == pytest.approx(seconds["indices"]["oscillation_period"],
                                                                     rel=1e-3)


def test_a_loop_in_manual(tmp_path: Path) -> None:
    out = _json(runner.invoke(app, ["health", str(_write(tmp_path / "m.csv", Faults(), man=True)), "--json"]).stdout)
    assert out["flags"] == ["manual"] and out["recommendation"] == "put_in_auto"


GOOD_HEADER = "t,sp,pv,mv\n"


@pytest.mark.parametrize("text, message", [
    ("", "empty: expected a header row with the columns t, sp, pv, mv"),
    ("t,sp,pv\n0,1,2\n1,1,2\n", ":1: missing column 'mv' (the header has: t, sp, pv)"),
    (GOOD_HEADER + "0,50,50,50\n1,50,50,50\n2,50,5O.1,50\n", ":4: column 'pv': '5O.1' is not a number"),
    (GOOD_HEADER + "0,50,50,50\n1,50,50,50\n1,50,50,50\n", ":4: column 't': 1 is not after the line before's 1"),
    (GOOD_HEADER + "0,50,50,50\n1,50,,50\n", ":3: column 'pv': empty"),
    (GOOD_HEADER + "0,50,50,50\n1,50,50\n", ":3: 3 fields, the header has 4"),
    (GOOD_HEADER + "0,50,50,50\nnoon,50,50,50\n", ":3: column 't': 'noon' is neither seconds nor an ISO-8601"),
    ("t,sp,pv,mv,mode\n0,50,50,50,AUTO\n1,50,50,50,CAS\n", ":3: column 'mode': 'CAS' is neither AUTO nor MAN"),
    (GOOD_HEADER + "".join(f"{k},50,50,50\n" for k in range(5)), "5 samples in the window: an assessment needs"),
])
def test_a_bad_file_is_named_with_its_line_and_column(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(text)
    result = runner.invoke(app, ["health", str(path)])
    assert result.exit_code == 2, result.output
    assert message in " ".join(result.stderr.split()), result.stderr
    assert "Traceback" not in result.stderr
    assert result.exception is None or isinstance(result.exception, SystemExit)


@pytest.mark.parametrize("args, message", [
    (["--mv-limits", "100:0"], "bad --mv-limits '100:0'"),
    (["--model", "1/(s+"], "bad --model expression"),
    (["--ts", "0"], "bad --ts 0"),
])
def test_bad_options_exit_2(tmp_path: Path, args: list[str], message: str) -> None:
    path = tmp_path / "ok.csv"
    path.write_text(GOOD_HEADER + "".join(f"{k},50,50,50\n" for k in range(30)))
    result = runner.invoke(app, ["health", str(path), *args])
    assert result.exit_code == 2 and message in result.stderr, result.stderr


def test_the_console_script_prints_the_json_object_last(tmp_path: Path) -> None:
    path = _write(tmp_path / "tic102.csv", STICKY)
    script = Path(sys.executable).with_name("autotuner")
    proc = subprocess.run([str(script), "health", str(path), "--json"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "Traceback" not in proc.stderr
    assert set(_json(proc.stdout)) >= {"flags", "recommendation", "reasons", "indices"}
    missing = subprocess.run([str(script), "health", str(tmp_path / "nope.csv")], capture_output=True, text=True,
                             timeout=120)
    assert missing.returncode == 2 and "nope.csv: cannot read" in missing.stderr
    assert "Traceback" not in missing.stderr
