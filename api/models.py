"""Response bodies of the API (they make the OpenAPI description; the request body is autotuner.service.config.TuneRequest).

Pydantic lives here, at the boundary: the result inside is the engine's ``TuneResult`` and its one
encoder ``as_json``; tests/test_result_types.py checks these models against the keys it gives.

Units: ``ite`` plant seconds left while busy, the code when done; ``point.omega``
rad/s, ``phase_deg`` degrees (negative for lag); gains in the standard (ISA)
form, times in seconds; ``t`` of a trace in plant seconds; times of day
(``last_tuned_at``, ``applied_at``, ...) UTC ISO 8601; ``time`` of an event
unix seconds (wall clock).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict


class Point(BaseModel):
    """The identified point F(jω)."""

    omega: float
    gain: float
    phase_deg: float


class GainsOut(BaseModel):
    """PID gains, standard form: pk, pti (null: no integral), ptd, pnd, pb, pc."""

    pk: float
    pti: float | None
    ptd: float
    pnd: float
    pb: float
    pc: float


class TuneDefaults(BaseModel):
    """What a TUNE without a body runs: the loop's configured controller, relay amplitude (MV units), hysteresis
    (PV units; null: measured from the noise), phase lag (degrees), Ms, and whether the gains are applied."""

    controller: Literal["PI", "PID"]
    amp: float
    hysteresis: float | None
    phase: float
    ms: float
    apply: bool


class CodeOut(BaseModel):
    """One outcome code: ``value`` is what ``ite`` shows when a session has ended; ``warning``: reported with
    ``te`` false (gains usable, a target missed)."""

    value: int
    name: str
    message: str
    warning: bool


class Whoami(BaseModel):
    """The caller: the token's name (recorded in the history as the user) and its role."""

    name: str
    role: Literal["viewer", "operator", "admin"]


class RestoreStatus(BaseModel):
    """A loop the daemon could not hand back yet (``ite`` 20): the session, the mode and MV it restores, since when
    (UTC), how many tries so far and why the last one failed; retried with back-off (docs/handback.md)."""

    session: str
    mode: Literal["MAN", "AUTO"]
    mv: float
    since: str
    attempts: int
    last_error: str


class LoopStatus(BaseModel):
    """A loop: the PIDAT outputs (tbsy, te, ite), the stage and progress (0–1), the last point and gains, and
    the live values.

    mode, pv, sp, mv: the loop now (engineering units; null: not read yet or
    link down) — from the monitor while idle, from the session while tuning
    (SP: the saved one, mode MAN). current_gains: the controller's gains as
    last read. last_tuned_at, last_outcome: the newest finished session.
    pending_gains: idle, and that session succeeded with gains not applied.
    monitor_error: why the monitor cannot read the loop, null when fine.
    defaults: the settings a TUNE without a body runs with.
    restore: the loop is not handed back yet (te true, ite 20, TUNE refused), null when it is.
    """

    id: str
    description: str
    group: str | None
    link: str
    speed: float
    tbsy: bool
    te: bool
    ite: float
    stage: Literal["noise", "relay", "done"] | None
    progress: float
    message: str
    session: str | None
    controller: str | None
    point: Point | None
    static_gain: float | None
    gains: GainsOut | None
    mode: Literal["MAN", "AUTO"] | None
    pv: float | None
    sp: float | None
    mv: float | None
    current_gains: GainsOut | None
    last_tuned_at: str | None
    last_outcome: Literal["success", "failure"] | None
    pending_gains: bool
    monitor_error: str | None
    defaults: TuneDefaults
    restore: RestoreStatus | None = None


class Accepted(BaseModel):
    """A TUNE or TBRK accepted for ``loop``; ``session`` is the session's id (``GET /sessions/{sid}``)."""

    loop: str
    session: str


class SessionSummary(BaseModel):
    """One session as listed in a loop's history.

    state: running, finished, or interrupted (the daemon stopped during it);
    outcome: success or failure; code: the final ``ite``; request: the
    settings in force; saved: the loop's state before the experiment;
    applied_at, applied_by: when and by whom its gains were last written to
    the controller (at its end with ``apply``, or ``POST /loops/{id}/apply``),
    null if never; gains_after then the gains read back. gains_intent: a
    gains write recorded as intended whose outcome is not recorded yet
    (``{"gains", "by", "at"}``; a restart reconciles it with the device), else null.
    """

    id: str
    loop: str
    user: str
    started_at: str
    finished_at: str | None
    state: Literal["running", "finished", "interrupted", "not_restored"]
    request: dict[str, Any]
    saved: dict[str, Any] | None
    gains_before: GainsOut | None
    gains_after: GainsOut | None
    outcome: Literal["success", "failure"] | None
    code: int | None
    message: str | None
    result: dict[str, Any] | None
    applied_at: str | None
    applied_by: str | None
    gains_intent: dict[str, Any] | None = None


class TraceOut(BaseModel):
    """Downsampled samples: t (plant seconds from the session's start), PV and MV."""

    t: list[float]
    pv: list[float]
    mv: list[float]


class Session(SessionSummary):
    """One session in full, with its downsampled trace."""

    trace: TraceOut | None


class Health(BaseModel):
    """The daemon is up; how many loops it owns."""

    status: Literal["ok"]
    loops: int


class ApplyRequest(BaseModel):
    """Body of ``POST /loops/{id}/apply`` (optional): the session whose gains to write; absent: the newest."""

    model_config = ConfigDict(extra="forbid")

    session: str | None = None


class Applied(BaseModel):
    """Gains of ``session`` written to ``loop``; ``gains``: as read back from the controller."""

    loop: str
    session: str
    gains: GainsOut


class AnalysisPoint(Point):
    """The identified point with its real and imaginary parts (PV units per MV unit)."""

    re: float
    im: float


class Model(BaseModel):
    """The model the design fitted: FOPDT ``k·e^{−ls}/(ts + 1)`` (k PV/MV) or IPDT ``k·e^{−ls}/s`` (k PV/MV per
    second, t = 0); t and l in seconds; text in the expression grammar."""

    kind: Literal["FOPDT", "IPDT"]
    k: float
    t: float
    l: float  # noqa: E741 (the dead time's usual name)
    text: str


class Circle(BaseModel):
    """The Ms circle in the Nyquist plane: |1 + L| = 1/Ms around −1."""

    center_re: float
    radius: float


class Nyquist(BaseModel):
    """L(jω) = C(jω)·F(jω) on the model; omega rad/s, increasing."""

    omega: list[float]
    re: list[float]
    im: list[float]


class StepOut(BaseModel):
    """A simulated step response: t plant seconds, PV, MV."""

    t: list[float]
    pv: list[float]
    mv: list[float]


class LoopResponse(BaseModel):
    """Gains on the model: Ms (null if the closed loop is unstable), stability, Nyquist curve, and the unit
    set-point and unit load (process input) steps; an unstable loop's steps are clipped."""

    gains: GainsOut
    ms: float | None
    stable: bool
    nyquist: Nyquist
    setpoint: StepOut
    load: StepOut


class Analysis(BaseModel):
    """What a session's gains (new) and the controller's before it (old, null if unknown) do on the model."""

    session: str
    loop: str
    controller: str | None
    ms_target: float
    point: AnalysisPoint
    model: Model
    ms_circle: Circle
    old: LoopResponse | None
    new: LoopResponse
