"""How much a field can take: its CPU per sample, measured, and the share of a core a new session would need.

A sampler is one Python process: it can use one core at most, and its
samples come late well before that (a busy event loop answers late). So a
TUNE is admitted only while the loop's sampler is predicted to need at most
``sampler_load`` of a core (config, default 0.6) with the
new session added: the CPU seconds it spends per sample — a session's sample
or a monitor reading, measured over each batch of timings and smoothed
(:class:`Cost`) — times the samples per second of everything it would run,
counted from the plans (sample time, speed) and the monitor periods, not
measured, so that a hundred TUNEs asked at once are judged on what they will
need, not on what has started yet.
"""

from __future__ import annotations

from dataclasses import dataclass

# CPU seconds per sample assumed until a field has measured its own (two Modbus requests, the step, the status).
DEFAULT_COST = 400e-6
# Fewest samples (and monitor readings) a batch must hold for its CPU per sample to update the estimate.
MIN_SAMPLES = 50
# Weight of a new measurement in the estimate.
SMOOTHING = 0.2


@dataclass
class Cost:
    """CPU seconds a field spends per sample or monitor reading (an exponential average of its measurements)."""

    per_sample: float = DEFAULT_COST

    def update(self, cpu: float, samples: int) -> None:
        """``cpu`` CPU seconds spent over ``samples`` samples and readings (ignored below :data:`MIN_SAMPLES`)."""
        if samples >= MIN_SAMPLES:
            self.per_sample += SMOOTHING * (cpu / samples - self.per_sample)

    def load(self, rate: float) -> float:
        """The share of a core ``rate`` samples per second need."""
        return self.per_sample * rate
