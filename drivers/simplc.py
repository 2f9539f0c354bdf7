"""A simulated PLC: a process under a PIDU-like PID unit, with the autotuner handshake.

It is what the simulated plant servers (Modbus, CAN) expose: PV, MV, SP,
mode (MAN/AUTO), the PID gains, the manual MV, and the TUNE/TBRK/TBSY/TE/ite
bits. In MAN the PID unit copies the manual MV to its output and tracks it,
so returning to AUTO is bumpless, as on the real block: the tuner writes
the saved MV, waits until the actual MV reads it back (the unit has ticked
in MAN with it and its state tracks it), and only then writes AUTO; the
first AUTO output is then the saved MV (docs/handback.md). Faults can be
injected for tests: a PV that reads NaN; and for the loop-health monitor
(``faults``, :class:`autotuner.engine.plant.faults.Faults`): a sticky valve
or a valve deadband between the PID unit and the process (the PLC shows the
PID unit's output, not the valve's position), a stochastic load and a
sinusoidal disturbance at the process input, a frozen PV sensor.

The hand-back watchdog (:class:`drivers.link.Watchdog`): while ``watchdog``
is armed and ``heartbeat`` has not changed for its timeout (plant seconds),
the PLC falls back by itself, bumplessly the same way: one tick in MAN at
the fallback MV, then the fallback mode, TBSY cleared, TE set and ite
:attr:`Code.WATCHDOG_FALLBACK`, the watchdog disarmed.

Time is the plant's: :meth:`tick` advances one sample; :func:`run` ticks in
real time (or ``speed`` times faster), deadline-scheduled so it does not drift;
:func:`run_many` ticks many PLCs of one sample time from one task (a plant).
"""

from __future__ import annotations

import asyncio
import functools
import math
import secrets
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from autotuner.engine.design.point_design import design
from autotuner.engine.control.gains import Gains
from autotuner.engine.control.pid import PidUnit
from autotuner.engine.plant.faults import Faults, FaultyLoop
from autotuner.engine.plant.process import Process
from autotuner.engine.plant.simulation import PlantSim
from autotuner.engine.design.process_data import exact_point, least_lag_point
from autotuner.engine.simulated_tuning import default_sample_time

from autotuner.engine.outcome import Code

from .link import Mode, TuneFlags, Watchdog


@functools.lru_cache(maxsize=64)
def safe_gains(process: Process) -> Gains:
    """A cautious PI for the simulated plant's starting state (designed from the exact 135° point at Ms 1.2).

    Remembered per process (a Process and Gains are frozen): the design takes ~0.1 s, and a plant of many
    loops of one process (:mod:`drivers.modbus_plant`) would make it once per loop.

    An open-loop unstable process never lags as little as 135°: its PI is designed from the point of least
    lag (a real loop's controller holds it; k = 0.1 would hold it only while it sits exactly at rest, and it
    ran away the moment a tuner handed the loop back). A process no PI holds keeps k = 0.1.
    """
    point = exact_point(process, 135.0)
    if point is None and process.static_gain() < 0.0:
        point = least_lag_point(process)
    if point is None:
        return Gains(k=0.1, ti=10.0)
    try:
        g = design(point, process.static_gain(), "PI", ms=1.2).gains
    except ValueError:  # (a Refusal too: no PI stabilises it)
        return Gains(k=0.1, ti=10.0)
    return Gains(k=g.k, ti=g.ti, b=1.0)


