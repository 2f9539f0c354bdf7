"""The phase-shifting filter in front of the relay: a first-order lag or lead.

A lag ``1/(τs + 1)`` adds ``atan(ωτ)`` of phase lag to the relay loop and
moves the oscillation to a point of *less* process lag; a lead
``(1 + τs)/(1 + τs/N)`` subtracts lag, for targets near 180° that the
sampled relay (which itself lags by about a sample) cannot reach otherwise.
The lead's gain is bounded by ``N`` at high frequency so measurement noise is
amplified at most that much.

Phases are in radians, positive for lag; ``omega`` in rad/s; ``dt`` in s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

LEAD_N = 5.0
MAX_LAG = math.radians(89.0)
# The lead's largest phase is asin((N − 1)/(N + 1)) ≈ 41.8° for N = 5; stay clear of it.
MAX_LEAD = math.radians(35.0)


@dataclass
class PhaseFilter:
    """First-order lag (``tau`` > 0 s, ``lead`` False), lead (``lead`` True) or nothing (``tau`` = 0); ``state``:
    the lag's output, PV units."""

    tau: float = 0.0
    lead: bool = False
    state: float = 0.0

    def set_phase(self, theta: float, omega: float) -> None:
        """Make the filter's phase at ``omega`` equal ``theta`` (clipped to the achievable range)."""
        theta = min(max(theta, -MAX_LEAD), MAX_LAG)
        self.lead = theta < 0.0
        if not self.lead:
            self.tau = math.tan(theta) / omega
            return
        # atan(x) − atan(x/N) = |θ| → (t/N)x² − (1 − 1/N)x + t = 0, smaller root.
        t = math.tan(-theta)
        a, b = t / LEAD_N, 1.0 - 1.0 / LEAD_N
        x = (b - math.sqrt(b * b - 4.0 * a * t)) / (2.0 * a)
        self.tau = x / omega

    def phase(self, omega: float) -> float:
        """Phase lag at ``omega`` (negative for a lead)."""
        x = omega * self.tau
        return -(math.atan(x) - math.atan(x / LEAD_N)) if self.lead else math.atan(x)

    def _pole(self) -> tuple[float, float]:
        """(time constant of the filter's pole, direct gain ``a``): output = a·e + (1 − a)·lag(e)."""
        return (self.tau / LEAD_N, LEAD_N) if self.lead else (self.tau, 0.0)

    def step(self, e: float, dt: float) -> float:
        """Filter one sample of the error ``e`` taken ``dt`` seconds after the previous one."""
        pole, direct = self._pole()
        if pole <= 0.0:
            self.state = e
            return e
        self.state += (1.0 - math.exp(-dt / pole)) * (e - self.state)
        return direct * e + (1.0 - direct) * self.state

    def noise_gain(self, dt: float) -> float:
        """Standard deviation of the output for unit white noise at the input, sampled every ``dt``."""
        pole, direct = self._pole()
        if pole <= 0.0:
            return 1.0
        alpha = 1.0 - math.exp(-dt / pole)
        lag_var = alpha / (2.0 - alpha)
        now = direct + (1.0 - direct) * alpha
        return math.sqrt(now * now + (1.0 - direct) ** 2 * (1.0 - alpha) ** 2 * lag_var)
