"""Response bodies of the API (they make the OpenAPI description; the request body is autotuner.service.config.TuneRequest).

Units: ``ite`` plant seconds left while busy, the code when done; ``point.omega``
rad/s, ``phase_deg`` degrees (negative for lag); gains in the standard (ISA)
form, times in seconds; ``t`` of a trace in plant seconds; times of day
(``last_tuned_at``, ``applied_at``, ...) UTC ISO 8601; ``time`` of an event
unix seconds (wall clock). Every field carries its description, unit and an
example (taken from the demo's TIC-101) into the OpenAPI document.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from autotuner.engine.described import described
from autotuner.engine.health.indices import Indices
from autotuner.engine.result import GainsRecord, PointRecord, ResultRecord
from autotuner.service.daemon.status import (FlagName, HealthSummary, LoopStatus, OwnerRecord, Recommendation,
                                             RestoreStatus, UnitsRecord)

__all__ = ["HealthSummary", "LoopStatus", "OwnerRecord", "RestoreStatus", "UnitsRecord"]  # the loop's status: the daemon's own record

SID = "3f2c9a7e5b1d4c6a8e0f2b4d6a8c0e1f"
WHEN = "2026-12-01T20:57:36.412Z"


def _f(description: str, example: Any) -> Any:
    """A required field with its description (unit included) and one example."""
    return Field(description=description, examples=[example])


def _d(description: str) -> Any:
    """A required field holding a model (or null): its description; the example comes from the model's fields."""
    return Field(description=description)


class CodeOut(BaseModel):
    """One outcome code: what ``ite`` shows once a session has ended."""

    value: int = _f("the code (ite after the end; TE true unless it is 0 or a warning)", 3)
    name: str = _f("its name in autotuner/engine/outcome.py", "NO_OSCILLATION")
    message: str = _f("what it means, for people", "no oscillation: the relay did not make the PV cross the set "
                      "point repeatedly")
    warning: bool = _f("reported with TE false: the gains are usable but a target was missed", False)


class Whoami(BaseModel):
    """The caller's token."""

    name: str = _f("the token's name (recorded in the history as the user)", "hmi")
    role: Literal["viewer", "operator", "admin"] = _f("what it may do: viewer reads, operator also TUNE/TBRK/apply",
                                                      "operator")


class DaemonMember(BaseModel):
    """A daemon of the fleet alive now."""

    name: str = _f("its name", "autotuner-a")
    url: str = _f("where its API answers", "http://10.0.0.5:8000")
    draining: bool = _f("drained: it serves no new loop", False)


class FleetStatus(BaseModel):
    """The fleet as this daemon sees it (docs/fleet.md)."""

    daemon: str | None = _f("this daemon's name (null: no fleet, an SQLite history)", "autotuner-a")
    draining: bool = _f("this daemon is drained", False)
    members: list[DaemonMember] = _d("the daemons alive now (seen within a lease time)")
    loops: dict[str, OwnerRecord | None] = _d("who serves each loop (null: nobody holds its lease now)")


class DrainRequest(BaseModel):
    """Body of ``POST /fleet/drain``."""

    model_config = ConfigDict(extra="forbid")

    drain: bool = Field(description="true: drain this daemon (its loops go to the others); false: serve again",
                        examples=[True])


class Accepted(BaseModel):
    """A TUNE or TBRK accepted."""

    loop: str = _f("loop id", "TIC-101")
    session: str = _f("the session's id (GET /sessions/{sid})", SID)


