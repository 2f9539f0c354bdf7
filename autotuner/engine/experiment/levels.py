"""The relay's two MV levels: their centre, the bias and its sign, and a drift followed between switches.

The relay alternates between ``centre + amp`` and ``centre − amp·(1 − 2·bias)``
(the bias gives the oscillation a DC component that reveals the static gain).
The centre starts at ``mv0`` and follows a fitted load within ±amp
(load_following.py); the bias changes sign once after a load step, drops to
``UNSTABLE_BIAS`` on an open-loop unstable process, and a rescued half period
(runaway.py) holds the full amp. Every change of the levels starts a
transient: ``changed_at`` tells the estimates when.
"""

from __future__ import annotations

import math

from autotuner.engine.experiment.config import RelayConfig

# The relay's low level in its first half period, as a share of amp: no estimate uses the first period, and
# an unstable process with D/T ≥ ln(1 + 0.4) ≈ 0.34 overshoots beyond it at once, while the PV is still
# near the set point, and is recognised in the first period (runaway.py) before a phase filter's lag can
# make it run away beyond the full amp; a rescue to the full amp still holds it (up to D/T ≈ 0.55).
FIRST_LOW = 0.4
# Open-loop unstable processes (a negative mean ratio, or a PV that ran away from a weak relay
# level): the relay's bias drops to this, so that the weaker level (amp·(1 − 2·bias)) keeps the
# authority to bring the PV back after the overshoot the dead time gives (e^{D/T} − 1 at D/T = 0.5
# is 0.65 × amp: more than the 0.6 of bias 0.2).
UNSTABLE_BIAS = 0.1


def listed(config: RelayConfig, mv0: float) -> tuple[float, ...]:
    """Every MV level a relay centred at ``mv0`` (MV units) with ``config`` can hold, ascending."""
    lo, hi = config.mv_limits
    amp = config.amp
    shares = {1.0, 1.0 - 2.0 * config.bias, min(FIRST_LOW, 1.0 - 2.0 * config.bias),
              1.0 - 2.0 * min(config.bias, UNSTABLE_BIAS)}
    low = {max(mv0 - amp * share, lo) for share in shares}
    return tuple(sorted(low | {min(mv0 + amp, hi)}))


class Levels:
    """The high and low MV levels (MV units) and what sets them: the settings ``config`` and the MV ``mv0`` at
    the start (MV units), the first centre."""

    def __init__(self, config: RelayConfig, mv0: float) -> None:
        self.config = config
        lo, hi = config.mv_limits
        self.high = min(mv0 + config.amp, hi)
        self.low = max(mv0 - config.amp * min(FIRST_LOW, 1.0 - 2.0 * config.bias), lo)
        self.first_low = True  # the first half period's weak level (FIRST_LOW) is held
        self.center = mv0
        self.bias = config.bias
        self.bias_sign = 1.0
        self.flipped = False
        self.full = False  # a rescued half period holds the full amp (runaway.py)
        self.follow_rate = 0.0  # a drifting load followed continuously, MV units per s
        self.follow_from = 0.0  # ... from this time, s
        self.changed_at = -math.inf  # when the levels last changed, s

    def reset(self) -> None:
        """Levels from the centre and the sign of the bias, within the MV limits."""
        lo, hi = self.config.mv_limits
        amp, short = self.config.amp, self.config.amp * (1.0 - 2.0 * self.bias)
        up, down = (amp, short) if self.bias_sign > 0 else (short, amp)
        self.high = min(self.center + up, hi)
        self.low = max(self.center - down, lo)

    def mv(self, relay: int, now: float) -> float:
        """The MV at the level ``relay`` (+1 high, −1 low) at time ``now`` (s)."""
        level = self.high if relay > 0 else self.low
        if self.follow_rate:
            # A drifting load is followed continuously: no step, no transient.
            lo, hi = self.config.mv_limits
            level = min(max(level - self.follow_rate * (now - self.follow_from), lo), hi)
        return level

    def at_full_amp(self, relay: int) -> bool:
        """True when the level ``relay`` (+1 high, −1 low) is the full amp from the centre."""
        level = self.high if relay > 0 else self.low
        return abs(level - self.center) >= self.config.amp * (1.0 - 1e-9) or self.full

    def end_first_low(self) -> None:
        """The first whole period is over: the biased levels from now on (unless a rescue holds the full amp)."""
        if self.first_low:
            self.first_low = False
            if not self.full:
                self.reset()

    def strengthen(self, relay: int) -> None:
        """Hold the level ``relay`` (+1 high, −1 low) at the full amp until the next switch."""
        lo, hi = self.config.mv_limits
        if relay > 0:
            self.high = min(self.center + self.config.amp, hi)
        else:
            self.low = max(self.center - self.config.amp, lo)
        self.full = True

    def end_rescue(self) -> None:
        """A switch ends a rescued half period: the weaker bias from now on."""
        if self.full:
            self.full = False
            self.reset()

    def weaken_bias(self, now: float) -> None:
        """An open-loop unstable process: the bias drops to ``UNSTABLE_BIAS`` (a change at ``now``, s)."""
        if self.bias > UNSTABLE_BIAS:
            self.bias = min(self.bias, UNSTABLE_BIAS)
            if not self.full:
                self.reset()
            self.changed_at = now

    def flip_once(self) -> None:
        """Change the sign of the bias, once per experiment: after a load step the static gain then has a
        known excitation as well."""
        if not self.flipped:
            self.bias_sign = -self.bias_sign
            self.flipped = True

    def centre_at(self, then: float) -> float:
        """The centre the relay holds at ``then`` (s), with the drift followed: MV units."""
        return self.center - self.follow_rate * (then - self.follow_from)

    def follow(self, center: float, rate: float, then: float) -> None:
        """Centre the levels at ``center`` (MV units) at ``then`` (s) and follow a drift of ``rate`` (MV units
        per s) from there."""
        self.center, self.follow_rate, self.follow_from = center, rate, then
        self.reset()
