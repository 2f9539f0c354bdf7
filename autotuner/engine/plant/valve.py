"""A control valve with stiction: Choudhury's two-parameter data-driven model.

Choudhury, Thornhill and Shah, "Modelling valve stiction", Control Engineering
Practice 13 (2005) 641–658. The valve takes the controller output ``u`` (MV
units) and returns its position ``x`` (MV units). Two parameters, both in MV
units here (a plant file gives them in % of the MV span):

* ``s`` — deadband plus stickband: how far ``u`` must move back after a
  reversal before the valve moves again;
* ``j`` — the slip jump: how far ``u`` must move on in the same direction
  after it has come to rest before the valve moves again, and so the size of
  the jump the valve makes when it breaks free.

The valve sticks whenever ``u`` stops or reverses; it slips once ``u`` has
passed the input it stuck at by more than s (moving back) or j (moving on the
same way), and while it moves it follows ``u`` at the distance (s − j)/2
behind it: x = u − sign(Δu)·(s − j)/2. With j = 0 the model is a pure
deadband (backlash) of width s.

At the start the valve rests at ``u`` in the middle of its band: it first moves
when ``u`` has left the start by more than s/2 either way (so with j = 0 it is
exactly the play operator of width s from x = u).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field


def _sign(x: float) -> int:
    return (x > 0.0) - (x < 0.0)


@dataclass
class StickyValve:
    """Choudhury's valve: ``s`` deadband plus stickband and ``j`` slip jump, MV units (both ≥ 0).

    :meth:`step` takes the controller output (MV units) and returns the valve position (MV units).
    """

    s: float
    j: float = 0.0
    _x: float = field(default=math.nan, init=False, repr=False)  # the valve position
    _u: float = field(default=math.nan, init=False, repr=False)  # the last controller output
    _moving: int = field(default=0, init=False, repr=False)  # direction the input last moved in (0: not yet)
    _stuck_at: float | None = field(default=None, init=False, repr=False)  # the input where the valve stuck
    _stuck_moving: int = field(default=0, init=False, repr=False)  # the input's direction when it stuck

    def __post_init__(self) -> None:
        for name in ("s", "j"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"valve {name} must be a finite number ≥ 0 (MV units), got {value}")

    def _band(self, direction: int) -> float:
        """How far the input must move from where the valve stuck, in ``direction``, before it slips."""
        if self._stuck_moving == 0:  # at rest in the middle of the band since the start
            return 0.5 * self.s
        return self.j if direction == self._stuck_moving else self.s

    def step(self, u: float) -> float:
        """The valve position (MV units) once the controller output has moved to ``u`` (MV units)."""
        if not math.isfinite(u):
            raise ValueError(f"controller output must be finite, got {u}")
        if math.isnan(self._x):  # first sample: at rest at u, in the middle of the band
            self._x, self._u, self._stuck_at = u, u, u
            return u
        direction = _sign(u - self._u)
        if self._stuck_at is None and direction != self._moving:  # stops or reverses: sticks
            self._stuck_at, self._stuck_moving = self._u, self._moving
        if self._stuck_at is None:
            self._x = u - direction * 0.5 * (self.s - self.j)
        elif direction != 0 and direction * (u - self._stuck_at) > self._band(direction):
            self._stuck_at = None  # slips
            self._x = u - direction * 0.5 * (self.s - self.j)
        self._u = u
        if direction != 0:
            self._moving = direction
        return self._x
