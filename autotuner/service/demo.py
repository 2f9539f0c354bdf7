"""The built-in demo of ``autotuner serve``: the demo plant's loops (``drivers/data/demo_plant.yaml``).

Three healthy loops of different process classes first (TIC-101, LIC-201, FIC-301), then four that are not
(a sticky valve, an over-tuned loop, a sluggish one, one left in MAN; docs/health.md, "The demo plant"). Each
is a simulated PLC (the process under a PID unit, steady at PV = MV = SP = 50, with the plant file's noise,
gains, mode and faults) run ``speed`` times faster than real time inside the daemon, so one tuning takes a few
seconds of wall time (about 120–180 plant seconds at speed 20). The history is kept in memory.
"""

from __future__ import annotations

from typing import Any

import yaml

from drivers.plant_file import demo_plant_path

from autotuner.engine.plant.expression import parse_process
from autotuner.engine.simulated_tuning import EXPERIMENT_SAMPLES_PER_PERIOD, default_sample_time
from autotuner.service.config import DaemonConfig

# Engineering units by the loop's kind (its id's prefix); the MV is a valve position in % everywhere.
UNITS = {"TIC": {"pv": "°C", "mv": "%", "decimals": 2}, "LIC": {"pv": "%", "mv": "%", "decimals": 1},
         "FIC": {"pv": "m³/h", "mv": "%", "decimals": 2}}
# Wall seconds between two monitor readings: at 20× one plant second, the sample time the health assessment
# reads the loops at (at 2 plant seconds the over-tuned FIC-302's fast cycle looks like noise; docs/health.md).
MONITOR_PERIOD = 0.05
# The demo's experiments sample about this many times per oscillation period (at the 135° point): half the
# default, so the demo's real-time loops cost less.
DEMO_SAMPLES_PER_PERIOD = 50
# The demo's loops are assessed over the default hour of plant time (3 wall minutes at 20×: the sluggish
# TIC-103's slow recoveries need it), every minute of plant time.
DEMO_HEALTH = {"window": 3600.0, "every": 60.0}


def experiment_ts(plant: str, tick: float) -> float:
    """The demo's experiment sample time for ``plant`` ticking every ``tick`` plant seconds: the whole number of
    ticks nearest to :data:`DEMO_SAMPLES_PER_PERIOD` samples per period (a sample between two ticks would read
    the older one)."""
    wanted = default_sample_time(parse_process(plant)) * EXPERIMENT_SAMPLES_PER_PERIOD / DEMO_SAMPLES_PER_PERIOD
    return tick * max(1, round(wanted / tick))


def demo_loop(data: dict[str, Any], speed: float) -> dict[str, Any]:
    """One demo loop's config from its plant-file entry ``data``, run at ``speed``."""
    sim = {key: value for key, value in data.items() if key not in ("id", "description")}
    return {"id": data["id"], "description": data.get("description", ""), "sim": sim,
            "ts": experiment_ts(sim["plant"], sim["ts"]), "speed": speed, "monitor_period": MONITOR_PERIOD,
            "tuning": {"amp": 5.0, "time_limit": 1000.0}, "limits": {"pv": [0.0, 100.0], "mv": [0.0, 100.0]},
            "units": UNITS.get(data["id"][:3], {}), "health": DEMO_HEALTH}


def demo_config(speed: float = 20.0) -> DaemonConfig:
    """The demo plant's loops, each at ``speed`` plant seconds per wall second."""
    with open(demo_plant_path(), encoding="utf-8") as f:
        plant = yaml.safe_load(f)
    loops = [demo_loop(data, speed) for data in plant["loops"]]
    return DaemonConfig.model_validate({"history": ":memory:", "loops": loops})
