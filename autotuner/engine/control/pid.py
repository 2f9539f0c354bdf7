"""PID unit with the semantics of the PIDU function block (methods.md §3.4).

A pure, sample-driven object: the caller supplies the time stamp of every
sample (seconds); there is no clock and no I/O. In automatic mode

    v  = ±K [ b·sp − pv + (1/Ti)∫(sp − pv)dt + Td·D_f(c·sp − pv) ] + dv
    mv = clip(v, lolim, hilim)

where ± is the reverse-action (RACT) sign, ``dv`` the feed-forward (added as
given, never sign-flipped: it is already in MV units) and D_f the derivative
filtered with time constant Td/N.

Discretisation (h = t − t_prev, from the time stamps, so a variable sample time
is handled exactly as it comes):

* integral: Tustin (trapezoid) on the true error sp − pv;
* derivative: backward difference, ``y_n = (Tf·y_{n−1} + x_n − x_{n−1})/(Tf + h)``
  with ``Tf = Td/N`` and ``x = c·sp − pv``; stable for any Td, h;
* tracking (back-calculation, §3.2): the integrator also receives
  ``(ũ − v)/tt``. ``ũ`` is the limited output, or the tracking input ``tv``
  (limited) when given. The tracking ODE is integrated exactly over each
  interval (zero-order hold on ``ũ − v``), i.e. the integrator moves by
  ``(1 − exp(−h/tt))·(ũ − v)``, so tracking is stable for any ratio h/tt.

The integral state is kept in MV units. That is what makes gain changes and
mode switches bumpless: the accumulated MV does not depend on K or Ti.

With finite output limits the integral state is kept within
:data:`INTEGRAL_SPANS` spans of them (``[lolim − n·span, hilim + n·span]``):
extreme but valid gains (k 1e38, ti 1e-30) would otherwise wind it up (or,
through a bumpless change back, push it) so far that the output stays pinned
at a limit for minutes after sane gains are written back. The band is wide
enough that a sane loop never reaches it (a PI without tracking winds up
within it as before); from its edge tracking drains in a few ``tt``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from autotuner.engine.checks import finite
from autotuner.engine.control.gains import Gains

__all__ = ["PidUnit", "KINDS"]

KINDS = ("P", "I", "PI", "PD", "PID")

# Changing any of these alters the control law, so the integral/bias state is
# adjusted to keep the output continuous.
_LAW_FIELDS = frozenset({"gains", "kind", "reverse"})
_CONFIG_FIELDS = _LAW_FIELDS | {"lolim", "hilim", "tt"}
# How many output spans beyond the limits the integral state may go (finite limits only).
INTEGRAL_SPANS = 10.0


def _check_config(gains: Any, kind: Any, reverse: Any, lolim: Any, hilim: Any, tt: Any) -> None:
    if not isinstance(gains, Gains):
        raise ValueError(f"gains must be a Gains instance, got {type(gains).__name__}")
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {', '.join(KINDS)}; got {kind!r}")
    if kind == "I" and not gains.has_integral:
        raise ValueError("kind 'I' needs a finite ti (the integral gain is k/ti)")
    if not isinstance(reverse, bool):
        raise ValueError(f"reverse must be a bool, got {reverse!r}")
    for name, lim in (("lolim", lolim), ("hilim", hilim)):
        if isinstance(lim, bool) or not isinstance(lim, (int, float)) or math.isnan(lim):
            raise ValueError(f"{name} must be a number (±inf allowed), got {lim!r}")
    if lolim > hilim:
        raise ValueError(f"lolim must be <= hilim, got lolim = {lolim}, hilim = {hilim}")
    if tt is not None:
        if isinstance(tt, bool) or not isinstance(tt, (int, float)) or not math.isfinite(tt) or tt <= 0:
            raise ValueError(f"tt must be None or a finite time > 0 seconds, got {tt!r}")


@dataclass
class PidUnit:
    """PID controller unit (PIDU semantics). Times in seconds.

    gains:   standard-form gains (:class:`autotuner.engine.control.gains.Gains`).
    kind:    which terms act: "P", "I", "PI", "PD", "PID". A term whose
             parameter switches it off (ti = inf, td = 0) is absent whatever
             the kind, so "PID" with ti = inf behaves as "PD". "I" is the pure
             integral controller mv = (k/ti)∫(sp − pv)dt (+ dv) and needs a
             finite ti; b, c, td are then unused.
    reverse: RACT. False: more MV → more PV (error sp − pv drives MV up).
             True: more MV → less PV (the control law's sign is flipped).
    lolim, hilim: output limits, MV units (±inf = none).
    tt:      tracking time constant, seconds. None → PIDU's rule of thumb
             sqrt(ti·td) with derivative action, ti/2 without.

    P and PD units have no integrator; their state is a constant bias (manual
    reset) that is set by :meth:`reset`, follows ``hv`` in manual mode
    (bumpless return to automatic) and absorbs gain changes. In automatic
    mode it does not move, so ``tv`` is ignored for them: a static law cannot
    wind up.

    Outputs of the last :meth:`step`: ``mv``, ``dmv`` (mv change since the
    previous sample), ``de`` (deviation sp − pv, before the RACT sign), ``hl``
    / ``ll`` (the unlimited value was above hilim / below lolim; in manual mode
    this refers to hv) and ``sat`` (hl or ll).
    """

    gains: Gains
    kind: str = "PID"
    reverse: bool = False
    lolim: float = -math.inf
    hilim: float = math.inf
    tt: float | None = None

    mv: float = field(default=0.0, init=False)
    dmv: float = field(default=0.0, init=False)
    de: float = field(default=0.0, init=False)
    hl: bool = field(default=False, init=False)
    ll: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        _check_config(self.gains, self.kind, self.reverse, self.lolim, self.hilim, self.tt)
        self._integral = 0.0  # MV units: integral term, or bias of P/PD
        self._dfilt = 0.0  # filtered derivative of c·sp − pv, PV units/s
        self._track_err = 0.0  # ũ − v at the last sample, applied over the next interval
        self._t_prev: float | None = None
        self._e_prev = 0.0
        self._x_prev = 0.0
        self._last: tuple[float, float] | None = None  # (sp, pv) of the last sample
        self._ready = True

    # -- configuration ---------------------------------------------------

    def __setattr__(self, name: str, value: Any) -> None:
        if name not in _CONFIG_FIELDS or not self.__dict__.get("_ready", False):
            object.__setattr__(self, name, value)
            return
        cfg = {f: getattr(self, f) for f in _CONFIG_FIELDS}
        cfg[name] = value
        _check_config(**cfg)
        if name in _LAW_FIELDS and self._last is not None:
            # Bumpless change: whatever the P and D terms gain or lose at the
            # last sample is taken from (given to) the integral state.
            sp, pv = self._last
            before = self._static_terms(sp, pv)
            object.__setattr__(self, name, value)
            self._integral = self._bounded(self._integral + (before - self._static_terms(sp, pv)))
            # A new c changes c·sp − pv without the signal moving; re-basing the
            # derivative's previous input avoids a spurious derivative kick.
            self._x_prev = self.gains.c * sp - pv
        else:
            object.__setattr__(self, name, value)

    @property
    def has_p(self) -> bool:
        """Proportional term active."""
        return "P" in self.kind

    @property
    def has_i(self) -> bool:
        """Integral term active (kind includes I and ti is finite)."""
        return "I" in self.kind and self.gains.has_integral

    @property
    def has_d(self) -> bool:
        """Derivative term active (kind includes D and td > 0)."""
        return "D" in self.kind and self.gains.has_derivative

    @property
    def tt_effective(self) -> float:
        """Tracking time constant in use, seconds (inf when there is no integrator)."""
        if self.tt is not None:
            return float(self.tt)
        if not self.has_i:
            return math.inf
        if self.has_d:
            return math.sqrt(self.gains.ti * self.gains.td)
        return self.gains.ti / 2.0

    @property
    def sat(self) -> bool:
        """SAT output: the last mv was limited."""
        return self.hl or self.ll

    @property
    def integral(self) -> float:
        """Integral (or bias) state, MV units."""
        return self._integral

    # -- the law ---------------------------------------------------------

    def _sign(self) -> float:
        return -1.0 if self.reverse else 1.0

    def _static_terms(self, sp: float, pv: float) -> float:
        """P + D contribution, MV units, at (sp, pv) with the current filter state."""
        g = self.gains
        out = 0.0
        if self.has_p:
            out += g.k * (g.b * sp - pv)
        if self.has_d:
            out += g.k * g.td * self._dfilt
        return self._sign() * out

    def _bounded(self, x: float) -> float:
        """Integral state ``x`` kept within INTEGRAL_SPANS spans of finite output limits (module docstring)."""
        lo, hi = self.lolim, self.hilim
        if not (math.isfinite(lo) and math.isfinite(hi)):
            return x
        span = INTEGRAL_SPANS * (hi - lo)
        if math.isnan(x):  # inf − inf of an overflowing extreme gain: start again from the middle
            x = 0.5 * (lo + hi)
        return min(max(x, lo - span), hi + span)

    def _clip(self, x: float) -> float:
        return min(max(x, self.lolim), self.hilim)

    def step(
        self,
        t: float,
        sp: float,
        pv: float,
        *,
        dv: float = 0.0,
        tv: float | None = None,
        man: bool = False,
        hv: float | None = None,
    ) -> float:
        """Process one sample taken at time ``t`` (seconds); return mv.

        sp, pv: set point and process value (PV units). dv: feed-forward
        (MV units). tv: tracking input (MV units; None → track the unit's own
        limited output). man: manual mode; mv = hv limited, and the state
        follows so that returning to automatic is bumpless. The first call
        after construction or :meth:`reset` only initialises the time base.

        ``hv``: the MV to hold in manual (``man``), MV units (None: the previous output).
        """
        t, sp, pv, dv = finite("t", t), finite("sp", sp), finite("pv", pv), finite("dv", dv)
        if tv is not None:
            tv = finite("tv", tv)
        if man:
            if hv is None:
                raise ValueError("hv (manual value) is required when man=True")
            hv = finite("hv", hv)

        first = self._t_prev is None
        e = sp - pv
        x = self.gains.c * sp - pv
        integral = self._integral if first else self._advance(t, e, x)

        rest = self._static_terms(sp, pv) + dv
        v = rest + integral
        raw = hv if man else v
        mv = self._clip(raw)

        if man:
            # Exact, not via tt: the operator may switch back after one sample.
            integral = mv - rest
            track_err = 0.0
        elif self.has_i:
            target = mv if tv is None else self._clip(tv)
            track_err = target - v
        else:
            track_err = 0.0

        # The state of the sample, set at once: none of it is configuration, so it bypasses __setattr__'s checks
        # (the cost of a simulated plant's tick is mostly this method's, docs/modbus.md).
        self.__dict__.update(
            _integral=integral, _track_err=track_err, dmv=0.0 if first else mv - self.mv, mv=mv, de=e,
            hl=raw > self.hilim, ll=raw < self.lolim, _t_prev=t, _e_prev=e, _x_prev=x, _last=(sp, pv))
        return mv

    def _advance(self, t: float, e: float, x: float) -> float:
        """Advance the derivative filter and the integral from the previous sample to ``t`` (s) with the error
        ``e`` and the weighted error ``x`` (PV units); the integral now (MV units)."""
        h = t - self._t_prev
        if h <= 0.0:
            raise ValueError(f"t must increase from sample to sample; got t = {t} after {self._t_prev}")
        g = self.gains
        tf = g.td / g.nd
        self._dfilt = (tf * self._dfilt + (x - self._x_prev)) / (tf + h)
        integral = self._integral
        if self.has_i:
            tt = self.tt_effective
            integral += (1.0 - math.exp(-h / tt)) * self._track_err
            integral += self._sign() * g.ki * h * 0.5 * (e + self._e_prev)
            integral = self._bounded(integral)
        return integral

    def reset(self, mv: float, sp: float, pv: float, *, dv: float = 0.0) -> None:
        """Initialise the state so that the next output equals ``mv``.

        ``mv`` (MV units) is limited to [lolim, hilim]; the derivative filter
        is cleared. The next :meth:`step` starts a new time base (no
        integration over the gap), and with the same sp, pv, dv it returns
        exactly the limited ``mv``.

        ``sp``, ``pv``, ``dv``: the set point, the PV (PV units) and the feed-forward (MV units) the next step
        starts from.
        """
        mv = finite("mv", mv)
        sp = finite("sp", sp)
        pv = finite("pv", pv)
        dv = finite("dv", dv)
        self._dfilt = 0.0
        mv = self._clip(mv)
        self._integral = mv - (self._static_terms(sp, pv) + dv)
        self._track_err = 0.0
        self._t_prev = None
        self._e_prev = sp - pv
        self._x_prev = self.gains.c * sp - pv
        self._last = (sp, pv)
        self.mv = mv
        self.dmv = 0.0
        self.de = sp - pv
        self.hl = self.ll = False
