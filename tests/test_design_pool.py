"""The design's worker processes: same result as in-process, CPU accounted, and never outliving the daemon."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

import pickle

from autotuner.service import design_pool as session
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.experiment.relay import RelayConfig
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.simulated_tuning import DesignJob, result_of, run_experiment

PLANT = "exp(-s)/(s+1)"


def test_the_worker_designs_what_the_process_itself_would():
    experiment, trace = run_experiment(PlantSim(parse_process(PLANT), 0.05), RelayConfig(amp=1.0))
    cpu = session.design_cpu()
    job = DesignJob.of(experiment, "PID", 1.4)
    code, _, pooled = asyncio.run(session.designed(job))
    direct = result_of(experiment, trace, "PID", 1.4)
    assert code == direct.code and pooled.gains == direct.design.gains
    assert session.design_cpu() > cpu  # the worker's CPU is counted
    session.close_design_pool()


def test_a_design_job_carries_the_identification_not_the_experiment():
    # What a worker is sent: the identification and the settings (under 1 KB), not the record of every sample.
    experiment, trace = run_experiment(PlantSim(parse_process(PLANT), 0.05), RelayConfig(amp=1.0))
    sent = len(pickle.dumps(DesignJob.of(experiment, "PID", 1.4)))
    assert sent < 1024 < len(pickle.dumps(trace)), sent


@pytest.mark.parametrize("ending", ["SIGKILL", "SIGTERM"])
def test_workers_exit_when_the_daemon_is_killed(ending, tmp_path):
    # A daemon that designs once, reports its workers and dies by a signal (no atexit, no pool shutdown).
    script = textwrap.dedent(f"""
        import asyncio, os, signal
        from autotuner.service import design_pool as session
        from autotuner.engine.plant.expression import parse_process
        from autotuner.engine.experiment.relay import RelayConfig
        from autotuner.engine.plant.simulation import PlantSim
        from autotuner.engine.simulated_tuning import DesignJob, run_experiment

        experiment, trace = run_experiment(PlantSim(parse_process({PLANT!r}), 0.05), RelayConfig(amp=1.0))
        assert asyncio.run(session.designed(DesignJob.of(experiment, "PI", 1.4)))[2] is not None
        print(" ".join(str(pid) for pid in session.worker_pids()), flush=True)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        os.kill(os.getpid(), signal.{ending})
    """)
    # Output to a file: a pipe would stay open as long as an orphaned worker holds it.
    out = tmp_path / "out"
    with out.open("w") as stdout:
        subprocess.run([sys.executable, "-c", script], stdout=stdout, stderr=subprocess.STDOUT, timeout=120)
    workers = [int(pid) for pid in out.read_text().split() if pid.isdigit()]
    assert workers, out.read_text()
    deadline = time.monotonic() + 10 * session.PARENT_CHECK + 5.0
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = [pid for pid in workers if _alive(pid)]
    for pid in alive:  # don't leave them behind when the test fails
        os.kill(pid, signal.SIGKILL)
    assert not alive


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().split(") ")[1][0] != "Z"  # a zombie has ended
    except FileNotFoundError:
        return False
