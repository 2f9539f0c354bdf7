"""Faults of a simulated loop for the loop-health monitor: a sticky valve, a valve deadband, a stochastic load,
random load steps, an external sinusoidal disturbance and a frozen PV sensor.

:class:`Faults` says which faults a loop has (all off by default); :class:`FaultyLoop` applies them sample by
sample between the controller and the plant (:class:`autotuner.engine.plant.simulation.PlantSim`): the
controller output goes through the valve (:class:`autotuner.engine.plant.valve.StickyValve`), the loads add at
the process input, and the sensor may freeze. Detuned gains are no fault of the plant: they are the controller's
gains (the plant file's ``detune``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.plant.valve import StickyValve


@dataclass(frozen=True)
class Faults:
    """What is wrong with a simulated loop (every field off by default).

    stiction_s, stiction_j: Choudhury's valve stiction, deadband plus stickband S and slip jump J, % of the MV
    span. deadband: a valve deadband (backlash), % of the MV span; it adds to S (Choudhury's S is deadband plus
    stickband). load_std, load_tau: a stochastic load at the process input, first-order filtered white noise of
    standard deviation ``load_std`` MV units and time constant ``load_tau`` plant seconds.
    sine_amplitude, sine_period: an external sinusoidal disturbance at the process input, MV units and plant
    seconds. step_size, step_interval: random load steps at the process input, of ±0.5–1 × ``step_size`` MV
    units at exponentially distributed intervals of mean ``step_interval`` plant seconds.
    frozen_at: the PV sensor freezes at this plant time (seconds from the start) and reads the same value from
    then on (None: never).
    """

    stiction_s: float = 0.0
    stiction_j: float = 0.0
    deadband: float = 0.0
    load_std: float = 0.0
    load_tau: float = 0.0
    sine_amplitude: float = 0.0
    sine_period: float = 0.0
    step_size: float = 0.0
    step_interval: float = 0.0
    frozen_at: float | None = None

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if value is not None and not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"fault {f.name} must be a finite number ≥ 0, got {value}")
        if self.load_std > 0.0 and self.load_tau <= 0.0:
            raise ValueError("a stochastic load (load_std > 0) needs its time constant load_tau > 0 s")
        if self.sine_amplitude > 0.0 and self.sine_period <= 0.0:
            raise ValueError("a sinusoidal disturbance (sine_amplitude > 0) needs its period sine_period > 0 s")
        if self.step_size > 0.0 and self.step_interval <= 0.0:
            raise ValueError("random load steps (step_size > 0) need their mean interval step_interval > 0 s")

    @property
    def any(self) -> bool:
        """True when at least one fault is on."""
        return self != Faults()

    @property
    def valve_band(self) -> float:
        """The valve's S (deadband plus stickband), % of the MV span."""
        return self.stiction_s + self.deadband


class FaultyLoop:
    """The faults of one loop applied between its controller and ``sim``, sample by sample.

    ``span``: the MV span (MV units) the valve's % refer to; ``seed``: of the stochastic load's noise.

    ``faults``: what is wrong.
    """

    def __init__(self, faults: Faults, sim: PlantSim, span: float, seed: int | None) -> None:
        if not (math.isfinite(span) and span > 0.0):
            raise ValueError(f"the MV span must be a positive number of MV units, got {span}")
        self.faults = faults
        self.sim = sim
        band = faults.valve_band
        self._valve = StickyValve(band * span / 100.0, faults.stiction_j * span / 100.0) if band > 0.0 else None
        self._rng = np.random.default_rng(seed)
        self._phi = math.exp(-sim.ts / faults.load_tau) if faults.load_std > 0.0 else 0.0
        self._noise = 0.0  # the stochastic load now, MV units
        self._steps = 0.0  # the random load steps so far, MV units
        self._next_step = self._rng.exponential(faults.step_interval) if faults.step_size > 0.0 else math.inf
        self._load = 0.0  # the total of this class's loads the plant holds, MV units
        self._frozen: float | None = None

    def _disturbance(self) -> float:
        """The stochastic load, the sinusoid and the random steps over the next interval, MV units."""
        f = self.faults
        if f.load_std > 0.0:
            self._noise = self._phi * self._noise + f.load_std * math.sqrt(1.0 - self._phi ** 2) * float(
                self._rng.standard_normal())
        sine = f.sine_amplitude * math.sin(2.0 * math.pi * self.sim.t / f.sine_period) if f.sine_amplitude else 0.0
        while self.sim.t >= self._next_step:
            self._steps += float(self._rng.choice((-1.0, 1.0)) * self._rng.uniform(0.5, 1.0)) * f.step_size
            self._next_step += self._rng.exponential(f.step_interval)
        return self._noise + sine + self._steps

    def advance(self, mv: float) -> float:
        """Hold the controller output ``mv`` (MV units) over the next interval through the valve, with the loads;
        returns the controller output as the plant's limits clip it (the MV a PLC shows, not the valve's)."""
        lo, hi = self.sim.mv_limits
        applied = min(max(float(mv), lo), hi)
        load = self._disturbance()
        self.sim.step_load(load - self._load)
        self._load = load
        self.sim.advance(applied if self._valve is None else self._valve.step(applied))
        return applied

    def measure(self) -> float:
        """The PV as the sensor reads it: the plant's measurement, or the value it froze at."""
        if self._frozen is not None:
            return self._frozen
        pv = self.sim.measure()
        if self.faults.frozen_at is not None and self.sim.t >= self.faults.frozen_at:
            self._frozen = pv
        return pv
