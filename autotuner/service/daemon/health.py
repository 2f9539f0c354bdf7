"""A loop's online health (docs/health.md, "Online"): the monitor's readings kept over the window, the job that
assesses them in a worker process, and what REST, the event streams and OPC UA show of the result.

Per loop a bounded record of the idle loop's monitor readings (t in plant seconds, SP, PV, MV, AUTO) covering
the configured window (:class:`Readings`), restarted when a tuning session starts: new gains make the samples
before another loop. :class:`LoopHealth` says when the loop is due (every ``every`` plant seconds, on a grid
staggered across the loops), builds the :class:`HealthJob` (the record, the MV limits and PV range, the newest
successful session's identified model) that :func:`run_job` assesses in a worker process, and keeps the
result: the summary (``state``, ``severity``, ``rank``, ``flags``, ``recommendation``, ``reason``, ``time``),
the assessment, the evidence drawn on the page, and the last assessment before the newest tuning.

The loop is ``pending`` until its record holds :data:`MIN_READINGS` readings covering :data:`MIN_SHARE` of the
window, ``off`` when its config disables the monitoring, ``ok`` once assessed for its current gains.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from autotuner.engine.health.assessment import MIN_SAMPLES, LoopRecord, assess_detail
from autotuner.engine.health.scales import LoopLimits
from autotuner.engine.plant.process import Process
from autotuner.service.config import LoopConfig

# A record needs this many readings (the assessment's own minimum) ...
MIN_READINGS = MIN_SAMPLES
# ... covering this share of the window before the loop is assessed: fewer say little about an hour.
MIN_SHARE = 0.1
# Readings kept per loop at most: past this many per window, every k-th reading is kept so the record spans the
# window (an hour at 1 s is 3600; a day at 1 s would be 86 400, kept every 5th).
MAX_READINGS = 20_000
# Evidence points sent to the page at most (the assessed window downsampled evenly).
EVIDENCE_POINTS = 1000
# Assessments kept per loop in the history.
KEPT = 1000
# Severity levels, for the rank (higher: worse).
LEVELS = {"none": 0, "low": 1, "medium": 2, "high": 3}


class Readings:
    """A ring of the newest readings of one loop: ``capacity`` of them, one kept in ``stride``."""

    def __init__(self, capacity: int, stride: int = 1) -> None:
        self.capacity, self.stride = capacity, stride
        self._data = np.zeros((5, capacity))
        self._n = 0  # readings kept so far (the newest at (_n - 1) % capacity)
        self._seen = 0  # readings offered, for the stride

    def __len__(self) -> int:
        return min(self._n, self.capacity)

    def clear(self) -> None:
        """Forget every reading."""
        self._n = self._seen = 0

    @property
    def last_t(self) -> float:
        """Plant time of the newest reading kept (-inf: none)."""
        return float(self._data[0, (self._n - 1) % self.capacity]) if self._n else -math.inf

    @property
    def span(self) -> float:
        """Plant seconds from the oldest reading kept to the newest (0: fewer than two)."""
        if self._n < 2:
            return 0.0
        oldest = 0 if self._n <= self.capacity else self._n % self.capacity
        return self.last_t - float(self._data[0, oldest])

    def add(self, t: float, sp: float, pv: float, mv: float, auto: bool) -> None:
        """Keep a reading (``t`` plant s, SP and PV PV units, MV MV units, ``auto`` in AUTO) unless the stride
        skips it; one whose time does not increase (a wall clock stepped back) or whose values are not finite
        is dropped."""
        self._seen += 1
        if (self._seen - 1) % self.stride or not t > self.last_t or not math.isfinite(sp + pv + mv):
            return
        self._data[:, self._n % self.capacity] = (t, sp, pv, mv, 1.0 if auto else 0.0)
        self._n += 1

    def columns(self) -> np.ndarray:
        """The readings kept, oldest first: rows t, sp, pv, mv, auto (a copy)."""
        n = len(self)
        if self._n <= self.capacity:
            return self._data[:, :n].copy()
        k = self._n % self.capacity
        return np.concatenate((self._data[:, k:], self._data[:, :k]), axis=1)


@dataclass(frozen=True)
class HealthJob:
    """What a worker assesses: one loop's readings (rows t, sp, pv, mv, auto), its ``limits``, its ``model``
    (None: none), the ``window`` (plant s) and the PV's unit for the reasons."""

    loop: str
    columns: np.ndarray
    limits: LoopLimits
    model: Process | None
    window: float
    pv_unit: str


