"""Linear process model: a rational transfer function in s times a dead time.

    F(s) = num(s) / den(s) * exp(-delay * s)

Times are in seconds, frequencies in rad/s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# Relative size below which a trailing coefficient counts as zero, i.e. a root
# at the origin: a few ulps of the coefficient sum, so that only cancellation
# to rounding level is mistaken for an exact zero.
_ORIGIN_TOL = 64 * np.finfo(float).eps
# Relative real part above which a pole counts as unstable; loose because
# repeated roots (e.g. (s+1)^8) are found by np.roots only to ~eps**(1/m).
_UNSTABLE_TOL = 1e-7


def _strip_leading_zeros(coeffs: Sequence[float]) -> tuple[float, ...]:
    out = [float(c) for c in coeffs]
    while len(out) > 1 and out[0] == 0.0:
        out.pop(0)
    return tuple(out)


def _trailing_zeros(coeffs: tuple[float, ...]) -> int:
    """Number of roots at the origin (trailing coefficients that are ~0)."""
    tol = _ORIGIN_TOL * sum(abs(c) for c in coeffs)
    count = 0
    for c in reversed(coeffs[1:]):
        if abs(c) > tol:
            break
        count += 1
    return count


def _format_poly(coeffs: tuple[float, ...]) -> str:
    """Polynomial in s in the expression grammar, e.g. ``2*s^2-0.5*s+1``."""
    n = len(coeffs) - 1
    parts: list[str] = []
    for i, c in enumerate(coeffs):
        power = n - i
        if c == 0.0 and not (power == 0 and not parts):
            continue
        sign = "-" if c < 0 else "+"
        mag = abs(c)
        if power == 0:
            body = f"{mag:.12g}"
        else:
            var = "s" if power == 1 else f"s^{power}"
            body = var if mag == 1.0 else f"{mag:.12g}*{var}"
        if parts:
            parts.append(sign + body)
        else:
            parts.append(body if sign == "+" else "-" + body)
    return "".join(parts)


@dataclass(frozen=True)
class Process:
    """Transfer function ``num(s)/den(s) * exp(-delay*s)``.

    ``num`` and ``den`` are polynomial coefficients in s, highest power first.
    On construction leading zero coefficients are removed and both
    polynomials are scaled so that ``den[0] == 1``. ``delay`` is the dead time
    in seconds; ``text`` is the source expression, kept for messages.

    Raises ``ValueError`` for a zero denominator, an improper transfer
    function (deg num > deg den), non-finite coefficients or a negative or
    non-finite delay.
    """

    num: tuple[float, ...]
    den: tuple[float, ...]
    delay: float = 0.0
    text: str = ""

    def __post_init__(self) -> None:
        name = f" in {self.text!r}" if self.text else ""
        num = _strip_leading_zeros(self.num)
        den = _strip_leading_zeros(self.den)
        if not num or not den:
            raise ValueError(f"empty numerator or denominator polynomial{name}")
        if not all(math.isfinite(c) for c in num + den):
            raise ValueError(f"transfer function coefficients must be finite{name}")
        if den[0] == 0.0:
            raise ValueError(f"denominator polynomial is zero{name}")
        if num[0] == 0.0:
            num = (0.0,)
        if len(num) > len(den):
            raise ValueError(
                f"improper transfer function{name}: numerator degree {len(num) - 1} "
                f"exceeds denominator degree {len(den) - 1} (not physically realisable)"
            )
        delay = float(self.delay)
        if not math.isfinite(delay) or delay < 0.0:
            raise ValueError(f"dead time must be finite and >= 0 s, got {self.delay}{name}")
        lead = den[0]
        object.__setattr__(self, "num", tuple(c / lead for c in num))
        object.__setattr__(self, "den", tuple(c / lead for c in den))
        object.__setattr__(self, "delay", delay)

    @classmethod
    def from_tf(cls, num: Sequence[float], den: Sequence[float], delay: float = 0.0,
                text: str = "") -> Process:
        """Build from coefficient sequences (highest power first) and a dead time in s.

        ``num``, ``den``: the coefficients; ``delay``: s; ``text``: the expression it came from.
        """
        return cls(tuple(float(c) for c in num), tuple(float(c) for c in den), delay, text)

    @property
    def order(self) -> int:
        """Degree of the denominator (number of poles)."""
        return len(self.den) - 1

    @property
    def poles(self) -> np.ndarray:
        """Roots of the denominator, rad/s."""
        return np.roots(self.den)

    @property
    def zeros(self) -> np.ndarray:
        """Roots of the numerator, rad/s (empty for a constant numerator)."""
        return np.roots(self.num)

    @property
    def integrator_count(self) -> int:
        """Net number of poles at the origin (poles minus zeros there, at least 0)."""
        return max(0, _trailing_zeros(self.den) - _trailing_zeros(self.num))

    @property
    def is_integrating(self) -> bool:
        return self.integrator_count > 0

    @property
    def rhp_pole_count(self) -> int:
        """Number of poles with a positive real part (poles at the origin excluded)."""
        k = _trailing_zeros(self.den)
        poles = np.roots(self.den[: len(self.den) - k])
        return int(np.sum(poles.real > _UNSTABLE_TOL * np.abs(poles)))

    @property
    def is_unstable(self) -> bool:
        """True if a pole has a positive real part (poles at the origin excluded)."""
        return self.rhp_pole_count > 0

    def static_gain(self) -> float:
        """F(0). For integrating processes ``±math.inf``, signed like the low-frequency gain."""
        kn = _trailing_zeros(self.num)
        kd = _trailing_zeros(self.den)
        if self.num == (0.0,) or kn > kd:
            return 0.0
        ratio = self.num[len(self.num) - 1 - kn] / self.den[len(self.den) - 1 - kd]
        if kd > kn:
            return math.copysign(math.inf, ratio)
        return ratio

    def freqresp(self, omega: float | np.ndarray) -> np.ndarray:
        """Complex F(jω) for ω in rad/s (array or scalar), including exp(-jωL).

        At ω = 0 an integrating process gives an infinite value.

        ``omega``: rad/s.
        """
        s = 1j * np.asarray(omega, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.polyval(self.num, s) / np.polyval(self.den, s) * np.exp(-s * self.delay)

    def time_constant_text(self) -> str:
        """The process in time-constant form with real poles, e.g. ``1.5*exp(-2.5*s)/(8.8*s+1)`` (for models
        without zeros, such as the design's; 4 significant digits)."""
        n = self.integrator_count
        gain = self.num[-1] / self.den[-1 - n]
        text = f"{gain:.4g}" + (f"*exp(-{self.delay:.4g}*s)" if self.delay else "")
        text += "/s" * n
        text += "".join(f"/({-1.0 / p.real:.4g}*s+1)" for p in self.poles if p != 0)
        return text

    def __str__(self) -> str:
        """Readable form in the expression grammar (parses back to the same process)."""
        text = _format_poly(self.num)
        if len(self.num) > 1 and (self.delay or self.order):
            text = f"({text})"
        if self.delay:
            dead = f"exp(-{self.delay:.12g}*s)"
            text = dead if text == "1" else f"{text}*{dead}"
        if self.order:
            text = f"{text}/({_format_poly(self.den)})"
        return text
