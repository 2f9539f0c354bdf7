"""The result of a tuning: what the session holds (:class:`TuneResult`) and its record (:class:`ResultRecord`).

A :class:`TuneResult` carries everything the experiment and the design
produced (the identification, the design with its model family, the trace).
Its record is the result object of design.md — the JSON of ``autotuner tune``,
the daemon's loop status and history, the REST sessions: :meth:`ResultRecord.of`
is the one way from a result to a record, :meth:`ResultRecord.to_json` and
:meth:`ResultRecord.from_json` the one encoder and decoder. The record's
dataclasses describe each field (unit included) in ``metadata``, which the
API's response models (pydantic, at the boundary only) read as they are.

Units: ``omega`` rad/s of plant time; ``phase_deg`` degrees, negative for
lag; gains in the standard (ISA) form with times in seconds; ``duration``
plant seconds.
"""

import cmath
import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from autotuner.engine.control.gains import Gains, forms_json
from autotuner.engine.described import described
from autotuner.engine.design.point_design import Design
from autotuner.engine.experiment.point import Point
from autotuner.engine.experiment.relay import Identification
from autotuner.engine.outcome import Code, is_failure


def _f(description: str, example: Any) -> Any:
    """A field's description (unit included) and one example (the demo's TIC-101)."""
    return described(description, example=example)


def _o(description: str) -> Any:
    """An optional field (absent in records written before it existed): null by default."""
    return described(description, None)


@dataclass(frozen=True)
class Trace:
    """Recorded samples: times (s), PV, and the MV held from each sample on."""

    t: np.ndarray = described("sample times, plant seconds")
    pv: np.ndarray = described("PV at each sample, PV units")
    mv: np.ndarray = described("MV held from each sample on, MV units")

    def thinned(self, points: int) -> dict[str, list[float]]:
        """At most ``points`` evenly spaced samples (plant seconds, PV, MV) as lists, the last one included."""
        n = len(self.t)
        index = np.unique(np.linspace(0, n - 1, min(n, points)).round().astype(int)) if n else np.zeros(0, int)
        return {name: [float(x) for x in getattr(self, name)[index]] for name in ("t", "pv", "mv")}


@dataclass(frozen=True)
class TuneResult:
    """Outcome of one tuning; ``code`` is 0 on success, otherwise the error code shown in ``ite``."""

    code: Code = described("outcome, the value ite shows once the tuning has ended")
    message: str = described("what happened, for people ('ok', or why not)")
    controller: str = described("controller type designed: PI or PID")
    identification: Identification | None = described(
        "what the experiment identified (point, static gain, length); None if nothing")
    design: Design | None = described(
        "gains with the model they were designed on, Ms there and notes; None if none")
    trace: Trace = described("the experiment's samples")

    @classmethod
    def failed(cls, code: Code, message: str, controller: str) -> "TuneResult":
        """A tuning that ended before anything was identified (no point, no gains, no samples).

        ``code``, ``message``: how it ended; ``controller``: the controller type asked for.
        """
        return cls(code, message, controller, None, None, Trace(np.zeros(0), np.zeros(0), np.zeros(0)))

    @property
    def ok(self) -> bool:
        """True when gains were computed (``te`` false): code OK, or a warning that says what was missed."""
        return not is_failure(self.code) and self.design is not None

    def record(self) -> "ResultRecord":
        """The result's record (the result object of design.md)."""
        return ResultRecord.of(self)

    def as_json(self) -> dict[str, Any]:
        """The result object of design.md as JSON."""
        return self.record().to_json()


@dataclass(frozen=True)
class PointRecord:
    """The identified point F(jω₀) of the process."""

    omega: float = _f("frequency ω₀ of the point, rad/s (plant time)", 0.4187)
    gain: float = _f("|F(jω₀)|, PV units per MV unit", 0.3941)
    phase_deg: float = _f("∠F(jω₀), degrees (negative: lag)", -135.1)

    @classmethod
    def of(cls, point: Point) -> "PointRecord":
        """The record of an identified point.

        ``point``: the point.
        """
        return cls(float(point.omega), float(point.gain), float(point.phase_deg))

    def point(self) -> Point:
        """The point as the design takes it (a complex F(jω₀))."""
        return Point(self.omega, cmath.rect(self.gain, math.radians(self.phase_deg)))


@dataclass(frozen=True)
class GainsRecord:
    """PID gains in the standard (ISA) form K·(b·SP − PV + (1/(Ti·s))·e + Td·s/(1 + Td·s/N)·(c·SP − PV)), named
    as the block's outputs."""

    pk: float = _f("proportional gain K, MV units per PV unit", 0.6865)
    pti: float | None = _f("integral time Ti, seconds (null: no integral action)", 5.776)
    ptd: float = _f("derivative time Td, seconds (0: PI)", 0.0)
    pnd: float = _f("derivative filter N (Td/N is the filter's time constant), dimensionless", 10.0)
    pb: float = _f("set-point weight b of the proportional part, dimensionless (0–1)", 0.365)
    pc: float = _f("set-point weight c of the derivative part, dimensionless (0–1)", 0.0)

    @classmethod
    def of(cls, gains: Gains) -> "GainsRecord":
        """The record of gains (``pti`` null without integral action).

        ``gains``: the gains.
        """
        return cls(**gains.as_json())

    def gains(self) -> Gains:
        """The gains as the engine computes with them."""
        return Gains.from_json(asdict(self))