def run_job(job: HealthJob) -> dict[str, Any]:
    """Assess ``job`` (in a worker process): ``{"assessment": Assessment.to_json(), "evidence": {...}}``, or
    ``{"error": why}`` when the record cannot be assessed."""
    t, sp, pv, mv, auto = job.columns
    try:
        detail = assess_detail(LoopRecord.of(t, sp, pv, mv, auto > 0.5), job.limits, job.model, job.window,
                               pv_unit=job.pv_unit)
    except ValueError as exc:
        return {"error": str(exc)}
    rec = detail.record
    keep = np.unique(np.linspace(0, len(rec) - 1, min(len(rec), EVIDENCE_POINTS)).round().astype(int))
    start = float(rec.t[0])
    # arrays, not lists: they come back to the API's process pickled as buffers; made lists when asked for
    evidence = {"t": rec.t[keep] - start, "sp": rec.sp[keep], "pv": rec.pv[keep], "mv": rec.mv[keep],
                "crossings": detail.crossings - start, "period": detail.period, "amplitude": detail.amplitude}
    return {"assessment": detail.assessment.to_json(), "evidence": evidence}


def summary_of(state: str, assessment: dict[str, Any] | None, reason: str = "") -> dict[str, Any]:
    """The summary of a loop's health (docs/health.md, "Online"): ``state`` ok, pending or off; with an
    ``assessment`` (its JSON with ``time``) its flags, worst severity, rank and worst flag's reason; ``reason``
    what a pending loop waits for."""
    if assessment is None or state != "ok":
        return {"state": state, "severity": "none", "rank": 0, "flags": [], "recommendation": "none",
                "reason": reason, "time": None if assessment is None else assessment["time"]}
    severities = assessment["severities"]
    worst = max(assessment["flags"], key=lambda name: LEVELS[severities[name]], default=None)
    severity = "none" if worst is None else severities[worst]
    # worse first: the worst severity, then how many flags at all
    rank = 10 * LEVELS[severity] + len(assessment["flags"])
    return {"state": "ok", "severity": severity, "rank": rank, "flags": list(assessment["flags"]),
            "recommendation": assessment["recommendation"],
            "reason": "" if worst is None else assessment["reasons"][worst], "time": assessment["time"]}


def limits_of(config: LoopConfig) -> LoopLimits:
    """The MV limits and PV range the assessment weighs a loop against: its ``limits`` where finite, else its
    display ranges (``units``), else 0–100 for the MV and no PV range."""
    def finite(pair: tuple[float, float]) -> bool:
        return math.isfinite(pair[0]) and math.isfinite(pair[1])

    mv = config.limits.mv if finite(config.limits.mv) else config.units.mv_range or (0.0, 100.0)
    pv = config.limits.pv if finite(config.limits.pv) else config.units.pv_range
    return LoopLimits(mv=tuple(mv), pv=None if pv is None else tuple(pv))  # type: ignore[arg-type]


