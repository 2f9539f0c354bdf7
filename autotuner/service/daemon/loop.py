"""One loop as the loop manager holds it: its config, its tuning state, its last readings and its status."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from drivers.link import Link, LoopState, Mode
from drivers.simplc import SimulatedPlc

from autotuner.engine.control.gains import Gains
from autotuner.engine.experiment.relay import Status
from autotuner.engine.outcome import Code
from autotuner.engine.result import GainsRecord, ResultRecord
from autotuner.service.config import LoopConfig, TuneRequest
from autotuner.service.daemon.events import LoopEvents
from autotuner.service.daemon.field import Reach
from autotuner.service.daemon.health import LoopHealth
from autotuner.service.daemon.recorder import HistoryHealth
from autotuner.service.daemon.restore import Pending
from autotuner.service.daemon.settings import settings_of
from autotuner.service.daemon.status import BoundsRecord, HealthSummary, LoopStatus, OwnerRecord, UnitsRecord
from autotuner.service.link_session import SessionPlan, not_restored


@dataclass
class Session:
    """The running session of a loop, as the manager knows it: its id and task, the live PV and MV, what it
    recorded durably (the saved state, the relay's levels, the MV range, a gains intent) and how its hand-back
    ended ('' or why the loop is not handed back)."""

    sid: str
    plan: SessionPlan  # what it runs (its samples per second count in the admission)
    start: float = 0.0  # monotonic wall seconds
    task: asyncio.Task[None] | None = None
    pv: float = math.nan
    mv: float = math.nan
    saved: LoopState | None = None
    levels: tuple[float, ...] = ()
    mv_range: tuple[float, float] | None = None
    intended: Gains | None = None
    restore_error: str | None = None  # None: the hand-back has not reported yet


@dataclass
class Loop:
    """One loop at run time.

    ``mode``, ``pv``, ``sp``, ``mv`` and ``gains``: the monitor's last reading
    (None: not read yet); ``latest``: the newest finished session in the
    history; ``result``: the running or last session's result (None while it
    runs); ``running``: the running session (None: idle); ``pending``: a
    restore not done yet. ``history``: whether the daemon's history takes writes (one record for every loop).
    ``reach``: the loop's device in a local field (None
    in a sampler process): tests read its simulated PLC and may replace its
    connector.
    """

    config: LoopConfig
    reach: Reach | None = None
    running: Session | None = None
    session: str | None = None
    status: Status | None = None
    result: ResultRecord | None = None
    mode: Mode | None = None
    pv: float | None = None
    sp: float | None = None
    mv: float | None = None
    gains: Gains | None = None
    monitor_error: str | None = None
    latest: dict[str, Any] | None = None
    applying: bool = False
    pending: Pending | None = None
    restorer: asyncio.Task[None] | None = None
    owner: OwnerRecord | None = None  # in a fleet: the daemon holding the loop's lease
    events: LoopEvents = field(default_factory=LoopEvents)
    link_errors: int = 0  # failures of its watch's link and sessions ended by a link fault, since the start
    history: HistoryHealth = field(default_factory=HistoryHealth)  # the daemon's history, shared by every loop
    health: LoopHealth = field(kw_only=True)  # its online health

    @property
    def busy(self) -> bool:
        """TBSY: a session is running."""
        return self.running is not None

    @property
    def plc(self) -> SimulatedPlc | None:
        """The simulated PLC of a ``sim:`` loop in a local field (None otherwise)."""
        return None if self.reach is None else self.reach.plc

    @property
    def connect(self) -> Callable[[], Link]:
        """The local field's connector of this loop (tests replace it to inject faults)."""
        assert self.reach is not None, "the loop's field is not local"
        return self.reach.connect

    @connect.setter
    def connect(self, connect: Callable[[], Link]) -> None:
        assert self.reach is not None, "the loop's field is not local"
        self.reach.connect = connect

    @property
    def pending_gains(self) -> bool:
        """Idle, and the newest session succeeded with gains nobody has applied yet."""
        last = self.latest
        return (not self.busy and last is not None and last["outcome"] == "success"
                and last["applied_at"] is None and last["result"] is not None and last["result"].gains is not None)

    def live(self) -> tuple[str | None, float | None, float | None, float | None]:
        """Mode (MAN, AUTO or None), PV, SP and MV now: the session's while it runs, else the monitor's."""
        mode, pv, sp, mv = self.mode, self.pv, self.sp, self.mv
        s = self.running
        if s is not None and s.saved is not None:
            mode, sp = Mode.MAN, s.saved.sp  # the session holds the loop in MAN; its SP is the saved one
            if math.isfinite(s.pv):
                pv, mv = s.pv, s.mv
        return None if mode is None else Mode(mode).name, _finite(pv), _finite(sp), _finite(mv)

    def status_record(self) -> LoopStatus:
        """The status of design.md: tbsy, te, ite, stage, progress, last point and gains, live values."""
        c, s, r = self.config, self.status, self.result
        running = self.busy
        ite: float = (0.0 if s is None else s.ite) if running else (0 if r is None else r.ite)
        te = bool(r.te) if r is not None and not running else False
        message = "tuning" if running else (r.message if r else "idle")
        session = self.session
        p = self.pending
        if p is not None:  # not handed back: te, ite 20 and the message override the session's
            te, ite, message, session = True, float(Code.LOOP_NOT_RESTORED), not_restored(p.saved, p.error), p.sid
        mode, pv, sp, mv = self.live()
        return LoopStatus(
            id=c.id, description=c.description, group=c.group,
            link=c.link if c.link is not None else f"sim:{c.sim.plant}", speed=c.speed,
            tbsy=running, te=te, ite=ite, stage=None if s is None else s.stage.value,
            progress=0.0 if s is None else s.progress, message=message, session=session,
            controller=None if r is None else r.controller, point=None if r is None else r.point,
            static_gain=None if r is None else r.static_gain, gains=None if r is None else r.gains,
            mode=mode, pv=pv, sp=sp, mv=mv,  # type: ignore[arg-type]
            current_gains=None if self.gains is None else GainsRecord.of(self.gains),
            last_tuned_at=None if self.latest is None else self.latest["finished_at"],
            last_outcome=None if self.latest is None else self.latest["outcome"],
            pending_gains=self.pending_gains, monitor_error=self.monitor_error, history_error=self.history.error,
            defaults=settings_of(c, TuneRequest()), bounds=BoundsRecord(c.max_amp, c.max_hysteresis),
            units=_units(c), restore=None if p is None else p.status(), owner=self.owner,
            health=HealthSummary(**self.health.summary()))

    def as_json(self) -> dict[str, Any]:
        """The status as JSON (:meth:`status_record`)."""
        return self.status_record().to_json()


def _units(config: LoopConfig) -> UnitsRecord:
    u = config.units
    return UnitsRecord(u.pv, u.mv, u.decimals, u.pv_range, u.mv_range)


def _finite(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None
