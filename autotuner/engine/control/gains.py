"""PID controller parameters and conversions between the three usual forms.

The project reports gains in the standard (ISA, non-interacting) form

    U = K [ b W − Y + E/(Ti s) + Td s/(Td s/N + 1) · (c W − Y) ],   E = W − Y

(methods.md §3.1). Times are in seconds, K in MV units per PV unit.

Conventions chosen here:

* No integral action is written ``ti = math.inf`` (never ``0``: a zero integral
  time would mean infinite integral gain). In JSON it is ``"pti": null``.
* No derivative action is ``td = 0``.
* ``k`` must be finite and non-zero; a negative ``k`` is accepted (some rules
  return it for processes with negative static gain), but the usual way to
  reverse the action is the ``reverse`` (RACT) flag of the PID unit.
* A pure integral ("I") controller is not a set of standard-form gains (its
  proportional term would have to vanish while K/Ti stays finite). It is a
  *kind* of :class:`autotuner.engine.control.pid.PidUnit` that uses these same gains with only
  the integral term, integral gain ``k/ti``.
* The series form here is the ideal interacting form
  ``K'(1 + 1/(Ti' s))(1 + Td' s)``; the derivative filter ``N`` and the weights
  ``b, c`` do not take part in the conversion and are carried separately.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from autotuner.engine.checks import finite, real

__all__ = [
    "FormError",
    "Gains",
    "SeriesGains",
    "ParallelGains",
    "to_series",
    "from_series",
    "to_parallel",
    "from_parallel",
]

# Relative slack on the Ti ≥ 4·Td condition: a series controller with
# Ti' = Td' maps to exactly Ti = 4·Td, which rounding may put a hair below.
_SERIES_TOL = 1e-12


class FormError(ValueError):
    """A controller cannot be expressed in the requested form."""


def _nonzero(name: str, value: Any) -> float:
    x = finite(name, value)
    if x == 0.0:
        raise ValueError(f"{name} must be non-zero")
    return x


def _integral_time(name: str, value: Any) -> float:
    x = real(name, value)
    if math.isnan(x) or x <= 0.0:
        raise ValueError(
            f"{name} must be > 0 seconds (use math.inf for no integral action), got {x}"
        )
    return x


def _nonneg_finite(name: str, value: Any) -> float:
    x = finite(name, value)
    if x < 0.0:
        raise ValueError(f"{name} must be >= 0, got {x}")
    return x


def _positive_finite(name: str, value: Any) -> float:
    x = finite(name, value)
    if x <= 0.0:
        raise ValueError(f"{name} must be > 0, got {x}")
    return x


@dataclass(frozen=True)
class Gains:
    """Standard (ISA) form K[bW − Y + E/(Ti s) + Td s/(Td s/N + 1)(cW − Y)].

    k:  proportional gain, MV units per PV unit (finite, non-zero).
    ti: integral time, seconds, > 0; ``math.inf`` = no integral action.
    td: derivative time, seconds, >= 0; 0 = no derivative action.
    nd: derivative filter N (> 0); the filter time constant is td/nd seconds.
    b:  set-point weight of the proportional term.
    c:  set-point weight of the derivative term.
    """

    k: float
    ti: float = math.inf
    td: float = 0.0
    nd: float = 10.0
    b: float = 1.0
    c: float = 0.0

    def __post_init__(self) -> None:
        # object.__setattr__ because the dataclass is frozen; values are
        # normalised to float so that equality and JSON are predictable.
        object.__setattr__(self, "k", _nonzero("k", self.k))
        object.__setattr__(self, "ti", _integral_time("ti", self.ti))
        object.__setattr__(self, "td", _nonneg_finite("td", self.td))
        object.__setattr__(self, "nd", _positive_finite("nd", self.nd))
        object.__setattr__(self, "b", finite("b", self.b))
        object.__setattr__(self, "c", finite("c", self.c))

    @property
    def has_integral(self) -> bool:
        """True when the integral term is active (finite ti)."""
        return math.isfinite(self.ti)

    @property
    def has_derivative(self) -> bool:
        """True when the derivative term is active (td > 0)."""
        return self.td > 0.0

    @property
    def ki(self) -> float:
        """Integral gain k/ti, MV units per (PV unit · second); 0 without integral."""
        return self.k / self.ti if self.has_integral else 0.0

    @property
    def kd(self) -> float:
        """Derivative gain k·td, MV units per (PV unit / second)."""
        return self.k * self.td

    @property
    def controller_type(self) -> str:
        """"P", "PI", "PD" or "PID" from the active terms.

        "I" is never returned: the standard form always has a proportional term
        (see the module docstring).
        """
        return "P" + ("I" if self.has_integral else "") + ("D" if self.has_derivative else "")

    def as_json(self) -> dict[str, float | None]:
        """The block outputs pk, pti, ptd, pnd, pb, pc (seconds for times).

        ``pti`` is ``None`` (JSON null) when there is no integral action.
        """
        return {
            "pk": self.k,
            "pti": self.ti if self.has_integral else None,
            "ptd": self.td,
            "pnd": self.nd,
            "pb": self.b,
            "pc": self.c,
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "Gains":
        """Inverse of :meth:`as_json`; ``pti`` null or missing means no integral.

        ``d``: the JSON object (as :meth:`as_json` writes it).
        """
        if "pk" not in d:
            raise ValueError("gains JSON needs 'pk'")
        pti = d.get("pti")
        return cls(
            k=d["pk"],
            ti=math.inf if pti is None else pti,
            td=d.get("ptd", 0.0),
            nd=d.get("pnd", 10.0),
            b=d.get("pb", 1.0),
            c=d.get("pc", 0.0),
        )


@dataclass(frozen=True)
class SeriesGains:
    """Series (interacting) form K'(1 + 1/(Ti' s))(1 + Td' s).

    k: K', MV units per PV unit (finite, non-zero).
    ti: Ti', seconds, > 0; ``math.inf`` = no integral action.
    td: Td', seconds, >= 0.
    """

    k: float
    ti: float = math.inf
    td: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "k", _nonzero("k", self.k))
        object.__setattr__(self, "ti", _integral_time("ti", self.ti))
        object.__setattr__(self, "td", _nonneg_finite("td", self.td))


@dataclass(frozen=True)
class ParallelGains:
    """Parallel form K''(bW − Y) + (Ki''/s)E + Kd'' s/(Kd''/(N K'') s + 1)(cW − Y).

    kp: K'', MV units per PV unit (finite, non-zero).
    ki: Ki'', MV units per (PV unit · second); 0 = no integral action.
    kd: Kd'', MV units per (PV unit / second); 0 = no derivative action.
    ki and kd must have the sign of kp (Ti, Td are non-negative times).
    """

    kp: float
    ki: float = 0.0
    kd: float = 0.0

    def __post_init__(self) -> None:
        kp = _nonzero("kp", self.kp)
        ki = finite("ki", self.ki)
        kd = finite("kd", self.kd)
        if ki * kp < 0.0:
            raise ValueError(f"ki must have the sign of kp (kp = {kp}, ki = {ki})")
        if kd * kp < 0.0:
            raise ValueError(f"kd must have the sign of kp (kp = {kp}, kd = {kd})")
        object.__setattr__(self, "kp", kp)
        object.__setattr__(self, "ki", ki)
        object.__setattr__(self, "kd", kd)


def to_series(g: Gains) -> SeriesGains:
    """Standard → series; exists only if Ti ≥ 4·Td.

    Of the two series controllers with the same transfer function the one with
    Ti' ≥ Td' is returned. Raises :class:`FormError` when Ti < 4·Td.

    ``g``: the standard-form gains.
    """
    if not g.has_integral:
        # K(1 + Td s) is already a series PD controller.
        return SeriesGains(k=g.k, ti=math.inf, td=g.td)
    disc = 1.0 - 4.0 * g.td / g.ti
    if disc < 0.0:
        if disc < -_SERIES_TOL:
            raise FormError(
                "standard → series needs Ti ≥ 4·Td; "
                f"here Ti = {g.ti:g} s, Td = {g.td:g} s"
            )
        disc = 0.0
    root = math.sqrt(disc)
    return SeriesGains(
        k=0.5 * g.k * (1.0 + root),
        ti=0.5 * g.ti * (1.0 + root),
        td=0.5 * g.ti * (1.0 - root),
    )


def from_series(s: SeriesGains, nd: float = 10.0, b: float = 1.0, c: float = 0.0) -> Gains:
    """Series → standard: K = K'(Ti'+Td')/Ti', Ti = Ti'+Td', Td = Ti'Td'/(Ti'+Td').

    nd, b, c are passed through to the standard gains.

    ``s``: the series gains; ``nd``: the derivative filter's N; ``b``, ``c``: the set-point weights of P and D.
    """
    if not math.isfinite(s.ti):
        # Limits of the formulas as Ti' → ∞.
        return Gains(k=s.k, ti=math.inf, td=s.td, nd=nd, b=b, c=c)
    total = s.ti + s.td
    return Gains(k=s.k * total / s.ti, ti=total, td=s.ti * s.td / total, nd=nd, b=b, c=c)


def to_parallel(g: Gains) -> ParallelGains:
    """Standard → parallel: K'' = K, Ki'' = K/Ti, Kd'' = K·Td (N, b, c unchanged).

    ``g``: the standard-form gains.
    """
    return ParallelGains(kp=g.k, ki=g.ki, kd=g.kd)


def from_parallel(p: ParallelGains, nd: float = 10.0, b: float = 1.0, c: float = 0.0) -> Gains:
    """Parallel → standard: K = K'', Ti = K''/Ki'' (∞ if Ki'' = 0), Td = Kd''/K''.

    ``p``: the parallel gains; ``nd``: the derivative filter's N; ``b``, ``c``: the set-point weights of P and D.
    """
    ti = math.inf if p.ki == 0.0 else p.kp / p.ki
    return Gains(k=p.kp, ti=ti, td=p.kd / p.kp, nd=nd, b=b, c=c)


def json_number(x: float) -> float | None:
    """A JSON number; None (null) for an infinite value.

    ``x``: the value.
    """
    return None if math.isinf(x) else float(x)


def forms_json(gains: Gains) -> dict[str, Any]:
    """The gains in parallel and series form, as JSON: ``{"parallel": {kp, ki, kd}, "series": {k, ti, td}}``.

    ``series`` is null with ``series_reason`` saying why when the series form does not exist (Ti < 4·Td);
    an infinite series ti (no integral action) is null.

    ``gains``: the standard-form gains.
    """
    p = to_parallel(gains)
    out: dict[str, Any] = {"parallel": {"kp": p.kp, "ki": p.ki, "kd": p.kd}}
    try:
        ser = to_series(gains)
        out["series"] = {"k": ser.k, "ti": json_number(ser.ti), "td": ser.td}
    except FormError as exc:
        out["series"] = None
        out["series_reason"] = str(exc)
    return out

