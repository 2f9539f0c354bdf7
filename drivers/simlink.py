"""In-process link to a :class:`SimulatedPlc`: the Link protocol without a transport.

For tests of the session layer and for tuning a simulated loop end to end
without a server. ``outage`` injects a link loss: the calls numbered
``outage[0]`` up to (not including) ``outage[1]`` raise LinkError, as a dead
connection would; later calls work again.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from autotuner.engine.control.gains import Gains

from .link import LinkError, LoopState, Mode, Sample, TuneFlags, Watchdog, checked
from .simplc import SimulatedPlc


@dataclass
class SimLink:
    """Link to ``plc`` in the same process."""

    plc: SimulatedPlc
    outage: tuple[int, int] | None = None
    calls: int = 0
    pv_age: float | None = None  # the value is read at the moment of the call
    epoch: int | None = None  # a lease epoch is not written: the PLC is this process's own, no other writes it

    @property
    def carries_epoch(self) -> bool:
        return False

    def _call(self) -> None:
        self.calls += 1
        if self.outage is not None and self.outage[0] <= self.calls < self.outage[1]:
            raise LinkError("simulated link lost")

    def health(self) -> dict[str, Any]:
        """Call counter, and whether the simulated outage is on."""
        down = self.outage is not None and self.outage[0] <= self.calls < self.outage[1]
        return {"transport": "simulation", "connected": not down, "calls": self.calls}

    async def open(self) -> None:
        self._call()

    async def close(self) -> None:
        pass

    async def read_pv(self) -> float:
        self._call()
        return checked("pv", self.plc.read_pv())

    async def write_mv(self, mv: float) -> None:
        self._call()
        self.plc.hv = checked("mv", mv)

    async def read_state(self) -> LoopState:
        self._call()
        plc = self.plc
        return LoopState(mode=plc.mode, mv=plc.mv, sp=plc.sp, gains=plc.gains)

    async def read_sample(self) -> Sample:
        self._call()
        plc = self.plc
        return Sample(pv=checked("pv", plc.read_pv()), mv=plc.mv, sp=plc.sp, mode=plc.mode, boot=plc.boot)

    async def write_mode(self, mode: Mode) -> None:
        self._call()
        self.plc.mode = Mode(mode)

    async def write_gains(self, gains: Gains) -> None:
        self._call()
        self.plc.set_gains(gains)

    async def read_flags(self) -> TuneFlags:
        self._call()
        return self.plc.flags

    async def write_flags(self, flags: TuneFlags) -> None:
        self._call()
        plc = self.plc
        plc.flags = TuneFlags(tune=plc.flags.tune, tbrk=plc.flags.tbrk, tbsy=flags.tbsy, te=flags.te, ite=flags.ite)

    def mv_resolution(self, mv: float) -> float:
        """0: the MV goes to the PLC and back as the same float."""
        return 0.0

    async def write_watchdog(self, watchdog: Watchdog) -> None:
        self._call()
        self.plc.watchdog = watchdog

    async def write_heartbeat(self, counter: int) -> None:
        self._call()
        self.plc.heartbeat = counter % 65536
