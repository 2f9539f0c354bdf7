"""Smoke test of ``autotuner loadbench`` (the benchmark itself is not a test: docs/daemon.md, "Load benchmark")."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from autotuner.cli import app
from autotuner.benchmarks.load import lateness


def test_lateness_is_measured_against_the_deadline_schedule():
    starts = [10.0, 10.1, 10.2]
    done = [10.001, 10.103, 10.250]
    assert lateness(starts, done, 0.1) * 1e3 == pytest.approx([1.0, 3.0, 50.0])


def test_loadbench_two_loops_over_modbus():
    # 20 ms of wall time per sample: converges on a busy CI machine too.
    result = CliRunner().invoke(app, ["loadbench", "--loops", "2", "--speed", "5", "--markdown"])
    assert result.exit_code == 0, result.output
    row = result.output.strip().splitlines()[-1].strip("| ").split(" | ")
    assert row[:2] == ["2", "2/2"]
    assert int(row[3]) > 100  # samples
    assert float(row[5]) < 1000.0  # p99 lateness, ms: finite and sane


def test_loadbench_two_loops_published_over_opcua_to_a_subscribed_client():
    from api.opcua.address_space import VARIABLES

    result = CliRunner().invoke(app, ["loadbench", "--loops", "2", "--speed", "5", "--opcua", "--monitor-period",
                                      "0.2", "--markdown"])
    assert result.exit_code == 0, result.output
    lines = result.output.strip().splitlines()
    header, row = (line.strip("| ").split(" | ") for line in (lines[-3], lines[-1]))
    assert header[-2:] == ["OPC UA changes", "CPU OPC UA %"]
    assert row[:2] == ["2", "2/2"]
    # Beyond the first value of each subscribed variable: the tunings' changes reached the client.
    assert int(row[-2]) > 2 * len(VARIABLES), row
    assert 0.0 < float(row[-1]) < 100.0  # the server thread's CPU, % of a core
