"""The daemon's own health in numbers: ``GET /metrics`` in the Prometheus text format (viewer token).

Computed when scraped, from what the daemon keeps anyway (no work per
sample): the sessions' sampling lateness and the daemon's own part of it
(histograms, seconds), the analysis CPU per period (histogram, CPU seconds),
sessions ended by outcome code, link errors per loop, loops tuning now,
open event streams and OPC UA sessions, the history's queue and whether its
database is writable, and each sampler process's CPU. docs/daemon.md,
"Metrics", lists them with a scrape config.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector

from autotuner.engine.outcome import Code
from autotuner.service.daemon import LoopManager
from autotuner.service.daemon.timing import Histogram

# Histogram buckets exposed, seconds (a subset of the daemon's own, finer ones; +Inf added).
LATENESS_BUCKETS = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)
ANALYSIS_BUCKETS = (0.0001, 0.0002, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0)
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


def _histogram(name: str, doc: str, histogram: Histogram, bounds: tuple[float, ...]) -> HistogramMetricFamily:
    counts = histogram.cumulative([*bounds, float("inf")])
    return HistogramMetricFamily(name, doc, buckets=[(_le(b), c) for b, c in zip([*bounds, float("inf")], counts)],
                                 sum_value=histogram.total)


def _le(bound: float) -> str:
    return "+Inf" if bound == float("inf") else f"{bound:g}"


class DaemonCollector(Collector):
    """The metrics of ``manager`` and of the app's ``state`` (event streams, OPC UA)."""

    def __init__(self, manager: LoopManager, state: Any) -> None:
        self.manager, self.state = manager, state

    def collect(self) -> Iterator[Metric]:
        m = self.manager
        s = m.sampling
        yield _histogram("autotuner_sample_lateness_seconds", "How late each session sample's PV read completed "
                         "behind its due time (the link's round trip included)", s.late, LATENESS_BUCKETS)
        yield _histogram("autotuner_sample_own_lateness_seconds", "How late each session sample's read started by "
                         "the daemon's own fault (its CPU, its event loop; not the link)", s.own, LATENESS_BUCKETS)
        yield _histogram("autotuner_analysis_cpu_seconds", "CPU seconds of each period's analysis",
                         s.analysis, ANALYSIS_BUCKETS)
        overloaded = CounterMetricFamily("autotuner_samples_overloaded", "Session samples late enough by the "
                                         "daemon's own fault to hurt an experiment")
        overloaded.add_metric([], s.overloaded)
        yield overloaded
        sessions = CounterMetricFamily("autotuner_sessions", "Sessions ended, by outcome code (ite)",
                                       labels=["code", "name"])
        for code, count in sorted(m.outcomes.items()):
            sessions.add_metric([str(int(code)), Code(code).name], count)
        yield sessions
        errors = CounterMetricFamily("autotuner_link_errors", "Link failures of each loop's watch and sessions",
                                     labels=["loop"])
        for loop_id, loop in m.loops.items():
            errors.add_metric([loop_id], loop.link_errors)
        yield errors
        health = CounterMetricFamily("autotuner_health_assessments", "Loop health assessments made (docs/health.md)")
        health.add_metric([], m.health_assessed)
        yield health
        health_cpu = CounterMetricFamily("autotuner_health_cpu_seconds", "CPU seconds of the health assessments in "
                                         "the worker processes")
        health_cpu.add_metric([], m.health_cpu)
        yield health_cpu
        yield _gauge("autotuner_loops", "Loops configured", len(m.loops))
        yield _gauge("autotuner_loops_tuning", "Loops tuning now", sum(loop.busy for loop in m.loops.values()))
        yield _gauge("autotuner_loops_not_restored", "Loops whose hand-back is still pending",
                     sum(loop.pending is not None for loop in m.loops.values()))
        yield _gauge("autotuner_event_streams", "Event streams open (per-loop and overview)",
                     self.state.streams.count)
        opcua = getattr(self.state, "opcua", None)
        if opcua is not None:
            yield _gauge("autotuner_opcua_sessions", "OPC UA client sessions open", opcua.sessions)
        yield _gauge("autotuner_history_queue", "History writes asked for and not done yet", m.recorder.pending)
        yield _gauge("autotuner_history_failing", "1 while the history's writes fail (disk full, locked, server gone: "
                     "the loops' history_error says why), else 0", float(m.recorder.health.error is not None))
        cpu = getattr(m.field, "cpu_seconds", None)
        if cpu is not None:
            family = CounterMetricFamily("autotuner_sampler_cpu_seconds", "CPU seconds of each sampler process",
                                         labels=["sampler"])
            for number, seconds in cpu().items():
                family.add_metric([str(number)], seconds)
            yield family


def _gauge(name: str, doc: str, value: float) -> GaugeMetricFamily:
    gauge = GaugeMetricFamily(name, doc)
    gauge.add_metric([], value)
    return gauge


def registry_of(manager: LoopManager, state: Any) -> CollectorRegistry:
    """A registry of the daemon's metrics (and the Python process's own: CPU, memory, file descriptors)."""
    from prometheus_client import GC_COLLECTOR, PLATFORM_COLLECTOR, PROCESS_COLLECTOR

    registry = CollectorRegistry(auto_describe=False)
    registry.register(DaemonCollector(manager, state))
    for default in (PROCESS_COLLECTOR, PLATFORM_COLLECTOR, GC_COLLECTOR):
        registry.register(default)
    return registry


def exposition(registry: CollectorRegistry) -> bytes:
    """The metrics in the Prometheus text format."""
    return generate_latest(registry)
