"""Response bodies of the API (they make the OpenAPI description; the request body is autotuner.config.TuneRequest).

Units: ``ite`` plant seconds left while busy, the code when done; ``point.omega``
rad/s, ``phase_deg`` degrees (negative for lag); gains in the standard (ISA)
form, times in seconds; ``t`` of a trace in plant seconds.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel


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


class LoopStatus(BaseModel):
    """A loop: the PIDAT outputs (tbsy, te, ite), the stage and progress (0–1), and the last point and gains."""

    id: str
    description: str
    group: str | None
    link: str
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


class Accepted(BaseModel):
    """A TUNE or TBRK accepted for ``loop``; ``session`` is the session's id (``GET /sessions/{sid}``)."""

    loop: str
    session: str


class SessionSummary(BaseModel):
    """One session as listed in a loop's history.

    state: running, finished, or interrupted (the daemon stopped during it);
    outcome: success or failure; code: the final ``ite``; request: the
    settings in force; saved: the loop's state before the experiment.
    """

    id: str
    loop: str
    user: str
    started_at: str
    finished_at: str | None
    state: Literal["running", "finished", "interrupted"]
    request: dict[str, Any]
    saved: dict[str, Any] | None
    gains_before: GainsOut | None
    gains_after: GainsOut | None
    outcome: Literal["success", "failure"] | None
    code: int | None
    message: str | None
    result: dict[str, Any] | None


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
