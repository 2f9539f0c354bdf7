"""Auxiliary function blocks around the PID unit: MCU, SAT, SWU, SELU (methods.md §3.4).

Every block is a pure, sample-driven object in the style of
:class:`autotuner.engine.control.pid.PidUnit`: the caller supplies the time stamp ``t``
(seconds) of every sample; there is no clock and no I/O. Parameters are
dataclass fields, validated on construction and on every later assignment
(a ``ValueError`` names the offending parameter). Inputs of one sample are
the keyword arguments of ``step``.

Sample-time convention of the dynamic blocks (MCU, SAT): the inputs given at
sample ``t_k`` are taken to have acted over the interval ``(t_{k-1}, t_k]``
that ends at that sample, and each interval is integrated exactly whatever
its length, so a variable sample time is handled as it comes. The first
``step`` after construction only initialises the time base (no interval has
elapsed yet). ``t`` must increase strictly from sample to sample.

* :class:`ManualControlUnit` (MCU): operator ramp with UP/DN buttons whose
  rate accelerates by ``q`` every ``ta`` seconds until ``tf``; tracks ``tv``
  when idle; passes ``rv`` through in remote mode.
* :class:`SaturationUnit` (SAT): fixed or input-driven limits whose rate of
  change is bounded (``tp`` rising, ``tn`` falling); flags HL/LL.
* :class:`SwitchUnit` (SWU): feeds a tracking input with ``uc`` normally and
  ``uo`` when any of OR1..OR4 is set.
* :class:`SelectorUnit` (SELU): picks the active controller among u1..u4 and
  tells the others to track the selected value (bumpless switching).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, fields
from typing import Any

from autotuner.engine.checks import finite, real

__all__ = [
    "ManualControlUnit",
    "SaturationUnit",
    "SatOutput",
    "SwitchUnit",
    "SelectorUnit",
    "SeluOutput",
]


# -- validation helpers ---------------------------------------------------


def _flag(name: str, value: Any) -> bool:
    """A binary input: bool, or the integers 0 / 1."""
    if isinstance(value, bool):
        return value
    if isinstance(value, int) and value in (0, 1):
        return bool(value)
    raise ValueError(f"{name} must be a bool (or 0/1), got {value!r}")


def _time_param(name: str, value: Any, *, positive: bool) -> float:
    x = finite(name, value)
    if positive and x <= 0.0:
        raise ValueError(f"{name} must be a finite time > 0 seconds, got {value!r}")
    if not positive and x < 0.0:
        raise ValueError(f"{name} must be a finite time >= 0 seconds, got {value!r}")
    return x


def _limits(lolim: Any, hilim: Any, lo_name: str = "lolim", hi_name: str = "hilim") -> None:
    lo = real(lo_name, lolim)
    hi = real(hi_name, hilim)
    if lo > hi:
        raise ValueError(f"{lo_name} must be <= {hi_name}, got {lo_name} = {lo}, {hi_name} = {hi}")


class _Validated:
    """Re-validates the parameter fields on every assignment after construction."""

    def _check(self, cfg: dict[str, Any]) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def _params(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.init}  # type: ignore[arg-type]

    def __setattr__(self, name: str, value: Any) -> None:
        # The step functions assign their state every sample: only a parameter's assignment is checked.
        if self.__dict__.get("_ready", False) and name in _param_names(type(self)):
            cfg = self._params()
            cfg[name] = value
            self._check(cfg)
        object.__setattr__(self, name, value)


@functools.cache
def _param_names(cls: type) -> frozenset[str]:
    return frozenset(f.name for f in fields(cls) if f.init)


class _TimeBase:
    """Strictly increasing sample times; returns the interval since the last sample."""

    def __init__(self) -> None:
        self.t_prev: float | None = None

    def advance(self, t: Any) -> tuple[float, float | None]:
        """(t, h) with h = t − t_prev, or None on the first sample."""
        t = finite("t", t)
        if self.t_prev is None:
            return t, None
        h = t - self.t_prev
        if h <= 0.0:
            raise ValueError(f"t must increase from sample to sample; got t = {t} after {self.t_prev}")
        return t, h


# -- MCU ------------------------------------------------------------------


@dataclass
class ManualControlUnit(_Validated):
    """Manual control unit (MCU semantics): an operator station for a value y.

    Parameters (times in seconds, y in output units):

    tm:    initial ramp: while a button is held, y moves by one unit per ``tm``
           seconds, i.e. the base rate is ``1/tm`` units/s (> 0).
    q:     rate multiplier (> 0): the rate is multiplied by ``q`` after every
           ``ta`` seconds of continuous holding, as long as that moment is at
           most ``tf`` seconds after the press. A multiplication due exactly at
           ``tf`` happens (rounding slack 1e-9 relative); with the defaults
           (tm 100, q 5, ta 4, tf 8) the rate is 0.01 units/s for 0–4 s, 0.05
           for 4–8 s and 0.25 from 8 s on. ``tf < ta`` gives a constant rate.
    ta:    interval between rate multiplications (> 0).
    tf:    time after which the rate changes no more (>= 0).
    tt:    tracking time constant (>= 0): when idle, y approaches ``tv`` as
           ``dy/dt = (tv − y)/tt`` (integrated exactly with tv held over the
           interval); ``tt = 0`` copies ``tv`` at once.
    y0:    initial output (limited to [lolim, hilim]).
    lolim, hilim: output limits (±inf = none; REX's SATF = off). They apply
           to the ramp, the tracked value and the remote value alike; the
           internal state is the limited value, so there is no windup: after
           running into hilim, DN moves y down at once.

    Behaviour at each sample (inputs act over the interval ending at ``t``):

    * remote (``rem`` true, REX's LOC = off): ``y = rv`` limited. Returning to
      local mode continues from that value (bumpless).
    * exactly one of ``up``/``dn`` held: y moves by ±(R(τ_k) − R(τ_{k−1}))
      where τ is the time since the press and R(τ) = ∫₀^τ rate the ramp
      distance. The press counts from the sample *before* the one at which
      the button is first seen held (it acted over that whole interval), so
      after holding for τ seconds y = y_start ± R(τ) exactly, on any
      sampling grid. A change of direction restarts the acceleration.
    * neither held: y tracks ``tv`` if it is given (tracking enabled), else
      holds. Both held: they cancel; y holds and the acceleration restarts.

    Output of the last :meth:`step`: ``y``.
    """

    tm: float = 100.0
    q: float = 5.0
    ta: float = 4.0
    tf: float = 8.0
    tt: float = 1.0
    y0: float = 0.0
    lolim: float = -math.inf
    hilim: float = math.inf

    y: float = field(default=0.0, init=False)

    def _check(self, cfg: dict[str, Any]) -> None:
        _time_param("tm", cfg["tm"], positive=True)
        q = finite("q", cfg["q"])
        if q <= 0.0:
            raise ValueError(f"q must be > 0, got {cfg['q']!r}")
        _time_param("ta", cfg["ta"], positive=True)
        _time_param("tf", cfg["tf"], positive=False)
        _time_param("tt", cfg["tt"], positive=False)
        finite("y0", cfg["y0"])
        _limits(cfg["lolim"], cfg["hilim"])

    def __post_init__(self) -> None:
        self._check(self._params())
        self._clock = _TimeBase()
        self.y = self._clip(float(self.y0))
        self._dir = 0  # +1 UP held, −1 DN held, 0 otherwise
        self._press_t = 0.0  # start of the current press, s
        self._ready = True

    def _clip(self, x: float) -> float:
        return min(max(x, self.lolim), self.hilim)

    @property
    def multiplications(self) -> int:
        """Number of rate multiplications during one long press: ⌊tf/ta⌋."""
        return math.floor(self.tf / self.ta * (1.0 + 1e-9))

    def rate(self, tau: float) -> float:
        """Ramp rate (units/s) after holding a button for ``tau`` seconds."""
        k = min(math.floor(max(tau, 0.0) / self.ta), self.multiplications)
        return self.q**k / self.tm

    def ramp_distance(self, tau: float) -> float:
        """R(τ): distance (units) travelled after holding a button for ``tau`` s, no limits."""
        tau = max(tau, 0.0)
        n = self.multiplications
        k = min(math.floor(tau / self.ta), n)
        q = self.q
        whole = k if q == 1.0 else (q**k - 1.0) / (q - 1.0)  # Σ_{j<k} q^j
        return (whole * self.ta + q**k * (tau - k * self.ta)) / self.tm

    def step(
        self,
        t: float,
        *,
        up: bool = False,
        dn: bool = False,
        tv: float | None = None,
        rv: float | None = None,
        rem: bool = False,
    ) -> float:
        """Process one sample at time ``t`` (s); return y (output units).

        up, dn: the buttons. tv: tracking value while idle (None → no tracking,
        y holds). rv: remote value, required when ``rem`` is true.
        """
        up = _flag("up", up)
        dn = _flag("dn", dn)
        rem = _flag("rem", rem)
        if tv is not None:
            tv = finite("tv", tv)
        if rem:
            if rv is None:
                raise ValueError("rv (remote value) is required when rem=True")
            rv = finite("rv", rv)
        elif rv is not None:
            rv = finite("rv", rv)
        t, h = self._clock.advance(t)
        direction = int(up) - int(dn)

        if rem:
            self.y = self._clip(rv)
            direction = 0
        elif direction != 0:
            if h is None:
                self._press_t = t  # no interval yet: the press starts now
            else:
                if direction != self._dir:
                    self._press_t = t - h
                t_prev = t - h
                dist = self.ramp_distance(t - self._press_t) - self.ramp_distance(t_prev - self._press_t)
                self.y = self._clip(self.y + direction * dist)
        elif not (up and dn) and tv is not None and h is not None:
            if self.tt == 0.0:
                self.y = self._clip(tv)
            else:
                self.y = self._clip(tv + (self.y - tv) * math.exp(-h / self.tt))

        self._dir = direction
        self._clock.t_prev = t
        return self.y


# -- SAT ------------------------------------------------------------------


@dataclass(frozen=True)
class SatOutput:
    """SAT outputs of one sample.

    y: limited signal. hl, ll: the input was above the high / below the low
    effective limit (y is held at that limit). hi, lo: the effective limits
    used at this sample (after rate limiting).
    """

    y: float
    hl: bool
    ll: bool
    lo: float
    hi: float


@dataclass
class SaturationUnit(_Validated):
    """Saturation with fixed or input-driven, rate-limited limits (SAT semantics).

    Parameters:

    lolim, hilim: fixed limits, used when the ``lo`` / ``hi`` input of a
        sample is None (unconnected). lolim <= hilim; ±inf allowed.
    tp: rise time of the limits, s per unit: an effective limit rises by at
        most ``h/tp`` over an interval of ``h`` seconds (maximum rate of rise
        ``1/tp`` units/s). ``tp = 0``: no bound (limits rise at once).
    tn: fall time, likewise: maximum rate of fall ``1/tn`` units/s; 0 = no bound.

    Both limits obey the same bounds, so effective limits never cross when
    their targets do not. At the first sample, and whenever an effective limit
    is infinite (it cannot ramp from infinity), the effective limit equals
    its target at once. A target of ±inf (limit removed) is approached at the
    maximum rate, so removing a limit widens it gradually too.

    The output is ``y = clip(u, lo_eff, hi_eff)``; ``hl = u > hi_eff``,
    ``ll = u < lo_eff``. Targets with lo > hi raise ``ValueError``.
    """

    lolim: float = -1.0
    hilim: float = 1.0
    tp: float = 0.0
    tn: float = 0.0

    def _check(self, cfg: dict[str, Any]) -> None:
        _limits(cfg["lolim"], cfg["hilim"])
        _time_param("tp", cfg["tp"], positive=False)
        _time_param("tn", cfg["tn"], positive=False)

    def __post_init__(self) -> None:
        self._check(self._params())
        self._clock = _TimeBase()
        self.lo_eff = -math.inf
        self.hi_eff = math.inf
        self.out: SatOutput | None = None
        self._ready = True

    def _move(self, prev: float, target: float, h: float | None) -> float:
        if h is None or not math.isfinite(prev):
            return target
        if target > prev:
            return target if self.tp == 0.0 else min(target, prev + h / self.tp)
        return target if self.tn == 0.0 else max(target, prev - h / self.tn)

    def step(self, t: float, u: float, *, lo: float | None = None, hi: float | None = None) -> SatOutput:
        """Process one sample at time ``t`` (s): limit ``u``.

        lo, hi: input-driven limit targets (None → lolim / hilim).
        """
        u = finite("u", u)
        lo_t = self.lolim if lo is None else real("lo", lo)
        hi_t = self.hilim if hi is None else real("hi", hi)
        if lo_t > hi_t:
            lo_name = "lolim" if lo is None else "lo"
            hi_name = "hilim" if hi is None else "hi"
            raise ValueError(f"{lo_name} must be <= {hi_name}, got {lo_name} = {lo_t}, {hi_name} = {hi_t}")
        t, h = self._clock.advance(t)
        self.lo_eff = self._move(self.lo_eff, float(lo_t), h)
        self.hi_eff = self._move(self.hi_eff, float(hi_t), h)
        y = min(max(u, self.lo_eff), self.hi_eff)
        self.out = SatOutput(y=y, hl=u > self.hi_eff, ll=u < self.lo_eff, lo=self.lo_eff, hi=self.hi_eff)
        self._clock.t_prev = t
        return self.out


# -- SWU ------------------------------------------------------------------


@dataclass
class SwitchUnit:
    """Switch for a tracking input (SWU semantics); static, no parameters.

    ``y = uo`` when any of ``or1``..``or4`` is true, else ``y = uc``. Typical
    wiring: uc = the controller's own limited output, uo = the value that
    actually drives the process when something else (a manual station, an
    override) is in charge; y feeds the PID's ``tv``.

    ``t`` is accepted for a uniform block interface and checked to be finite;
    the block has no state. Outputs of the last :meth:`step`: ``y`` and
    ``sw`` (uo selected).
    """

    y: float = field(default=0.0, init=False)
    sw: bool = field(default=False, init=False)

    def step(
        self,
        t: float,
        uc: float,
        uo: float,
        *,
        or1: bool = False,
        or2: bool = False,
        or3: bool = False,
        or4: bool = False,
    ) -> float:
        """Return uo if any OR input is set, else uc.

        ``t``: the sample's time (s, finite); ``uc``: the controller's own output; ``uo``: the other one;
        ``or1``, ``or2``, ``or3``, ``or4``: the OR inputs that select ``uo``.
        """
        finite("t", t)
        uc = finite("uc", uc)
        uo = finite("uo", uo)
        flags = [_flag(f"or{i}", v) for i, v in enumerate((or1, or2, or3, or4), start=1)]
        self.sw = any(flags)
        self.y = uo if self.sw else uc
        return self.y


# -- SELU -----------------------------------------------------------------


@dataclass(frozen=True)
class SeluOutput:
    """SELU outputs of one sample.

    y: the selected input. isel: its number (1–4). track[i]: controller i+1
    is not selected and must track (``track``: the four of them). tv[i]: the value to feed to controller
    i+1's tracking input — ``y`` for the non-selected ones, None for the
    selected one (it tracks its own limited output), which is exactly what
    :meth:`autotuner.engine.control.pid.PidUnit.step` takes as ``tv``.
    """

    y: float
    isel: int
    track: tuple[bool, bool, bool, bool]
    tv: tuple[float | None, float | None, float | None, float | None]


@dataclass
class SelectorUnit(_Validated):
    """Selector of the active controller among u1..u4 (SELU semantics); static.

    binary: how the selection is given.
        False (default): by the integer input ``isel`` in 1..4.
        True: by the binary inputs SL1, SL2 as a two-bit number,
        ``isel = 1 + SL1 + 2·SL2``:

        ====  ====  =========
        SL1   SL2   selected
        ====  ====  =========
        0     0     u1
        1     0     u2
        0     1     u3
        1     1     u4
        ====  ====  =========

    Unconnected inputs u3, u4 are None; selecting an unconnected input is an
    error. Bumpless switching: feed ``out.tv[i]`` to controller i+1's ``tv``
    each sample (in a sampled loop, the previous sample's ``out``), with a
    tracking time ``tt`` of the order of the sample time. A non-selected PI
    then sits within about ``tt·(k/ti)·|e|`` of y, so the switch moves the
    output by no more than a few normal per-sample changes.

    ``t`` is accepted for a uniform block interface and checked to be finite.
    Output of the last :meth:`step`: ``out``.
    """

    binary: bool = False

    def _check(self, cfg: dict[str, Any]) -> None:
        if not isinstance(cfg["binary"], bool):
            raise ValueError(f"binary must be a bool, got {cfg['binary']!r}")

    def __post_init__(self) -> None:
        self._check(self._params())
        self.out: SeluOutput | None = None
        self._ready = True

    def select(self, *, isel: int | None = None, sl1: bool = False, sl2: bool = False) -> int:
        """Selected input number 1..4 from the selection inputs.

        ``isel``: the selected input's number 1..4 (without ``binary``); ``sl1``, ``sl2``: the two selection bits
        (with ``binary``).
        """
        sl1 = _flag("sl1", sl1)
        sl2 = _flag("sl2", sl2)
        if self.binary:
            if isel is not None:
                raise ValueError("isel is not used when binary=True (select with sl1, sl2)")
            return 1 + int(sl1) + 2 * int(sl2)
        if isel is None:
            raise ValueError("isel (1..4) is required when binary=False")
        if sl1 or sl2:
            raise ValueError("sl1/sl2 are not used when binary=False (select with isel)")
        if isinstance(isel, bool) or not isinstance(isel, int):
            raise ValueError(f"isel must be an integer 1..4, got {isel!r}")
        if not 1 <= isel <= 4:
            raise ValueError(f"isel must be in 1..4, got {isel}")
        return isel

    def step(
        self,
        t: float,
        u1: float | None,
        u2: float | None,
        u3: float | None = None,
        u4: float | None = None,
        *,
        isel: int | None = None,
        sl1: bool = False,
        sl2: bool = False,
    ) -> SeluOutput:
        """Select one of u1..u4 and tell the others to track it.

        ``t``: the sample's time (s, finite); ``u1``, ``u2``, ``u3``, ``u4``: the inputs (``u3``, ``u4`` may be None when unused);
        ``isel``, ``sl1``, ``sl2``: the selection, as for :meth:`select`.
        """
        finite("t", t)
        n = self.select(isel=isel, sl1=sl1, sl2=sl2)
        inputs = (u1, u2, u3, u4)
        for i, u in enumerate(inputs, start=1):
            if u is not None:
                finite(f"u{i}", u)
        chosen = inputs[n - 1]
        if chosen is None:
            raise ValueError(f"u{n} is selected (isel = {n}) but not connected (None)")
        y = float(chosen)
        track = tuple(i != n for i in range(1, 5))
        tv = tuple(y if tr else None for tr in track)
        self.out = SeluOutput(y=y, isel=n, track=track, tv=tv)  # type: ignore[arg-type]
        return self.out
