"""How much a field can take: its CPU per sample, measured, and the share of a core a new session would need.

A sampler is one Python process: it can use one core at most, and its
samples come late well before that (a busy event loop answers late). So a
TUNE is admitted only while the loop's sampler is predicted to need at most
``sampler_load`` of a core (config, default 0.6) with the
new session added: the CPU seconds it spends per session sample and per monitor
reading — measured over each batch of timings and smoothed (:class:`Cost`) —
times the samples and readings per second of everything it would run
(:class:`Rates`), counted from the plans (sample time, speed) and the monitor
periods, not measured, so that a hundred TUNEs asked at once are judged on what
they will need, not on what has started yet.

The two costs are kept apart because they differ several times over (a session's
sample is a read, the experiment's step, a write, a status and its share of the
period's analyses; a reading one request), and a sampler that has only monitored
knows only the second: with one cost, 300 TUNEs asked of an idle plant were judged
on the readings' cost, all admitted, and 224 ended mid-experiment for lateness
(docs/daemon.md, "A plant"). Until a sampler has measured its sessions' samples,
they are assumed to cost :data:`DEFAULT_SAMPLE_COST`.
"""

from __future__ import annotations

from dataclasses import dataclass

# CPU seconds per session sample assumed until a field has measured its own (two Modbus requests, the step, the
# status, the analyses' share), and per monitor reading (one request, the reading's publication).
DEFAULT_SAMPLE_COST = 400e-6
DEFAULT_READING_COST = 100e-6
# Fewest samples (or monitor readings) a batch must hold for its CPU per sample (per reading) to update the estimate.
MIN_SAMPLES = 50
# Weight of a new measurement in the estimate.
SMOOTHING = 0.2


@dataclass(frozen=True)
class Rates:
    """What a field runs, per wall second: session ``samples`` and monitor ``readings``."""

    samples: float = 0.0
    readings: float = 0.0


@dataclass
class Cost:
    """CPU seconds a field spends per session ``sample`` and per monitor ``reading`` (exponential averages of its
    measurements)."""

    sample: float = DEFAULT_SAMPLE_COST
    reading: float = DEFAULT_READING_COST

    def update(self, cpu: float, samples: int, readings: int) -> None:
        """``cpu`` CPU seconds spent over ``samples`` session samples and ``readings`` monitor readings: a batch of
        readings alone updates the reading's cost; one with at least :data:`MIN_SAMPLES` samples the sample's (what
        the readings did not take). Other batches say nothing certain and are ignored."""
        if samples == 0 and readings >= MIN_SAMPLES:
            self.reading += SMOOTHING * (cpu / readings - self.reading)
        elif samples >= MIN_SAMPLES:
            own = max(cpu - readings * self.reading, 0.0)
            self.sample += SMOOTHING * (own / samples - self.sample)

    def load(self, rates: Rates) -> float:
        """The share of a core ``rates`` need."""
        return self.sample * rates.samples + self.reading * rates.readings
