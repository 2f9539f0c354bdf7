"""The built-in demo of ``autotuner serve``: three simulated loops of different process classes.

Each is a simulated PLC (the process under a PID unit, steady in AUTO at
PV = MV = 50) run ``speed`` times faster than real time inside the daemon,
so one tuning takes a few seconds of wall time (about 120–180 plant seconds
at speed 20). The history is kept in memory.
"""

from __future__ import annotations

from autotuner.service.config import DaemonConfig
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.simulated_tuning import EXPERIMENT_SAMPLES_PER_PERIOD, default_sample_time

# (id, description, plant, units) — a lag with dead time, an integrating level, a lag-dominant loop; the MV is a
# valve position in % everywhere.
DEMO_LOOPS = (
    ("TIC-101", "temperature: two lags with dead time", "1.5*exp(-0.7*s)/(4*s+1)^2",
     {"pv": "°C", "mv": "%", "decimals": 2}),
    ("LIC-201", "level: integrating with dead time", "0.2*exp(-1*s)/(s*(2*s+1))",
     {"pv": "%", "mv": "%", "decimals": 1}),
    ("FIC-301", "lag-dominant flow/pressure loop", "2*exp(-0.5*s)/((20*s+1)*(2*s+1))",
     {"pv": "m³/h", "mv": "%", "decimals": 2}),
)
# Wall seconds between two monitor readings: at 20× a few plant seconds, so the trend after an experiment is
# not a staircase (the default 1 s would be 20 plant seconds).
MONITOR_PERIOD = 0.25
# The demo's experiments sample this many times per oscillation period (at the 135° point): half the
# default, so the demo's real-time loops cost less.
DEMO_SAMPLES_PER_PERIOD = 50


def demo_config(speed: float = 20.0) -> DaemonConfig:
    """The demo's loops, each at ``speed`` plant seconds per wall second."""
    loops = [
        {"id": loop_id, "description": description, "sim": {"plant": plant},
         "ts": default_sample_time(parse_process(plant)) * EXPERIMENT_SAMPLES_PER_PERIOD / DEMO_SAMPLES_PER_PERIOD,
         "speed": speed,
         "monitor_period": MONITOR_PERIOD,
         "tuning": {"amp": 5.0, "time_limit": 1000.0}, "limits": {"pv": [0.0, 100.0], "mv": [0.0, 100.0]},
         "units": units}
        for loop_id, description, plant, units in DEMO_LOOPS
    ]
    return DaemonConfig.model_validate({"history": ":memory:", "loops": loops})
