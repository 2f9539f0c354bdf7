"""The plant file: many simulated loops from one YAML file, each with its process, gains, noise and faults;
bad files are refused with the file, the loop and the key named. The demo plant shows what it says it does."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from autotuner.engine.health.assessment import assess
from autotuner.engine.health.scales import LoopLimits
from autotuner.engine.plant.faults import Faults
from drivers.link import Mode
from drivers.plant_file import PlantFileError, demo_plant_path, load_plant, plant_from_dict
from drivers.sim_record import record_plc
from drivers.simplc import safe_gains

PLANT = """
loops:
  - id: A-1
    plant: "exp(-1*s)/(5*s+1)"
    ts: 0.5
    noise: 0.1
    seed: 3
    gains: {k: 2.0, ti: 4.0}
    detune: {k: 1.5}
    faults:
      stiction: {s: 3, j: 1}
      deadband: 0.5
      load: {std: 1.0, tau: 20}
      sine: {amplitude: 2, period: 60}
      steps: {size: 5, every: 300}
      frozen_pv: 600
  - id: B-2
    description: plain
    plant: "0.2/s"
    mode: MAN
"""


def test_a_plant_file_builds_one_plc_per_loop(tmp_path: Path) -> None:
    path = tmp_path / "plant.yaml"
    path.write_text(PLANT)
    a, b = load_plant(path)
    assert (a.id, b.id, b.description) == ("A-1", "B-2", "plain")
    assert a.plc.ts == 0.5 and a.plc.noise_std == 0.1 and a.plc.seed == 3
    assert (a.plc.gains.k, a.plc.gains.ti) == (3.0, 4.0)
    assert a.plc.faults == Faults(stiction_s=3.0, stiction_j=1.0, deadband=0.5, load_std=1.0, load_tau=20.0,
                                  sine_amplitude=2.0, sine_period=60.0, step_size=5.0, step_interval=300.0,
                                  frozen_at=600.0)
    assert a.plc.mode is Mode.AUTO and b.plc.mode is Mode.MAN
    assert b.plc.faults == Faults() and b.plc.gains == safe_gains(b.plc.process)


@pytest.mark.parametrize("data, message", [
    ({"loops": []}, "'loops' must be a non-empty list"),
    ({"loops": [{"plant": "1/(s+1)"}]}, r"loops\[0\]: missing key 'id'"),
    ({"loops": [{"id": "A", "plant": "1/(s+"}]}, r"loops\[0\]\.plant: "),
    ({"loops": [{"id": "A", "plant": "1/(s+1)", "faults": {"stiction": {"s": 3}}}]},
     r"loops\[0\]\.faults\.stiction: missing key 'j'"),
    ({"loops": [{"id": "A", "plant": "1/(s+1)", "faults": {"load": {"std": 1, "tau": 0}}}]},
     r"loops\[0\]\.faults\.load\.tau: must be > 0"),
    ({"loops": [{"id": "A", "plant": "1/(s+1)", "faults": {"stiction": {"s": "x", "j": 1}}}]},
     r"loops\[0\]\.faults\.stiction\.s: must be a finite number"),
    ({"loops": [{"id": "A", "plant": "1/(s+1)", "faults": {"valve": 1}}]}, r"unknown key 'valve'"),
    ({"loops": [{"id": "A", "plant": "1/(s+1)", "mode": "CAS"}]}, r"loops\[0\]\.mode: must be AUTO or MAN"),
    ({"loops": [{"id": "A", "plant": "1/(s+1)"}, {"id": "A", "plant": "1/(s+1)"}]}, r"loops\[1\]\.id: 'A' given twice"),
])
def test_bad_plant_files_are_refused_naming_where(data: object, message: str) -> None:
    with pytest.raises(PlantFileError, match=message):
        plant_from_dict(data, "plant.yaml")


def test_an_unreadable_or_invalid_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(PlantFileError, match="cannot read the plant file"):
        load_plant(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("loops: [")
    with pytest.raises(PlantFileError, match="bad.yaml: not valid YAML"):
        load_plant(bad)


# What each demo loop is meant to show (docs/health.md, "The demo plant"): its flags and recommendation.
DEMO = {
    "TIC-101": (set(), "none"),
    "LIC-201": (set(), "none"),
    "FIC-301": (set(), "none"),
    "TIC-102": ({"oscillating", "stiction"}, "check_valve"),
    "FIC-302": ({"oscillating"}, "retune"),
    "TIC-103": ({"sluggish"}, "retune"),
    "LIC-202": ({"manual"}, "put_in_auto"),
}


def test_the_demo_plant_shows_what_it_says() -> None:
    loops = load_plant(demo_plant_path())
    assert [loop.id for loop in loops] == list(DEMO)
    for loop in loops:
        record = record_plc(loop.plc, int(math.ceil(3600.0 / loop.plc.ts)))  # an hour of plant time
        result = assess(record, LoopLimits(pv=(0.0, 100.0)), loop.plc.process, ts=1.0)  # at the daemon's 1 s
        flags, recommendation = DEMO[loop.id]
        assert flags <= {f.name for f in result.flags}, (loop.id, result.to_json())
        assert result.recommendation == recommendation, (loop.id, result.to_json())
        if not flags:
            assert not result.flags, (loop.id, result.to_json())


def test_a_daemon_configs_sim_loop_takes_a_plant_files_keys() -> None:
    """A config's ``sim:`` is a plant file's loop without its id and description, checked by the same reader."""
    from autotuner.service.config import parse_config
    from autotuner.service.daemon import simulated_plc

    sim = {"plant": "1.5*exp(-0.7*s)/(4*s+1)^2", "noise": 0.05, "seed": 4, "mode": "MAN",
           "gains": {"k": 0.4, "ti": 6.9}, "detune": {"k": 2.0}, "faults": {"stiction": {"s": 3, "j": 1}}}
    config = parse_config({"loops": [{"id": "TIC-102", "ts": 0.3, "sim": sim},
                                     {"id": "TIC-103", "ts": 0.3, "sim": {**sim, "ts": 0.25}}]}, "daemon.yaml")
    plc, ticked = simulated_plc(config.loops[0]), simulated_plc(config.loops[1])
    file_plc = plant_from_dict({"loops": [{"id": "TIC-102", **sim}]}).pop().plc
    assert plc.faults == file_plc.faults == Faults(stiction_s=3.0, stiction_j=1.0)
    assert plc.gains == file_plc.gains and (plc.gains.k, plc.gains.ti) == (0.8, 6.9)
    assert plc.mode is Mode.MAN and plc.noise_std == 0.05 and plc.seed == 4
    assert math.isclose(plc.ts, 0.3 / 5) and ticked.ts == 0.25  # the loop's ts over 5 ticks, unless given


@pytest.mark.parametrize("sim, message", [
    ({"plant": "1/(s+1)", "faults": {"stiction": {"s": "x", "j": 1}}},
     r"daemon.yaml: loops\[0\]\.sim: faults\.stiction\.s: must be a finite number, got 'x'"),
    ({"plant": "1/(s+1)", "faults": {"load": {"std": 1}}}, r"loops\[0\]\.sim: faults\.load: missing key 'tau'"),
    ({"plant": "1/(s+1)", "mode": "CAS"}, r"loops\[0\]\.sim: mode: must be AUTO or MAN"),
    ({"plant": "1/(s+1)", "detune": {"k": 0}}, r"loops\[0\]\.sim: detune\.k: must be > 0"),
    ({"plant": "1/(s+1)", "noise": -1}, r"loops\[0\]\.sim: noise: must be ≥ 0"),
    ({"plant": "1/(s+1)", "valve": 1}, r"loops\[0\]\.sim\.valve: Extra inputs are not permitted"),
])
def test_a_bad_sim_loop_in_a_daemon_config_is_refused_naming_the_key(sim: dict[str, object], message: str) -> None:
    from autotuner.service.config import ConfigError, parse_config

    with pytest.raises(ConfigError, match=message):
        parse_config({"loops": [{"id": "A", "ts": 0.3, "sim": sim}]}, "daemon.yaml")
