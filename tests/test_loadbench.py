"""Smoke test of ``autotuner loadbench`` (the benchmark itself is not a test: docs/daemon.md, "Load benchmark")."""

from __future__ import annotations

from typer.testing import CliRunner

from autotuner.cli import app


def _table(output: str) -> tuple[list[str], list[str]]:
    lines = output.strip().splitlines()
    return lines[-3].strip("| ").split(" | "), lines[-1].strip("| ").split(" | ")


def test_loadbench_two_loops_one_idle_and_two_clients_over_modbus():
    # 20 ms of wall time per sample: converges on a busy CI machine too.
    result = CliRunner().invoke(app, ["loadbench", "--loops", "2", "--idle", "1", "--clients", "2", "--speed", "5",
                                      "--markdown"])
    assert result.exit_code == 0, result.output
    header, row = _table(result.output)
    fields = dict(zip(header, row))
    assert (fields["loops"], fields["idle"], fields["clients"], fields["tuned"]) == ("2", "1", "2", "2/2")
    assert int(fields["samples"]) > 100
    assert 0.0 < float(fields["p50 ms"]) <= float(fields["p99 ms"]) <= float(fields["max ms"]) < 1000.0
    analysis = [float(x) for x in fields["analysis p50/p99/max ms"].split(" / ")]
    assert 0.0 <= analysis[0] <= analysis[1] <= analysis[2]
    assert float(fields["RSS MB"]) > 50.0  # the daemon's and its sampler's peak memory
    assert int(fields["events read"]) > 10  # the read stream got the tuning's samples


def test_loadbench_two_loops_published_over_opcua_to_a_subscribed_client():
    from api.opcua.address_space import VARIABLES

    result = CliRunner().invoke(app, ["loadbench", "--loops", "2", "--speed", "5", "--opcua", "--monitor-period",
                                      "0.2", "--markdown"])
    assert result.exit_code == 0, result.output
    header, row = _table(result.output)
    fields = dict(zip(header, row))
    assert fields["tuned"] == "2/2"
    # Beyond the first value of each subscribed variable: the tunings' changes reached the client.
    assert int(fields["OPC UA changes"]) > 2 * len(VARIABLES), row
    assert 0.0 < float(fields["CPU OPC UA %"]) < 100.0  # the server process's CPU, % of a core
