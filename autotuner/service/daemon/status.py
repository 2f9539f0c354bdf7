"""A loop's status: one typed record for REST (``GET /loops/{id}``), the event streams and OPC UA.

:class:`LoopStatus` is the status of design.md — the PIDAT outputs (tbsy,
te, ite), the stage and progress, the last session's point and gains, the
live values — with each field's description, unit and an example in its
``metadata`` (pydantic reads them into the OpenAPI document, as it does the
result's records). :meth:`LoopStatus.to_json` is its one encoder.
"""

# No ``from __future__ import annotations`` here: pydantic 2.6 (the lowest allowed) resolves the string
# annotations of the stdlib dataclasses nested in a model (HealthSummary in LoopStatus in api/models.py) in the
# namespace of the module that builds the model, where this module's Literal aliases are not defined.
import functools
from dataclasses import dataclass, fields, is_dataclass
from enum import Enum
from typing import Any, Literal

from autotuner.engine.described import described
from autotuner.engine.result import GainsRecord, PointRecord
from autotuner.service.daemon.settings import Settings

SID = "3f2c9a7e5b1d4c6a8e0f2b4d6a8c0e1f"
WHEN = "2026-12-01T20:57:36.412Z"


@dataclass(frozen=True)
class UnitsRecord:
    """The loop's engineering units and display, from its config's ``units`` (docs/daemon.md, "Units")."""

    pv: str = described("unit of the PV and SP (and of the hysteresis); \"\": none configured", example="°C")
    mv: str = described("unit of the MV (and of the relay amplitude); \"\": none configured", example="%")
    decimals: int | None = described("digits after the decimal point of PV, SP and MV values (null: 4 significant "
                                     "digits)", example=1)
    pv_range: tuple[float, float] | None = described("display range [low, high] of the PV axis, PV units (null: fit "
                                                     "the data)", example=[20.0, 120.0])
    mv_range: tuple[float, float] | None = described("display range [low, high] of the MV axis, MV units (null: fit "
                                                     "the data)", example=[0.0, 100.0])


@dataclass(frozen=True)
class BoundsRecord:
    """The loop's own bounds on a TUNE's settings, tighter than the OpenAPI schema's global ones (a static schema
    cannot carry a bound per loop): a request above one is refused (422 invalid, naming the field)."""

    amp: float = described("largest relay amplitude, MV units: the span of the MV limits, else tuning.max_amp",
                           example=100.0)
    hysteresis: float = described("largest relay hysteresis, PV units: tuning.max_hysteresis, else a quarter of "
                                  "the span of the PV limits (25 without them)", example=25.0)


@dataclass(frozen=True)
class RestoreStatus:
    """A loop the daemon could not hand back yet (``ite`` 20), retried with back-off (docs/handback.md)."""

    session: str = described("the session whose hand-back is pending", example=SID)
    mode: Literal["MAN", "AUTO"] = described("the mode it restores", example="AUTO")
    mv: float = described("the MV it restores, MV units", example=50.0)
    since: str = described("since when, UTC ISO 8601", example=WHEN)
    attempts: int = described("how many tries so far", example=3)
    last_error: str = described("why the last try failed", example="timeout: no answer from 192.0.2.10:502")


@dataclass(frozen=True)
class OwnerRecord:
    """The daemon of the fleet that serves a loop (holds its lease): only it tunes, applies and restores it."""

    name: str = described("the daemon's name in the fleet", example="autotuner-a")
    url: str = described("where its API answers (commands for the loop go there)", example="http://10.0.0.5:8000")
    epoch: int = described("the lease's epoch: it grows by one each time another daemon takes the loop over",
                           example=3)


FlagName = Literal["manual", "saturated", "oscillating", "stiction", "sluggish", "noisy", "frozen_pv",
                   "poor_tracking"]
Recommendation = Literal["retune", "check_valve", "check_sensor", "put_in_auto", "none"]
SeverityName = Literal["none", "low", "medium", "high"]


@dataclass(frozen=True)
class HealthSummary:
    """A loop's health in short (docs/health.md, "Online"): what the overview shows and sorts by."""

    state: Literal["ok", "pending", "off"] = described(
        "ok: assessed for the loop's current gains; pending: not enough samples yet since the start or the loop's "
        "last tuning (flags empty, reason says what it waits for); off: monitoring disabled in its config",
        example="ok")
    severity: SeverityName = described("the worst flag's severity (none without flags)", example="medium")
    rank: int = described("orders loops worst first (higher: worse): 10 × the worst severity (low 1, medium 2, "
                          "high 3) + the number of flags; 0 without flags", example=22)
    flags: list[FlagName] = described("what is wrong (empty: healthy, or not assessed)",
                                      example=["oscillating", "stiction"])
    recommendation: Recommendation = described("the one thing to do first", example="check_valve")
    reason: str = described("the worst flag's one-line reason; while pending, what it waits for; '' when healthy",
                            example="a sticking valve keeps the loop in a limit cycle")
    time: float | None = described("when the assessment was made, unix s (null: none yet)", example=1796161110.8)