@dataclass
class SimulatedPlc:
    """Process ``process`` sampled every ``ts`` seconds (plant time) under a PID unit, starting steady in AUTO.

    ``loads``: (T, SIZE) load steps at the process input, SIZE MV units, T
    plant seconds after the PLC first ticks in MAN (a tuner taking the loop
    over): a disturbance during an experiment over the link. ``faults``: what
    is wrong with the loop (none by default); the stochastic load's noise is
    seeded from ``seed`` apart from the PV noise's. ``on_mode(t, mode, mv)``:
    called at the first tick in a new mode, with the plant time (s) and the MV
    the PID unit put out at that tick (MV units) — the device's own record of
    a hand-over, which a client reading it may be too late to see.
    """

    process: Process
    ts: float = 0.0
    pv0: float = 50.0
    mv0: float = 50.0
    noise_std: float = 0.0
    seed: int | None = 0
    mv_limits: tuple[float, float] = (0.0, 100.0)
    mode: Mode = Mode.AUTO
    flags: TuneFlags = field(default_factory=TuneFlags)
    nan_pv: bool = False
    heartbeat: int = 0
    fallbacks: int = 0
    loads: tuple[tuple[float, float], ...] = ()
    faults: Faults = Faults()
    # A new token at every start of the PLC (1..65535), served as ``boot``: a tuner whose session sees it change
    # knows the device restarted with its registers at their defaults (docs/modbus.md).
    boot: int = field(default_factory=lambda: secrets.randbelow(65535) + 1)
    # The newest lease epoch a fleet's daemon has written (0: none since the start); the servers refuse the writes
    # of a client whose own epoch is older (docs/fleet.md). ``fenced``: the writes they refused so.
    epoch: int = 0
    fenced: int = 0
    on_mode: Callable[[float, Mode, float], None] | None = None

    def __post_init__(self) -> None:
        if self.ts <= 0.0:
            self.ts = default_sample_time(self.process)
        self.sim = PlantSim(self.process, self.ts, pv0=self.pv0, mv0=self.mv0, noise_std=self.noise_std,
                            seed=self.seed, mv_limits=self.mv_limits)
        lo, hi = self.mv_limits
        # None without faults: the plant is then driven exactly as before faults existed
        self._faulty = (FaultyLoop(self.faults, self.sim, hi - lo, None if self.seed is None else [self.seed, 1])
                        if self.faults.any else None)
        self.pid = PidUnit(safe_gains(self.process), kind="PI", lolim=lo, hilim=hi)
        self.sp = self.pv0
        self.hv = self.mv0
        self.mv = self.mv0
        self.pv = self.sim.measure()
        self.pid.reset(self.mv0, self.sp, self.pv)
        self._watchdog = Watchdog()
        self._beat = (self.heartbeat, self.sim.t)  # the last heartbeat value seen and when it changed
        self._falling_back = False
        for time, size in self.loads:
            if not (math.isfinite(time) and time >= 0.0 and math.isfinite(size)):
                raise ValueError(f"load step ({time}, {size}) must be T ≥ 0 plant seconds and a finite size")
        self._pending = sorted(self.loads, reverse=True)  # next step last
        self._taken_at: float | None = None  # plant time of the first tick in MAN
        self._ticked_mode = self.mode  # the mode of the last tick

    @property
    def watchdog(self) -> Watchdog:
        """The hand-back watchdog as armed by the tuner (timeout 0: off)."""
        return self._watchdog

    @watchdog.setter
    def watchdog(self, watchdog: Watchdog) -> None:
        self._watchdog = watchdog
        self._beat = (self.heartbeat, self.sim.t)  # arming starts the timeout afresh

    @property
    def t(self) -> float:
        """Plant time, seconds."""
        return self.sim.t

    @property
    def gains(self) -> Gains:
        """The PID unit's gains."""
        return self.pid.gains

    def set_gains(self, gains: Gains) -> None:
        """New gains, bumpless (the PID unit moves the change into its integral state)."""
        self.pid.gains = gains

    def read_pv(self) -> float:
        """The PV as the PLC serves it (NaN while the fault is injected)."""
        return math.nan if self.nan_pv else self.pv

    def _check_watchdog(self) -> None:
        """Fall back when the armed watchdog's heartbeat has been still for its timeout."""
        if self._falling_back:  # the last tick ran in MAN at the fallback MV: the unit tracks it, resume
            self._falling_back = False
            self.mode = Mode(self._watchdog.mode)
            self._watchdog = Watchdog()
            self.fallbacks += 1
            self.flags = TuneFlags(tune=self.flags.tune, tbrk=self.flags.tbrk, tbsy=False, te=True,
                                   ite=float(Code.WATCHDOG_FALLBACK))
            return
        if self.heartbeat != self._beat[0]:
            self._beat = (self.heartbeat, self.sim.t)
            return
        if self._watchdog.timeout > 0.0 and self.sim.t - self._beat[1] >= self._watchdog.timeout:
            self._falling_back = True
            self.mode = Mode.MAN
            self.hv = self._watchdog.mv

    def _apply_loads(self, man: bool) -> None:
        if man and self._taken_at is None:
            self._taken_at = self.sim.t
        while self._pending and self._taken_at is not None and self.sim.t - self._taken_at >= self._pending[-1][0]:
            self.sim.step_load(self._pending.pop()[1])

    def tick(self) -> None:
        """One sample: controller output from the current PV, then the plant advances ``ts``."""
        self._check_watchdog()
        man = self.mode is Mode.MAN
        self._apply_loads(man)
        self.mv = self.pid.step(self.sim.t, self.sp, self.pv, man=man, hv=self.hv if man else None)
        if not man:
            self.hv = self.mv  # the manual value follows, so a switch to MAN is bumpless too
        if self.mode is not self._ticked_mode:
            self._ticked_mode = self.mode
            if self.on_mode is not None:
                self.on_mode(self.sim.t, self.mode, self.mv)
        if self._faulty is None:
            self.mv = self.sim.advance(self.mv)
            self.pv = self.sim.measure()
        else:
            self.mv = self._faulty.advance(self.mv)
            self.pv = self._faulty.measure()


async def run(plc: SimulatedPlc, speed: float = 1.0, stop: asyncio.Event | None = None) -> None:
    """Tick ``plc`` so its clock follows the wall clock ``speed`` times faster, until ``stop`` is set
    (:func:`run_many` of one PLC)."""
    await run_many([plc], speed, stop)


async def run_many(plcs: Sequence[SimulatedPlc], speed: float = 1.0, stop: asyncio.Event | None = None) -> None:
    """Tick every PLC of ``plcs`` (one sample time, seconds) so their clocks follow the wall clock ``speed`` times
    faster, until ``stop`` is set, from this one task: one timer for the lot, however many there are.

    After a stall (a busy machine) the due ticks are made at once, before any
    other task runs: whoever reads a PLC then sees the state of the present
    moment, never a plant lagging behind the wall clock. The PLCs are
    independent, so ticking them one after the other changes none of them.
    ValueError if there are none or their sample times differ.
    """
    times = sorted({plc.ts for plc in plcs})
    if len(times) != 1:
        raise ValueError(f"run_many needs PLCs of one sample time, got sample times {times}")
    period = plcs[0].ts / speed
    start = time.monotonic()
    done = 0
    while stop is None or not stop.is_set():
        due = int((time.monotonic() - start) / period)
        if due > done:
            for plc in plcs:
                for _ in range(due - done):
                    plc.tick()
            done = due
        await asyncio.sleep(max(start + (done + 1) * period - time.monotonic(), 0.0))