class SessionSummary(BaseModel):
    """One session as listed in a loop's history."""

    id: str = _f("session id", SID)
    seq: int = _f("its place in the history's order, assigned by the database when it was recorded: a later "
                  "session has a larger one, whatever the clocks said (newest first, the last outcome and apply's "
                  "default follow it; the times are for display)", 42)
    loop: str = _f("loop id", "TIC-101")
    user: str = _f("name of the token that started it (plc: the device's TUNE bit)", "hmi")
    started_at: str = _f("when it was requested, UTC ISO 8601", WHEN)
    finished_at: str | None = _f("when it ended, UTC ISO 8601 (null: running)", WHEN)
    state: Literal["running", "finished", "interrupted", "not_restored"] = _f(
        "running; finished; interrupted: the daemon stopped during it (closed on restart, the loop put back); "
        "not_restored: the loop is not handed back yet", "finished")
    request: dict[str, Any] = _f("the settings in force (the request completed with the loop's defaults)",
                                 {"controller": "PI", "amp": 5.0, "hysteresis": None, "phase": 135.0, "ms": 1.4,
                                  "apply": False})
    saved: dict[str, Any] | None = _f("the loop's state before the experiment: mode, MV (MV units), SP (PV units), "
                                      "gains (null: not read)", {"mode": "AUTO", "mv": 50.0, "sp": 50.0})
    gains_before: GainsRecord | None = _d("the controller's gains before the session")
    gains_after: GainsRecord | None = _d("the gains read back after the session or the last apply")
    outcome: Literal["success", "failure"] | None = _f("success (gains designed) or failure (null: running)",
                                                       "success")
    code: int | None = _f("the outcome code, the final ite (GET /codes); null: running", 0)
    message: str | None = _f("what happened, for people", "ok")
    result: ResultRecord | None = _d("the result object of docs/design.md (null: running)")
    applied_at: str | None = _f("when its gains were last written to the controller, UTC ISO 8601 (null: never)",
                                None)
    applied_by: str | None = _f("who wrote them (a token's name)", None)
    gains_intent: dict[str, Any] | None = Field(None, description="a gains write recorded as intended whose outcome "
                                                "is not recorded yet ({gains, by, at}; a restart reconciles it with "
                                                "the device), else null", examples=[None])


class TraceOut(BaseModel):
    """The experiment's samples (the whole experiment up to 8000 samples, evenly thinned past that)."""

    t: list[float] = _f("plant seconds since the session started", [0.0, 0.25, 0.5])
    pv: list[float] = _f("process value, PV units", [50.0, 50.01, 50.03])
    mv: list[float] = _f("manipulated value, MV units", [55.0, 55.0, 55.0])


class Session(SessionSummary):
    """One session in full, with its trace."""

    trace: TraceOut | None = _d("the experiment's samples (null: none recorded)")


class Health(BaseModel):
    """The daemon is up."""

    status: Literal["ok"] = _f("always ok", "ok")
    loops: int = _f("how many loops it owns", 3)


class ApplyRequest(BaseModel):
    """Body of ``POST /loops/{id}/apply`` (optional)."""

    model_config = ConfigDict(extra="forbid")

    session: str | None = Field(None, description="the session whose designed gains to write (absent or null: the "
                                "loop's newest finished session)", examples=[SID])


class Applied(BaseModel):
    """Gains written to the controller."""

    loop: str = _f("loop id", "TIC-101")
    session: str = _f("the session whose gains were written", SID)
    gains: GainsRecord = _d("the gains as read back from the controller")


@dataclass(frozen=True)
class AnalysisPoint(PointRecord):
    """The identified point with its real and imaginary parts."""

    re: float = field(metadata={"description": "Re F(jω₀), PV units per MV unit", "examples": [-0.279]})
    im: float = field(metadata={"description": "Im F(jω₀), PV units per MV unit", "examples": [-0.279]})


class Model(BaseModel):
    """The model the design fitted: FOPDT k·e^(−l·s)/(t·s + 1) or IPDT k·e^(−l·s)/s."""

    kind: Literal["FOPDT", "IPDT"] = _f("model family", "FOPDT")
    k: float = _f("gain: PV units per MV unit (FOPDT), per MV unit and second (IPDT)", 1.5)
    t: float = _f("time constant, seconds (0 for IPDT)", 8.76)
    l: float = _f("dead time, seconds", 2.52)  # noqa: E741 (the dead time's usual name)
    text: str = _f("the model in the process expression grammar", "1.5*exp(-2.517*s)/(8.76*s+1)")