@dataclass
class LoopHealth:
    """One loop's online health: its readings, when it is due, its newest assessment and the one before its
    newest tuning.

    ``origin``: the wall time (unix s) plant time counts from; ``phase``: the loop's offset on the grid of
    assessment times, a share of ``every`` (loops spread over it so their assessments do not come together).
    """

    config: LoopConfig
    origin: float
    phase: float = 0.0
    model: Process | None = None
    session: str | None = None  # the newest tuning session (the record restarted at its start)
    assessment: dict[str, Any] | None = None  # Assessment.to_json() + "time"; None: none for the current gains
    evidence: dict[str, Any] | None = None
    before: dict[str, Any] | None = None  # the last assessment before the newest tuning, with "session"
    busy: bool = False  # a job is in a worker
    generation: int = 0  # grows when the record restarts: a job of an older record is dropped
    due: float = -math.inf  # plant time of the next assessment
    readings: Readings = field(init=False)

    def __post_init__(self) -> None:
        spacing = self.config.monitor_period * self.config.speed  # plant s between two readings
        wanted = math.ceil(1.25 * self.config.health.window / spacing) + 10  # room for readings coming early
        stride = max(1, math.ceil(wanted / MAX_READINGS))
        self.readings = Readings(min(wanted, MAX_READINGS), stride)

    @property
    def enabled(self) -> bool:
        """The config enables the loop's health monitoring."""
        return self.config.health.enabled

    def plant_time(self, wall: float) -> float:
        """The plant seconds of unix time ``wall``."""
        return (wall - self.origin) * self.config.speed

    def add(self, wall: float, sp: float, pv: float, mv: float, auto: bool) -> None:
        """A monitor reading of the idle loop at unix time ``wall`` (SP, PV in PV units, MV in MV units)."""
        if self.enabled:
            self.readings.add(self.plant_time(wall), sp, pv, mv, auto)

    def restart(self, sid: str) -> None:
        """A tuning session ``sid`` starts: the record and the current assessment belong to the gains before it
        (the assessment is kept as the one before this tuning)."""
        if self.assessment is not None:
            self.before = {**self.assessment, "session": sid}
        self.session, self.assessment, self.evidence = sid, None, None
        self.readings.clear()
        self.generation += 1
        self.due = -math.inf

    def needed(self) -> int:
        """Readings the record needs before a first assessment."""
        spacing = self.config.monitor_period * self.config.speed * self.readings.stride
        return max(MIN_READINGS, math.ceil(MIN_SHARE * self.config.health.window / spacing))

    def ready(self) -> bool:
        """The record holds enough readings to be assessed."""
        n = len(self.readings)
        return n >= MIN_READINGS and (n >= self.needed() or self.readings.span >= MIN_SHARE * self.config.health.window)

    def is_due(self, wall: float) -> bool:
        """An assessment is due at unix time ``wall``: enabled, no job out, the record ready and the loop's grid's
        next time reached (the first: the grid's first time once the record is ready)."""
        if not self.enabled or self.busy or not self.ready():
            return False
        now = self.plant_time(wall)
        if self.due == -math.inf:  # the first on the loop's grid too: loops ready together are not assessed together
            every = self.config.health.every
            self.due = (math.ceil(now / every - self.phase) + self.phase) * every
        return now >= self.due

    def job(self, wall: float) -> HealthJob:
        """The job assessing the record now; the next one is due at the grid's next time."""
        every = self.config.health.every
        now = self.plant_time(wall)
        self.due = (math.floor(now / every - self.phase) + 1 + self.phase) * every
        self.busy = True
        return HealthJob(self.config.id, self.readings.columns(), limits_of(self.config), self.model,
                         self.config.health.window, self.config.units.pv)

    def done(self, result: dict[str, Any], wall: float, generation: int) -> bool:
        """A job's ``result`` (:func:`run_job`) made at unix time ``wall`` for record ``generation``: kept
        unless the record restarted meanwhile. True when kept."""
        self.busy = False
        if generation != self.generation or "assessment" not in result:
            return False
        self.assessment = {**result["assessment"], "time": wall}
        self.evidence = result["evidence"]
        return True

    def summary(self) -> dict[str, Any]:
        """The loop's health summary now (:func:`summary_of`)."""
        if not self.enabled:
            return summary_of("off", None, "health monitoring is disabled in the loop's config")
        if self.assessment is None:
            return summary_of("pending", None, f"collecting: {len(self.readings)} of {self.needed()} samples")
        return summary_of("ok", self.assessment)

    def detail(self) -> dict[str, Any]:
        """The loop's health in full (``GET /loops/{id}/health``): the summary's state, severity, rank and reason,
        the assessment, the configured window, the assessment before the newest tuning and the evidence."""
        summary = self.summary()
        return {"loop": self.config.id, "state": summary["state"], "severity": summary["severity"],
                "rank": summary["rank"], "reason": summary["reason"], "assessment": self.assessment,
                "window_setting": self.config.health.window, "before_tuning": self.before,
                "evidence": None if self.assessment is None or self.evidence is None else {
                    key: value.tolist() if isinstance(value, np.ndarray) else value
                    for key, value in self.evidence.items()}}

    def restore(self, latest: dict[str, Any] | None, before: dict[str, Any] | None) -> None:
        """After a restart: the newest stored assessment (``latest``, with its ``session``: the newest tuning
        before it) is the current one unless the loop was tuned since (``self.session`` differs): then it is the
        one before that tuning, as is ``before`` (the newest stored before the newest tuning started)."""
        if latest is not None and latest.get("session") == self.session:
            self.assessment = {k: v for k, v in latest.items() if k != "session"}
        if self.session is not None and before is not None:
            self.before = {**before, "session": self.session}


def now() -> float:
    """Unix seconds now (the assessments' ``time``)."""
    return time.time()
