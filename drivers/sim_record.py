"""A simulated PLC's record for the loop-health assessment: its set point, PV, MV and mode, sample by sample,
faster than real time (the plant's clock, not the wall's)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from autotuner.engine.health.record import LoopRecord

from .link import Mode
from .simplc import SimulatedPlc


def record_plc(plc: SimulatedPlc, samples: int, sp_steps: Sequence[tuple[float, float]] = (),
               load_steps: Sequence[tuple[float, float]] = ()) -> LoopRecord:
    """Tick ``plc`` ``samples`` times and record each scan: the time (plant seconds), set point, PV and mode the
    PID unit starts it with and the MV it computes from them.

    ``sp_steps``: (T, SP) set-point changes, T plant seconds from now, SP in PV units; each takes effect at the
    first tick at or after T. ``load_steps``: (T, SIZE) load steps at the process input, SIZE MV units, likewise.
    """
    if samples < 2:
        raise ValueError(f"a record needs at least 2 samples, got {samples}")
    start = plc.t
    pending = sorted(sp_steps, reverse=True)  # next change last
    loads = sorted(load_steps, reverse=True)
    t, sp, pv, mv, auto = (np.empty(samples) for _ in range(5))
    for k in range(samples):
        while pending and plc.t - start >= pending[-1][0] - 1e-9 * plc.ts:
            plc.sp = float(pending.pop()[1])
        while loads and plc.t - start >= loads[-1][0] - 1e-9 * plc.ts:
            plc.sim.step_load(float(loads.pop()[1]))
        t[k], sp[k], pv[k], auto[k] = plc.t, plc.sp, plc.read_pv(), plc.mode is Mode.AUTO
        plc.tick()
        mv[k] = plc.mv
    return LoopRecord.of(t, sp, pv, mv, auto.astype(bool))