class Circle(BaseModel):
    """The Ms circle in the Nyquist plane: |1 + L| = 1/Ms around −1."""

    center_re: float = _f("real part of its centre (−1), dimensionless", -1.0)
    radius: float = _f("radius 1/Ms, dimensionless", 0.714)


class Nyquist(BaseModel):
    """L(jω) = C(jω)·F(jω) on the model."""

    omega: list[float] = _f("frequencies, rad/s, increasing", [0.01, 0.1, 1.0])
    re: list[float] = _f("Re L(jω), dimensionless", [-0.9, -0.5, -0.05])
    im: list[float] = _f("Im L(jω), dimensionless", [-40.0, -3.1, -0.2])


class Complex(BaseModel):
    """A point of the Nyquist plane."""

    re: float = _f("real part, dimensionless", -0.6)
    im: float = _f("imaginary part, dimensionless", -0.35)


class ParallelForm(BaseModel):
    """The gains in the parallel form Kp + Ki/s + Kd·s."""

    kp: float = _f("Kp, MV units per PV unit", 0.8)
    ki: float = _f("Ki, MV units per PV unit and second", 0.09)
    kd: float = _f("Kd, MV units × seconds per PV unit", 0.0)


class SeriesForm(BaseModel):
    """The gains in the series (interacting) form K′(1 + 1/(Ti′·s))(1 + Td′·s)."""

    k: float = _f("K′, MV units per PV unit", 0.8)
    ti: float | None = _f("Ti′, seconds (null: no integral action)", 8.8)
    td: float = _f("Td′, seconds", 0.0)


class Forms(BaseModel):
    """The same gains in the parallel and series forms (autotuner/engine/control/gains.py)."""

    parallel: ParallelForm = _d("the parallel form")
    series: SeriesForm | None = _d("the series form (null: none exists, Ti < 4·Td)")
    series_reason: str | None = Field(None, description="why there is no series form (absent when there is one)")


class StepOut(BaseModel):
    """A simulated unit step response of the closed loop on the model."""

    t: list[float] = _f("plant seconds after the step", [0.0, 1.0, 2.0])
    pv: list[float] = _f("process value, PV units per unit step", [0.0, 0.02, 0.1])
    mv: list[float] = _f("manipulated value, MV units per unit step", [0.25, 0.3, 0.4])


class LoopResponse(BaseModel):
    """What one set of gains does on the model."""

    gains: GainsRecord = _d("the gains analysed")
    forms: Forms = _d("the gains in the parallel and series forms")
    ms: float | None = _f("maximum sensitivity reached, dimensionless (null: the closed loop is unstable)", 1.4)
    stable: bool = _f("whether the closed loop is stable on the model", True)
    nyquist: Nyquist = _d("open loop L(jω)")
    at_point: Complex = _d("L(jω₀) = C(jω₀)·F(jω₀): the controller times the identified point")
    setpoint: StepOut = _d("unit set-point step")
    load: StepOut = _d("unit load step at the process input (an unstable loop's steps are clipped)")


class Analysis(BaseModel):
    """What a session's gains (new) and the controller's gains before it (old) do on the identified model."""

    session: str = _f("session id", SID)
    loop: str = _f("loop id", "TIC-101")
    controller: str | None = _f("controller type", "PI")
    ms_target: float = _f("the Ms the design aimed at", 1.4)
    point: AnalysisPoint = _d("the identified point")
    model: Model = _d("the model fitted through the point")
    ms_circle: Circle = _d("the Ms circle")
    old: LoopResponse | None = _d("the gains before (null: not known)")
    new: LoopResponse = _d("the designed gains")


@dataclass(frozen=True)
class LoopHealthRow(HealthSummary):
    """One loop in the health list (``GET /loop-health``): its id and description with its health summary."""

    loop: str = described("loop id", example="TIC-102")
    description: str = described("free text from the config", example="temperature loop with a sticky valve")