@dataclass(frozen=True)
class LoopStatus:
    """A loop: the PIDAT outputs (tbsy, te, ite), the stage and progress, the last session's point and gains, and
    the live values."""

    id: str = described("loop id from the config", example="TIC-101")
    description: str = described("free text from the config", example="temperature: two lags with dead time")
    group: str | None = described("exclusion group (loops of one group never tune at the same time); null: none",
                                  example="reactor")
    link: str = described("how the daemon reaches the loop (URL; sim:PROCESS for a simulated plant)",
                          example="modbus://192.0.2.10:502/1")
    speed: float = described("plant seconds per wall second: 1 for a real plant, more for a simulated one",
                             example=1.0)
    tbsy: bool = described("TBSY: a session is running", example=False)
    te: bool = described("TE: the last session failed (no gains)", example=False)
    ite: float = described("while tbsy: estimated plant seconds left; afterwards the outcome code (GET /codes)",
                           example=0)
    stage: Literal["noise", "relay", "done"] | None = described("stage of the running or last session (null: none "
                                                                "yet)", example="done")
    progress: float = described("progress of the running session, 0–1", example=0.0)
    message: str = described("the last session's message (tuning while one runs, idle before any)", example="ok")
    session: str | None = described("id of the running or last session (null: none since the daemon started)",
                                    example=SID)
    controller: str | None = described("controller type of the last session", example="PI")
    point: PointRecord | None = described("point identified by the last session (null: none)")
    static_gain: float | None = described("static gain of the process identified by the last session, PV units per "
                                          "MV unit (null: integrating or not identified)", example=1.478)
    gains: GainsRecord | None = described("gains designed by the last session (null: none)")
    mode: Literal["MAN", "AUTO"] | None = described("the loop's mode now (MAN while a session holds it; null: not "
                                                    "read yet or the link is down)", example="AUTO")
    pv: float | None = described("process value now, PV units (null: not read yet or the link is down)",
                                 example=50.0)
    sp: float | None = described("set point now, PV units (while tuning: the SP saved before the experiment)",
                                 example=50.0)
    mv: float | None = described("manipulated value now, MV units", example=50.0)
    current_gains: GainsRecord | None = described("the gains in the controller as last read from it (monitor, end "
                                                  "of a session, apply); null until read")
    last_tuned_at: str | None = described("finish time of the newest finished session, UTC ISO 8601 (null: none)",
                                          example=WHEN)
    last_outcome: Literal["success", "failure"] | None = described("outcome of that session (null: none)",
                                                                   example="success")
    pending_gains: bool = described("idle, and the newest session succeeded with gains not applied yet",
                                    example=True)
    monitor_error: str | None = described("why the monitor cannot read the loop (null: fine)", example=None)
    history_error: str | None = described(
        "why the daemon's history cannot record now — its file (or database, password masked), since when, the "
        "database's reason, e.g. database or disk is full — the same for every loop; meanwhile a TUNE ends before "
        "it touches the loop (ite 27) and an apply is refused (503 history_unavailable); null: fine",
        example=None)
    defaults: Settings = described("the settings a TUNE without a body runs with")
    bounds: BoundsRecord = described("the loop's own bounds on a TUNE's amp and hysteresis (beside the schema's "
                                     "global ones)")
    units: UnitsRecord = described("engineering units and display of the loop's values (the config's units)")
    restore: RestoreStatus | None = described("the loop is not handed back yet (te true, ite 20, TUNE refused); "
                                              "null when it is", None)
    owner: OwnerRecord | None = described("the daemon of the fleet that serves the loop (docs/fleet.md); null "
                                          "without a fleet, or while no daemon holds the loop's lease", None)
    health: HealthSummary | None = described("the loop's health in short (GET /loops/{id}/health has it in full); "
                                             "null: not monitored by this daemon", None)

    def to_json(self) -> dict[str, Any]:
        """The status as JSON (nested records as objects, ranges as lists)."""
        return _plain(self)


def _plain(value: Any) -> Any:
    """``value`` as JSON: dataclasses as objects (field by field), tuples as lists, enums by value."""
    if is_dataclass(value) and not isinstance(value, type):
        return {name: _plain(getattr(value, name)) for name in _names(type(value))}
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    if isinstance(value, Enum):
        return value.value
    return value


@functools.cache
def _names(cls: type) -> tuple[str, ...]:
    """The field names of the dataclass ``cls`` (read once per class: ``fields`` is slow at a status per sample)."""
    return tuple(f.name for f in fields(cls))