@dataclass(frozen=True)
class DesignRecord:
    """What the gains were designed on and what they achieve there."""

    model: str = _f("the model the design used, as a process expression (plant seconds)",
                    "0.974*exp(-3.6*s)/(1+3.26*s)")
    ms_model: float = _f("maximum sensitivity Ms of the gains on that model", 1.40)
    ms_target: float = _f("the Ms the gains were designed for (the requested one, or raised for an unstable "
                          "process)", 1.4)
    noise_gain: float = _f("MV noise per PV noise of the controller (its high-frequency gain), MV units per PV unit",
                           0.69)
    notes: tuple[str, ...] = _f("one sentence per target missed or action given up (empty: everything met)", [])

    @classmethod
    def of(cls, des: Design) -> "DesignRecord":
        """The record of a design.

        ``des``: the design.
        """
        return cls(str(des.model), float(des.model_ms), float(des.ms_target), float(des.noise_gain),
                   tuple(des.notes))


@dataclass(frozen=True)
class ExperimentRecord:
    """How long the experiment ran."""

    duration: float = _f("from the first sample to the end, plant seconds", 96.0)
    periods: float | None = _f("the duration in oscillation periods (null: nothing identified)", 6.5)
    samples: int = _f("samples taken", 384)
    phase_target_deg: float | None = _o("the process phase lag the experiment aimed at, degrees: the requested one, "
                                        "or a reachable one when the requested phase was out of reach of an "
                                        "unstable process (null: nothing identified)")
    phase_moved: bool | None = _o("true when the phase target was moved from the requested one (null: nothing "
                                  "identified)")
    disturbance: bool | None = _o("true when a load step, a drift or a PV still settling at the start was "
                                  "detected and the static gain estimated through it (null: nothing identified)")
    load_estimate: float | None = _o("the load at the process input at the end relative to the start, MV units, "
                                     "as the experiment estimated and followed it (0: none; null: nothing "
                                     "identified)")


@dataclass(frozen=True)
class ResultRecord:
    """The result object of design.md: the PIDAT outputs at the end, what was identified and the gains."""

    tbsy: bool = _f("TBSY: always false in a result (the session has ended)", False)
    te: bool = _f("TE: true when no gains were designed (the code says why)", False)
    ite: int = _f("the outcome code (GET /codes): 0 ok, a warning with gains, or an error", 0)
    message: str = _f("what happened, for people", "ok")
    controller: str = _f("controller type designed: PI or PID", "PI")
    point: PointRecord | None = described("the identified point (null: none)")
    static_gain: float | None = _f("static gain of the process, PV units per MV unit (null: integrating or not "
                                   "identified)", 1.478)
    gains: GainsRecord | None = described("the designed gains (null: none)")
    experiment: ExperimentRecord = described("how long the experiment ran")
    design: DesignRecord | None = _o("the model the gains were designed on, Ms there and the notes (null: no gains, "
                                     "or a record written before this key existed)")
    forms: dict[str, Any] | None = _o("the gains in parallel {kp, ki, kd} and series {k, ti, td} form (series null "
                                      "with series_reason when it does not exist); null: no gains")

    @classmethod
    def of(cls, result: TuneResult) -> "ResultRecord":
        """The record of a tuning's result.

        ``result``: the result.
        """
        ident, des, t = result.identification, result.design, result.trace.t
        return cls(
            tbsy=False, te=not result.ok, ite=int(result.code), message=result.message,
            controller=result.controller,
            point=None if ident is None else PointRecord.of(ident.point),
            static_gain=None if ident is None or math.isinf(ident.static_gain) else float(ident.static_gain),
            gains=None if des is None else GainsRecord.of(des.gains),
            experiment=ExperimentRecord(float(t[-1] - t[0]) if len(t) else 0.0,
                                        None if ident is None else round(ident.periods, 2), len(t),
                                        None if ident is None else float(ident.phase_target_deg),
                                        None if ident is None else bool(ident.phase_moved),
                                        None if ident is None else bool(ident.disturbance),
                                        None if ident is None else float(ident.load_estimate)),
            design=None if des is None else DesignRecord.of(des),
            forms=None if des is None else forms_json(des.gains),
        )

    def to_json(self) -> dict[str, Any]:
        """The record as JSON (keys as in design.md; ``notes`` a list)."""
        out = asdict(self)
        if out["design"] is not None:
            out["design"]["notes"] = list(out["design"]["notes"])
        return out

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "ResultRecord":
        """The record of a result's JSON (keys added since a row was stored are null). Raises ValueError
        naming what is missing or wrong.

        ``d``: the JSON object.
        """
        try:
            point, gains, design, experiment = d["point"], d["gains"], d.get("design"), d["experiment"]
            return cls(
                tbsy=bool(d["tbsy"]), te=bool(d["te"]), ite=int(d["ite"]), message=str(d["message"]),
                controller=str(d["controller"]),
                point=None if point is None else PointRecord(**point),
                static_gain=None if d["static_gain"] is None else float(d["static_gain"]),
                gains=None if gains is None else GainsRecord(**gains),
                experiment=ExperimentRecord(**experiment),
                design=None if design is None else DesignRecord(**{**design, "notes": tuple(design["notes"])}),
                forms=d.get("forms"),
            )
        except (KeyError, TypeError) as exc:
            raise ValueError(f"not a result record: {type(exc).__name__} {exc}") from exc

    @property
    def code(self) -> Code:
        """The outcome code (``ite``)."""
        return Code(self.ite)