class HealthWindow(BaseModel):
    """The window an assessment read."""

    start: float = _f("its first sample, plant s (the loop's record clock)", 120.0)
    end: float = _f("its last sample, plant s", 3719.0)
    samples: int = _f("samples assessed (on an even grid)", 3600)
    ts: float = _f("the grid's sample time, plant s", 1.0)


class AssessmentOut(BaseModel):
    """One health assessment (the engine's ``Assessment.to_json()``, docs/health.md) and when it was made."""

    flags: list[FlagName] = _f("what is wrong (empty: healthy)", ["oscillating", "stiction"])
    recommendation: Recommendation = _f("the one thing to do first", "check_valve")
    reasons: dict[str, str] = _f("each flag's one-line reason", {"stiction": "a sticking valve keeps the loop in a "
                                                                 "limit cycle"})
    severities: dict[str, Literal["low", "medium", "high"]] = _f("each flag's severity", {"stiction": "medium"})
    indices: Indices = _d("every index, with its unit (docs/health.md, \"The indices\"); null where not computed")
    dead_time_source: Literal["model", "one sample"] | None = _f(
        "the dead time the Harris index used: the newest successful tuning's model, or one sample (no model: the "
        "index a lower bound); null: no index", "model")
    window: HealthWindow = _d("the window assessed")
    time: float = _f("when it was made, unix s", 1796161110.8)


class BeforeTuning(AssessmentOut):
    """The last assessment made before the loop's newest tuning session started."""

    session: str = _f("that tuning session's id", SID)


class HealthEvidence(BaseModel):
    """The assessed window's samples (downsampled by the server to at most 1000 points) and the oscillation
    found in it: what the page draws, computing nothing."""

    t: list[float] = _f("plant seconds from the window's start", [0.0, 1.0, 2.0])
    sp: list[float] = _f("set point, PV units", [50.0, 50.0, 50.0])
    pv: list[float] = _f("process value, PV units", [50.2, 50.6, 50.9])
    mv: list[float] = _f("controller output, MV units", [48.0, 48.0, 47.1])
    crossings: list[float] = _f("the control error's zero crossings the oscillation detector counted, plant s "
                                "from the window's start", [12.0, 75.5, 141.0])
    period: float | None = _f("the oscillation's mean period, s (null: none found)", 128.6)
    amplitude: float | None = _f("its mean amplitude, PV units (null: none found)", 0.87)


class LoopHealthDetail(BaseModel):
    """A loop's health in full (``GET /loops/{id}/health``)."""

    loop: str = _f("loop id", "TIC-102")
    state: Literal["ok", "pending", "off"] = _f("ok: assessed for the current gains; pending: collecting samples "
                                                "since the start or the last tuning; off: disabled", "ok")
    severity: Literal["none", "low", "medium", "high"] = _f("the worst flag's severity", "low")
    rank: int = _f("orders loops worst first (higher: worse), as in the summary", 12)
    reason: str = _f("the worst flag's reason; while pending, what it waits for", "a sticking valve ...")
    assessment: AssessmentOut | None = _d("the newest assessment for the current gains (null: pending or off)")
    window_setting: float = _f("the configured window, plant s", 3600.0)
    before_tuning: BeforeTuning | None = _d("the last assessment before the loop's newest tuning (null: none)")
    evidence: HealthEvidence | None = _d("the assessed window's samples and oscillation (null: no assessment)")


class HealthHistoryItem(BaseModel):
    """One stored assessment of a loop (``GET /loops/{id}/health/history``)."""

    time: float = _f("when it was made, unix s", 1796161110.8)
    state: Literal["ok"] = _f("always ok (only assessments are stored)", "ok")
    severity: Literal["none", "low", "medium", "high"] = _f("its worst flag's severity", "low")
    flags: list[FlagName] = _f("its flags", ["oscillating", "stiction"])
    recommendation: Recommendation = _f("its recommendation", "check_valve")
    session: str | None = _f("the newest tuning session before it (null: none)", SID)
