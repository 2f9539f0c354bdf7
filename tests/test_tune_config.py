"""``autotuner tune --config FILE --loop ID``: a loop of a daemon config tuned from the command line.

The loop is reached as the daemon reaches it: a ``sim:`` loop's plant runs at
its configured speed, a ``link:`` loop is a simulated PLC behind a real Modbus
TCP server on localhost. Points are checked against the plant's analytic
frequency response, written gains by reading the PLC back.
"""

from __future__ import annotations

import cmath
import json
import math

import pytest
import yaml
from typer.testing import CliRunner

from autotuner.cli import app
from autotuner.engine.plant.expression import parse_process
from autotuner.service.remote_tuning import PLANT_TICKS_PER_SAMPLE
from drivers.link import Mode
from drivers.simplc import SimulatedPlc
from test_api import modbus_plant

runner = CliRunner()
PLANT = "exp(-s)/(2*s+1)"
TS = 0.1
# Plant seconds per wall second: 10 ms of wall time per sample.
SPEED = 10.0


def true_response(omega: float) -> complex:
    """F(jω) of PLANT computed directly, independent of the parser and the model code."""
    s = 1j * omega
    return cmath.exp(-s) / (2.0 * s + 1.0)


def write_config(tmp_path, loop: dict) -> str:
    path = tmp_path / "daemon.yaml"
    base = {"id": "TIC-1", "ts": TS, "speed": SPEED, "tuning": {"amp": 5.0, "phase": 120.0, "time_limit": 500.0},
            "limits": {"pv": [-100.0, 100.0], "mv": [-100.0, 100.0]}}
    path.write_text(yaml.safe_dump({"history": str(tmp_path / "h.db"), "loops": [{**base, **loop}]}))
    return str(path)


def run_json(*args: str) -> tuple[int, dict]:
    result = runner.invoke(app, ["tune", *args, "--json"])
    return result.exit_code, json.loads(result.stdout.strip().splitlines()[-1])


def test_a_simulated_loop_is_tuned_with_its_configured_defaults_and_overrides(tmp_path):
    config = write_config(tmp_path, {"sim": {"plant": PLANT}})
    code, out = run_json("--config", config, "--loop", "TIC-1", "--controller", "PID")
    assert code == 0 and out["te"] is False, out["message"]
    assert out["controller"] == "PID"  # from the command line
    point = out["point"]
    assert point["phase_deg"] == pytest.approx(-120.0, abs=1.5)  # the loop's default phase, not 135°
    truth = true_response(point["omega"])
    assert point["gain"] == pytest.approx(abs(truth), rel=0.03)
    assert point["phase_deg"] == pytest.approx(math.degrees(cmath.phase(truth)), abs=1.5)
    # Sampled at the loop's ts (the experiment's duration spans its samples).
    experiment = out["experiment"]
    assert experiment["duration"] / experiment["samples"] == pytest.approx(TS, rel=0.1)


def test_a_modbus_loop_is_tuned_through_its_link_and_apply_writes_the_gains(tmp_path):
    plc = SimulatedPlc(parse_process(PLANT), ts=TS / PLANT_TICKS_PER_SAMPLE)
    with modbus_plant(plc, SPEED) as url:
        config = write_config(tmp_path, {"link": url})
        code, out = run_json("--config", config, "--loop", "TIC-1", "--apply")
    assert code == 0 and out["te"] is False, out["message"]
    assert plc.gains.k == pytest.approx(out["gains"]["pk"], rel=1e-3)
    assert plc.gains.ti == pytest.approx(out["gains"]["pti"], rel=1e-3)
    assert plc.mode is Mode.AUTO  # restored to the mode it was in


def test_without_apply_the_configured_loop_keeps_its_gains(tmp_path):
    plc = SimulatedPlc(parse_process(PLANT), ts=TS / PLANT_TICKS_PER_SAMPLE)
    before = plc.gains
    with modbus_plant(plc, SPEED) as url:
        config = write_config(tmp_path, {"link": url})
        code, out = run_json("--config", config, "--loop", "TIC-1")
    assert code == 0, out["message"]
    assert plc.gains == before and out["gains"]["pk"] != pytest.approx(before.k)


def test_the_configured_hand_back_arms_the_device_watchdog_as_the_daemon_does(tmp_path):
    plc = SimulatedPlc(parse_process(PLANT), ts=TS / PLANT_TICKS_PER_SAMPLE)
    armed: list[float] = []
    tick = plc.tick

    def recorded() -> None:  # the watchdog timeout the PLC holds at each of its ticks
        tick()
        armed.append(plc.watchdog.timeout)

    plc.tick = recorded
    with modbus_plant(plc, SPEED) as url:
        config = write_config(tmp_path, {"link": url})
        data = yaml.safe_load(open(config))
        data["handback"] = {"watchdog": 3.0}
        with open(config, "w") as out:
            yaml.safe_dump(data, out)
        code, out = run_json("--config", config, "--loop", "TIC-1")
    assert code == 0, out["message"]
    assert max(armed) == pytest.approx(3.0 * SPEED)  # wall seconds × speed: the device's seconds
    assert armed[-1] == 0.0 and plc.fallbacks == 0 and plc.mode is Mode.AUTO  # disarmed at the hand-back


@pytest.mark.parametrize(("args", "message"), [
    (["--loop", "NOPE"], "no loop 'NOPE' in the config (loops: TIC-1)"),
    (["--loop", "TIC-1", "--plant", "1/(s+1)"], "drop --plant"),
    (["--loop", "TIC-1", "--ts", "0.2"], "drop --ts"),
    (["--loop", "TIC-1", "--amp", "-1"], "--amp"),
    ([], "--config and --loop go together"),
])
def test_bad_combinations_exit_2_naming_the_problem(tmp_path, args, message):
    config = write_config(tmp_path, {"sim": {"plant": PLANT}})
    result = runner.invoke(app, ["tune", "--config", config, *args])
    assert result.exit_code == 2
    assert message in " ".join(result.stderr.split())


def test_a_bad_config_file_exits_2_naming_the_file(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("loops:\n  - id: A\n    ts: -1\n    sim: {plant: '1/(s+1)'}\n")
    result = runner.invoke(app, ["tune", "--config", str(path), "--loop", "A"])
    assert result.exit_code == 2
    text = " ".join(result.stderr.split())
    assert "bad.yaml" in text and "ts" in text
