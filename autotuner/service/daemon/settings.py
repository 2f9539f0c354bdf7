"""The settings of one session: a TUNE request completed with the loop's defaults, and the plan it runs."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Literal

from autotuner.engine.described import described
from autotuner.engine.experiment.relay import RelayConfig
from autotuner.service.config import LoopConfig, TuneRequest
from autotuner.service.link_session import HandBack, SessionPlan
from autotuner.service.remote_tuning import field_config


@dataclass(frozen=True)
class Settings:
    """The settings of one session (the request completed with the loop's defaults); recorded in the history as
    ``request``, and a loop's ``defaults`` in its status (what a TUNE without a body runs with)."""

    controller: Literal["PI", "PID"] = described("controller type designed", example="PI")
    amp: float = described("relay amplitude, MV units", example=5.0)
    hysteresis: float | None = described("relay hysteresis, PV units (null: 3σ of the noise measured first)",
                                         example=None)
    phase: float = described("phase lag of the point to identify, degrees (90–170)", example=135.0)
    ms: float = described("maximum sensitivity Ms the design aims at (1.05–4)", example=1.4)
    apply: bool = described("whether the gains are written to the controller on success", example=False)

    def as_json(self) -> dict[str, Any]:
        """The settings as recorded in the history (``request``)."""
        return asdict(self)


def settings_of(loop: LoopConfig, request: TuneRequest) -> Settings:
    """``request`` completed with the defaults of ``loop``."""
    d = loop.tuning
    return Settings(
        controller=request.controller or d.controller,
        amp=request.amp if request.amp is not None else d.amp,
        hysteresis=request.hysteresis if request.hysteresis is not None else d.hysteresis,
        phase=request.phase if request.phase is not None else d.phase,
        ms=request.ms if request.ms is not None else d.ms,
        apply=request.apply if request.apply is not None else loop.apply,
    )


def relay_config(loop: LoopConfig, settings: Settings) -> RelayConfig:
    """The experiment's settings with the loop's safety limits and the field tolerances."""
    return field_config(RelayConfig(
        amp=settings.amp, phase_deg=settings.phase, hysteresis=settings.hysteresis,
        pv_limits=loop.limits.pv, mv_limits=loop.limits.mv, time_limit=loop.tuning.time_limit,
    ))


def plan_of(loop: LoopConfig, settings: Settings, handback: HandBack | None = None) -> SessionPlan:
    """The session ``settings`` make on ``loop``: its experiment, sample time and speed, handed back as
    ``handback`` says (None: the defaults)."""
    return SessionPlan(relay_config(loop, settings), loop.ts, settings.controller, settings.ms, settings.apply,
                       loop.speed, HandBack() if handback is None else handback)
