"""The command line contract of docs/design.md: options, the JSON object, exit codes."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from autotuner import __version__
from autotuner.cli import app

runner = CliRunner()

PLANT = "exp(-s)/(2*s+1)"
# A plant with 135° of lag that the relay cannot excite: the hysteresis is far
# larger than any PV change amp = 1 can cause, so it fails fast with "no oscillation".
FAILING = ["--plant", "1/(s+1)", "--hysteresis", "100"]


def true_response(omega: float) -> complex:
    """F(jω) of PLANT computed directly, independent of the parser and the model code."""
    s = 1j * omega
    return complex(np.exp(-s) / (2.0 * s + 1.0))


def _strict_json(text: str) -> dict:
    def reject(name: str) -> None:
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=reject)


def _last_json(stdout: str) -> dict:
    return _strict_json(stdout.strip().splitlines()[-1])


def _invoke(*args: str):
    return runner.invoke(app, list(args))


def check_contract(doc: dict, controller: str = "PI") -> None:
    """Keys and types of the design.md JSON for a successful tuning of PLANT."""
    assert set(doc) == {"tbsy", "te", "ite", "message", "controller", "point", "static_gain", "gains", "design",
                        "forms", "experiment"}
    # The gains in parallel and series form, from the standard form (a PI's series form is itself).
    g = doc["gains"]
    assert doc["forms"]["parallel"] == {"kp": g["pk"], "ki": pytest.approx(g["pk"] / g["pti"]),
                                        "kd": pytest.approx(g["pk"] * g["ptd"])}
    if controller == "PI":
        assert doc["forms"]["series"] == {"k": g["pk"], "ti": g["pti"], "td": 0.0}
    else:  # designs keep Td <= Ti/4: the series form exists
        assert set(doc["forms"]["series"]) == {"k", "ti", "td"}
    assert set(doc["design"]) == {"model", "ms_model", "ms_target", "noise_gain", "notes"}
    assert doc["design"]["notes"] == [] and isinstance(doc["design"]["model"], str)
    assert doc["design"]["ms_model"] == pytest.approx(doc["design"]["ms_target"], abs=0.01)
    assert doc["tbsy"] is False and doc["te"] is False
    assert doc["ite"] == 0 and isinstance(doc["ite"], int)
    assert doc["message"] == "ok"
    assert doc["controller"] == controller
    assert set(doc["point"]) == {"omega", "gain", "phase_deg"}
    assert all(isinstance(v, float) for v in doc["point"].values())
    assert isinstance(doc["static_gain"], float)
    assert set(doc["gains"]) == {"pk", "pti", "ptd", "pnd", "pb", "pc"}
    assert all(isinstance(v, float) for v in doc["gains"].values())
    assert set(doc["experiment"]) == {"duration", "periods", "samples", "phase_target_deg", "phase_moved",
                                      "disturbance", "load_estimate"}
    assert doc["experiment"]["phase_target_deg"] == 135.0 and doc["experiment"]["phase_moved"] is False
    assert doc["experiment"]["disturbance"] is False and doc["experiment"]["load_estimate"] == 0.0
    assert isinstance(doc["experiment"]["duration"], float) and doc["experiment"]["duration"] > 0
    assert isinstance(doc["experiment"]["periods"], (int, float)) and doc["experiment"]["periods"] > 0
    assert isinstance(doc["experiment"]["samples"], int) and doc["experiment"]["samples"] > 0

    point = doc["point"]
    assert point["phase_deg"] == pytest.approx(-135.0, abs=2.0)
    assert point["gain"] == pytest.approx(abs(true_response(point["omega"])), rel=0.01)
    assert math.degrees(np.angle(true_response(point["omega"]))) == pytest.approx(point["phase_deg"], abs=2.0)
    assert doc["static_gain"] == pytest.approx(1.0, rel=0.02)


@pytest.mark.parametrize("controller", ["PI", "PID"])
def test_tune_json_contract(controller: str) -> None:
    result = _invoke("tune", "--plant", PLANT, "--controller", controller, "--json")
    assert result.exit_code == 0, result.output
    doc = _last_json(result.stdout)
    check_contract(doc, controller)
    if controller == "PI":
        assert doc["gains"]["ptd"] == 0.0
    else:
        assert doc["gains"]["ptd"] > 0.0


def test_tune_json_with_noise_is_seeded() -> None:
    args = ("tune", "--plant", PLANT, "--noise", "0.005", "--seed", "3", "--json")
    first, second = _invoke(*args), _invoke(*args)
    assert first.exit_code == 0, first.output
    assert _last_json(first.stdout) == _last_json(second.stdout)
    assert _last_json(first.stdout)["point"]["phase_deg"] == pytest.approx(-135.0, abs=2.0)


def test_tune_human_output_on_demo_plant() -> None:
    result = _invoke("tune")
    assert result.exit_code == 0, result.output
    out = result.stdout
    for label in ("point", "static gain", "experiment", "standard (ISA)", "series", "parallel", "model", "Ms on model",
                  "Ms on the plant"):
        assert label in out
    assert "rad/s" in out and "periods" in out and "samples" in out
    assert "{" not in out  # not JSON


def test_tune_failure_exits_1_with_json() -> None:
    result = _invoke("tune", *FAILING, "--json")
    assert result.exit_code == 1
    doc = _last_json(result.stdout)
    assert doc["te"] is True and doc["tbsy"] is False
    assert isinstance(doc["ite"], int) and doc["ite"] != 0
    assert "oscillation" in doc["message"]
    assert doc["gains"] is None and doc["point"] is None


def test_tune_failure_exits_1_human() -> None:
    result = _invoke("tune", *FAILING)
    assert result.exit_code == 1
    assert "failed" in result.stdout and "oscillation" in result.stdout


@pytest.mark.parametrize(
    ("plant", "token", "position"),
    [("1/(s+1", "(", 2), ("2s+1", "s", 1), ("exp(s)/(s+1)", None, None), ("foo", "foo", 0)],
)
def test_bad_plant_exits_2_and_names_the_token(plant: str, token: str | None, position: int | None) -> None:
    result = _invoke("tune", "--plant", plant, "--json")
    assert result.exit_code == 2
    assert result.stdout == ""
    assert "Traceback" not in result.output
    assert plant in result.stderr
    if token is not None:
        assert f"'{token}'" in result.stderr and f"position {position}" in result.stderr


@pytest.mark.parametrize(
    ("option", "value", "words"),
    [
        ("--amp", "-1", "amp"),
        ("--amp", "0", "amp"),
        ("--phase", "200", "phase"),
        ("--phase", "45", "phase"),
        ("--ts", "0", "sample time"),
        ("--ts", "-0.1", "sample time"),
        ("--hysteresis", "-1", "hysteresis"),
        ("--noise", "-1", "noise"),
        ("--ms", "0.9", "--ms"),
        ("--ms", "9", "--ms"),
        ("--controller", "PD", "--controller"),
        ("--amp", "x", "--amp"),
    ],
)
def test_bad_option_exits_2(option: str, value: str, words: str) -> None:
    result = _invoke("tune", option, value, "--json")
    assert result.exit_code == 2, result.output
    assert result.stdout == ""
    assert words in result.stderr
    assert "Traceback" not in result.output


def test_controller_is_case_insensitive() -> None:
    result = _invoke("tune", "--plant", PLANT, "--controller", "pid", "--json")
    assert result.exit_code == 0
    assert _last_json(result.stdout)["controller"] == "PID"


def test_version() -> None:
    for args in (["--version"], ["version"]):
        result = runner.invoke(app, args)
        assert result.exit_code == 0
        assert result.stdout.strip() == __version__


def test_bench_small_batch(tmp_path: Path) -> None:
    batch = tmp_path / "batch.csv"
    batch.write_text("id,family,params,expr\nP1-X,P1,T=1,exp(-s)/(s+1)\n")
    output = tmp_path / "bench.md"
    result = _invoke("bench", "--batch", str(batch), "--workers", "1", "--output", str(output))
    assert result.exit_code == 0, result.output
    table = output.read_text()
    assert table.startswith("| id |") and "P1-X" in table and "**median**" in table
    assert "| noise-free | 1 |" in table and "analyse() CPU ms" in table  # the experiment's CPU per call
    assert table.strip() in result.stdout
    assert "wall time" in result.stderr


def test_bench_bad_batch_exits_2(tmp_path: Path) -> None:
    batch = tmp_path / "batch.csv"
    batch.write_text("id,family,params,expr\nP1-X,P1,T=1,exp(-s)/(s+1\n")
    result = _invoke("bench", "--batch", str(batch), "--workers", "1")
    assert result.exit_code == 2
    assert "position" in result.stderr
    result = _invoke("bench", "--batch", str(tmp_path / "missing.csv"))
    assert result.exit_code == 2


def _console_script() -> Path:
    script = Path(sys.executable).parent / ("autotuner.exe" if sys.platform == "win32" else "autotuner")
    if not script.exists():
        pytest.skip(f"console script not installed next to {sys.executable}")
    return script


def test_installed_console_script_json() -> None:
    proc = subprocess.run(
        [str(_console_script()), "tune", "--plant", PLANT, "--json"],
        capture_output=True, text=True, timeout=120, check=False,
    )
    assert proc.returncode == 0, proc.stderr
    check_contract(_last_json(proc.stdout))


def test_installed_console_script_exit_codes() -> None:
    script = str(_console_script())
    failed = subprocess.run([script, "tune", *FAILING, "--json"], capture_output=True, text=True, timeout=120)
    assert failed.returncode == 1
    assert _last_json(failed.stdout)["te"] is True
    bad = subprocess.run([script, "tune", "--plant", "2s+1"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2
    assert "position 1" in bad.stderr and "Traceback" not in bad.stderr


def test_an_unstable_plant_tunes_without_numpy_warnings_on_stderr() -> None:
    # The load fit's unstable candidates overflow on purpose; their warnings used to reach the user.
    proc = subprocess.run([str(_console_script()), "tune", "--plant", "exp(-0.2*s)/(2*s-1)", "--json"],
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0 and _last_json(proc.stdout)["ite"] == 0, proc.stderr
    assert proc.stderr == ""


def test_tune_via_modbus_tunes_through_the_real_protocol_stack() -> None:
    result = _invoke("tune", "--plant", PLANT, "--via", "modbus", "--json")
    assert result.exit_code == 0, result.output
    doc = _last_json(result.stdout)
    assert doc["te"] is False and doc["ite"] == 0 and set(doc["gains"]) == {"pk", "pti", "ptd", "pnd", "pb", "pc"}
    point = doc["point"]
    true = true_response(point["omega"])
    # Sampled through a server whose clock is not the session's: a few percent.
    assert point["gain"] == pytest.approx(abs(true), rel=0.05)
    assert point["phase_deg"] == pytest.approx(math.degrees(np.angle(true)), abs=3.0)


def test_tune_via_can_with_a_load_step_made_by_the_plc() -> None:
    # --load with --via: the simulated PLC steps its load 7 s (1.3 periods) after the session takes the loop over
    # (at 2× real time: see test_hil's load test; a quiet run ends at 2.2 periods, the model rule's).
    result = _invoke("tune", "--plant", PLANT, "--via", "can", "--speed", "2", "--load", "7:-0.3", "--json")
    assert result.exit_code == 0, result.output
    doc = _last_json(result.stdout)
    assert doc["ite"] == 0 and doc["experiment"]["disturbance"] is True
    assert doc["experiment"]["load_estimate"] == pytest.approx(-0.3, abs=0.05)
    assert doc["static_gain"] == pytest.approx(1.0, rel=0.05)


def test_unreachable_link_fails_with_code_7_not_a_traceback() -> None:
    result = _invoke("tune", "--link", "modbus://127.0.0.1:1/1", "--ts", "0.1", "--json")
    assert result.exit_code == 1
    doc = _last_json(result.stdout)
    assert doc["te"] is True and doc["ite"] == 7
    assert "cannot connect" in doc["message"]


@pytest.mark.parametrize(
    "args, words",
    [
        (["--link", "foo://x", "--ts", "0.1"], "unknown link"),
        (["--link", "modbus://127.0.0.1:1/1"], "--ts"),
        (["--link", "modbus://host:notaport/1", "--ts", "0.1"], "Modbus URL"),
    ],
)
def test_bad_link_options_exit_2(args: list[str], words: str) -> None:
    result = _invoke("tune", *args)
    assert result.exit_code == 2
    assert words in result.output
    assert "Traceback" not in result.output


# -- field conditions (issue 13) ------------------------------------------------


def test_field_options_build_the_simulated_plant() -> None:
    from autotuner.cli.app import parse_loads
    from autotuner.cli.tune import _prepare

    steps = parse_loads(["20:0.2", "35.5:-0.1"], "the start of the experiment")
    assert steps == [(20.0, 0.2), (35.5, -0.1)]
    sim, _ = _prepare(PLANT, 0.05, 1.0, None, 135.0, 0.0, 0, 100.0, steps, 0.01, 0.002)
    assert sim.quantum == 0.002
    inputs = []
    for _ in range(1000):  # MV held at 0: the PV shows the loads and the ramp alone
        inputs.append(sim.true_pv())
        sim.advance(0.0)
    # At 50 s: steps 0.2 − 0.1 plus the ramp 0.01·50 have passed the lag and the dead time.
    assert inputs[-1] == pytest.approx(0.2 - 0.1 + 0.01 * (50.0 - 1.0 - 2.0), abs=0.03)
    assert sim.measure() == pytest.approx(round(sim.true_pv() / 0.002) * 0.002, abs=1e-12)


def test_the_table_names_a_detected_load() -> None:
    quiet = _invoke("tune", "--plant", PLANT)
    # (At 7 s, 1.3 periods in: the quiet run ends at 11.4 s, the model rule's, before a step at 15 s.)
    loaded = _invoke("tune", "--plant", PLANT, "--load", "7:0.2")
    assert quiet.exit_code == 0 and loaded.exit_code == 0, loaded.output
    assert "disturbance" not in quiet.stdout
    found = re.search(r"disturbance\s*│ a load change of ([+-][0-9.]+) MV units", loaded.stdout)
    assert found is not None, loaded.stdout
    assert float(found.group(1)) == pytest.approx(0.2, abs=0.03)


def test_load_step_option_reaches_the_experiment() -> None:
    clean = _last_json(_invoke("tune", "--plant", PLANT, "--json").stdout)
    loaded = _invoke("tune", "--plant", PLANT, "--load", "15:0.2", "--quantum", "0.001", "--json")
    assert loaded.exit_code in (0, 1), loaded.output
    doc = _last_json(loaded.stdout)
    assert doc != clean and set(doc) == set(clean)


@pytest.mark.parametrize("value", ["abc", "10", "10:", ":0.2", "-1:0.2", "1:nan", "inf:1"])
def test_bad_load_exits_2(value: str) -> None:
    result = _invoke("tune", "--plant", PLANT, "--load", value, "--json")
    assert result.exit_code == 2 and result.stdout == ""
    assert "--load" in result.stderr and "T:SIZE" in result.stderr


@pytest.mark.parametrize(("args", "words"), [
    (["--quantum", "-0.1"], "--quantum"),
    (["--drift", "x"], "--drift"),
    (["--link", "modbus://127.0.0.1:1/1", "--ts", "0.1", "--load", "1:1"], "simulated --plant only"),
    (["--via", "modbus", "--drift", "0.1"], "in-process --plant only"),
])
def test_bad_field_options_exit_2(args: list[str], words: str) -> None:
    result = _invoke("tune", *args, "--json")
    assert result.exit_code == 2, result.output
    assert words in result.stderr


@pytest.mark.parametrize(("plant", "words"), [("0", "is zero"), ("0*exp(-s)/(s+1)", "is zero"),
                                              ("2", "no dynamics"), ("-3.5", "no dynamics")])
def test_nonsense_plants_exit_2(plant: str, words: str) -> None:
    result = _invoke("tune", "--plant", plant, "--json")
    assert result.exit_code == 2 and result.stdout == ""
    assert words in result.stderr and "Traceback" not in result.output


def test_integrators_without_a_time_scale_get_a_sample_time_from_their_gain() -> None:
    from autotuner.engine.plant.expression import parse_process
    from autotuner.engine.simulated_tuning import default_sample_time

    # |F(jω)| = 1 at ω = 1 rad/s for 1/s and at 2 rad/s for 4/s²: 100 samples per period there.
    assert default_sample_time(parse_process("1/s")) == pytest.approx(2 * math.pi / 100)
    assert default_sample_time(parse_process("4/s^2")) == pytest.approx(2 * math.pi / 2 / 100)


def test_warning_result_exits_0_with_te_false_and_the_notes_in_the_message() -> None:
    result = _invoke("tune", "--controller", "PID", "--noise", "0.01", "--json")
    assert result.exit_code == 0, result.output
    doc = _last_json(result.stdout)
    assert doc["te"] is False and doc["ite"] == 15 and doc["gains"]["ptd"] > 0.0
    assert doc["design"]["notes"] and doc["design"]["notes"][0] in doc["message"]
    human = _invoke("tune", "--controller", "PID", "--noise", "0.01")
    assert human.exit_code == 0 and "warning" in human.stdout and "design note" in human.stdout


def test_bench_field_runs_every_scenario_on_a_batch(tmp_path: Path) -> None:
    from autotuner.benchmarks.design_bench import default_batch
    from autotuner.benchmarks.field_bench import SCENARIOS

    lines = default_batch().read_text().splitlines()
    batch = tmp_path / "one.csv"
    batch.write_text("\n".join([lines[0], lines[1]]) + "\n")  # P1-001, exp(-s)/(0.02*s+1)
    out = tmp_path / "field.md"
    result = _invoke("bench", "--field", "--batch", str(batch), "--workers", "1", "--output", str(out))
    assert result.exit_code == 0, result.output
    for scenario in SCENARIOS:
        assert f"| {scenario.name} | 1 |" in result.stdout
        assert f"### {scenario.name}" in out.read_text()
    assert "field scenarios:" in result.stdout and "of 14 runs tuned with Ms ≤ 1.6" in result.stdout
    assert "ZN PI:" in result.stdout and "AH PID:" in result.stdout
    assert "| clean (reference) | 1 |" in result.stdout and "| field scenarios | 14 |" in result.stdout
    clean = next(line for line in result.stdout.splitlines() if line.startswith("| clean"))
    assert "| 1 | 1 | 1 (100.0 %) |" in clean  # the undisturbed run tunes and keeps Ms ≤ 1.6


def test_a_warning_is_named_once_in_the_table() -> None:
    result = _invoke("tune", "--plant", "exp(-0.8*s)/(2*s-1)", "--controller", "pid")
    assert result.exit_code == 0, result.output
    text = " ".join(result.stdout.split())
    assert "warning (ite = 19): the design misses its Ms target" in text and "warning: the design" not in text
