"""The slow part of the experiment's data: static gain and load disturbances, fitted through one model.

The relay's limit cycle gives the point ``F(jω)``; what is left in the PV
below the oscillation frequency is the process's response to the *mean*
of the MV, plus whatever the plant did on its own: a load step, a drift, the
tail of a transient that was still settling when the experiment started.
Taking the ratio of the mean deviations (PV over MV) mixes all of that into
the static gain, which is how a load step of 0.2·amp used to end in a
negative static gain.

Here the slow part is explained by the first-order-plus-dead-time model that
the point and a candidate static gain fix exactly (methods.md §6: with
``x = |F(jω)|/K0``, ``T = sqrt(1/x² − 1)/ω`` and ``L = (φ − ∠K0 − atan ωT)/ω``;
``x < 0`` is the unstable model ``K0 < 0``, ``x = 0`` the integrator). For
each candidate ``x`` the model is driven with the MV as applied, and the
residual PV is fitted by least squares with regressors that are themselves
responses of the same model:

* an offset (the PV at the starting MV);
* a load step at the process input at time ``t_s`` (the model's step response
  from ``t_s``; ``t_s`` is searched on a grid), coefficient in MV units;
* a load ramp from the start (the model's ramp response), MV units per second;
* the free response of the model's lag from the start (a PV still settling).

Loads enter where the plant's do, at the process input, so the fitted
coefficients are the loads themselves in MV units: the relay can shift its
centre by them. Both sides are averaged over one oscillation period before
the fit, so the harmonics the model does not reproduce do not enter it.
``x`` is found by a coarse scan and Brent's method on the residual; terms
are kept only when the Bayesian information criterion says they explain more
than they cost (a quiet plant is fitted with the offset alone). The standard
error of ``x`` comes from the curvature of the residual.

The work of a fit is bounded whatever the record's length: at most
``SEARCH_RUNS`` candidate models (each one filter run over the record), run
on at most ``_GRID_MAX`` grid points (a longer record on a coarser grid), with
at most ``_ROWS_MAX`` averages and ``_STEPS_MAX`` step times. A refit as the
record grows searches near the fit accepted before (its terms, its x, its
step time: at most ``NEAR_RUNS`` models) and falls back to the full search
only when the record has moved away from it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.optimize
import scipy.signal
from scipy.linalg import lapack

from autotuner.engine.experiment.fourier import held_coefficient

# |x| above this is a process with no lag to speak of (dead time only): the
# model is then taken with x just below it (T small), which changes little.
_X_MAX = 0.995
# Step times are searched on this many points per oscillation period (at most _STEPS_MAX of them).
_STEP_GRID = 12
_STEPS_MAX = 384
# A fit runs its model on at most this many points of an even grid (a longer record on a coarser one)
# and compares at most this many one-period averages: a fit's work is bounded, whatever the record's
# length (a record of 40 periods of 100 samples is within both).
_GRID_MAX = 4096
_ROWS_MAX = 256
# The grid's step is the median of at most this many of the latest sample intervals.
_INTERVALS = 1024
# Effective number of independent averages per period after the one-period
# moving average (the information criterion counts these, not the samples).
_POINTS_PER_PERIOD = 2.0
# Averaged residuals within this fraction of the PV oscillation amplitude are
# the model's own mismatch (harmonics, a process that is not first order).
_RESOLUTION = 0.01
# Refinements of x in settled_x from the plain ratio of the means (3–4 settle it to 1e-3).
_SETTLE_ITERATIONS = 4
# ...and it has settled when its last step is within this share of itself (a fiftieth of static_tol):
# otherwise the root is searched to the same share.
_SETTLED = 4e-4
# settled_x's lag is summed over chunks of at most this many time constants (e^300 stays finite)...
_CHUNK = 300.0
# ...over the MV of this many time constants before its window (e^-36 is below a double's rounding).
MEMORY = 36.0
# The full search scans x on this many points over its range, then searches the best point's
# neighbourhood to _X_TOL (Brent's method: about 7 evaluations where the residual is smooth, at most
# _X_STEPS — the golden-section steps that narrow a cell of the scan's grid to _X_TOL); a refit near an
# earlier fit searches x the same way, from the scan's points next to the earlier x.
_X_GRID = 11
_X_TOL = 2.5e-4
_X_STEPS = 16
# A refit searches near an earlier fit whose x is this certain (a fifth of the scan's cell); near a less
# certain one it can settle in another basin of x and step time than the full search's scan finds.
_NEAR_STD = 0.02
# A refit whose residual grew beyond this many times the earlier fit's (plus the model's own mismatch,
# _RESOLUTION) meets something the earlier terms do not explain, such as a second load: the full search runs.
_MISFIT = 2.0
# Scaled regressors whose QR factor has a diagonal element below this share of the largest are nearly
# dependent: the residual is then lstsq's, which leaves such directions out.
_RANK = 1e-8


# The most candidate models one fit runs (each filters the record once: the fit's work, whatever the
# record's length). The full search: its grid of x, three searches of x (without a step, with a ramp, with the
# step: its time searched at each x, one model run) and the curvature's two points.
# A refit near an earlier fit: the full search's models without a step, twice a step-time scan near the
# earlier one and a search of x with the step (the scan's points next to the earlier x, then Brent's
# method), the curvature's two — and the full search after it when the record has moved away from the
# earlier fit.
SEARCH_RUNS = _X_GRID + 3 * _X_STEPS + 2  # (the step's search starts from the scan's best grid point)
NEAR_RUNS = _X_GRID + 2 * _X_STEPS + 2 * (1 + _X_STEPS) + 2  # (the scan's points are the grid's, run already)


@dataclass(frozen=True)
class LoadFit:
    """The slow part of the data as one model explains it.

    x: ``|F(jω)|/K0`` (0 integrating, < 0 unstable); x_std: its standard error.
    static_gain: ``|F(jω)|/x`` (``inf`` for ``x = 0``: integrating).
    offset: PV at the starting MV without load (PV units).
    step_time, step: a load step at the process input (s, MV units), or None/0.
    ramp: load ramp from the start (MV units per second).
    free: PV units of
    the free response at the start.
    residual_std: standard deviation of the averaged residual (PV units).
    score: the information criterion of the chosen model (lower explains the
    same record better; comparable between fits of one record only).
    """

    x: float
    x_std: float
    static_gain: float
    offset: float
    step_time: float | None
    step: float
    ramp: float
    free: float
    residual_std: float
    score: float

    def load_at(self, t: float, t0: float) -> float:
        """The fitted load at the process input at time ``t`` (MV units; ``t0`` is the record start)."""
        load = self.ramp * (t - t0)
        if self.step_time is not None and t >= self.step_time:
            load += self.step
        return load

    def loads(self, t: np.ndarray, t0: float) -> np.ndarray:
        """The fitted load at the process input at the times ``t`` (s; ``t0``: the record start), MV units."""
        load = self.ramp * (t - t0)
        if self.step_time is not None:
            load = load + np.where(t >= self.step_time, self.step, 0.0)
        return load

    @property
    def detected(self) -> bool:
        """True when any disturbance term was needed to explain the data."""
        return self.step_time is not None or self.ramp != 0.0 or self.free != 0.0


def first_order_model(x: float, gain: float, omega: float, lag: float) -> tuple[float, float, float]:
    """(K0, T, L) of the first-order-plus-dead-time model through the point ``gain`` (|F|, PV per MV unit),
    ``lag`` (radians) at ``omega`` (rad/s) with ``|F|/K0 = x``: K0 in PV per MV unit, T and L in s (K0 and T
    infinite for ``x`` = 0: an integrator ``|F|·ω/s`` with dead time L)."""
    x = min(max(x, -_X_MAX), _X_MAX)
    if x == 0.0:
        return math.inf, math.inf, max((lag - math.pi / 2) / omega, 0.0)
    k0 = gain / x
    t = math.copysign(math.sqrt(1.0 / (x * x) - 1.0) / omega, x)
    base = 0.0 if k0 > 0 else math.pi
    return k0, t, max((lag - base - math.atan(omega * t)) / omega, 0.0)


def _filter(dt: float, x: float, gain: float, omega: float, lag: float) -> tuple[list[float], list[float], int]:
    """(b, a, m): the model's discrete filter under zero-order hold and its dead time's whole samples.

    Exact under zero-order hold with a dead time that need not be whole samples
    (as the simulated plant does it): with ``L = m·dt + θ`` the delayed input
    switches within each interval at ``θ``.
    """
    k0, t, delay = first_order_model(x, gain, omega, lag)
    m = int(delay // dt)
    theta = delay - m * dt
    if math.isinf(k0):
        kv = gain * omega
        return [kv * (dt - theta), kv * theta], [1.0, -1.0], m
    pole = math.exp(-dt / t)
    late = math.exp(-(dt - theta) / t)
    return [k0 * (1.0 - late), k0 * late * (1.0 - math.exp(-theta / t))], [1.0, -pole], m


def _respond(u: np.ndarray, dt: float, x: float, gain: float, omega: float, lag: float) -> np.ndarray:
    """Model response (PV units) to the input ``u`` held over samples ``dt`` apart, from rest (see :func:`_filter`)."""
    b, a, m = _filter(dt, x, gain, omega, lag)
    shifted = np.concatenate((np.zeros(m + 1), u))[: len(u)]
    # y[k] is the output at sample k, before u[k] acts: one sample of delay.
    return scipy.signal.lfilter(b, a, shifted)


def settled_x(t: np.ndarray, u: np.ndarray, dy: float, x: float, gain: float, omega: float, lag: float,
                  ta: float, tb: float, slope: float = 0.0, t0: float = 0.0, u0: float = 0.0) -> float:
    """``|F|/K0`` from the means over [``ta``, ``tb``] (s): the PV's ``dy`` and the MV's as the slow part has seen
    it.

    The PV's mean over a period answers the MV's means of the periods before
    it through the process's slow lag: while the relay's mean is new (the
    start, a filter correction) the plain ratio of the two means is off by
    what the lag has not passed on yet (0.56 instead of 0.77 at the first
    estimate of ``exp(-s)/(0.5*s+1)``). Here the MV (``u``, held from the
    sample times ``t``, as deviations from ``u0`` and zero before them) goes through the lag and
    dead time of the model that ``x`` fixes with the point (``gain``,
    ``omega`` in rad/s, ``lag`` in rad), and ``x`` is refined from its own
    result a few times (the fixed point is where the model and the means
    agree). Once the means have settled the lag passes the mean on unchanged
    and the result is the plain ratio, whatever the model. ``x`` outside
    (0, 1) is returned as it is: an integrator or an unstable process has no
    settled mean to correct to.

    A PV still settling when the relay started (``slope``, PV units per
    second at ``t0``, with ``dy`` measured from the PV at ``t0``) is the lag's
    free response ``−slope·T·e^{−(t − t0)/T}`` towards a level ``slope·T``
    away: both are taken out of ``dy`` (a load step half a period before TUNE
    made ``exp(-s)/(2*s+1)`` read ``|F|/K0`` 0.10 instead of 0.39).

    Only the MV of the last ``MEMORY`` time constants of the lag before the
    window is read: an older input reaches the window's mean by less than
    e^−36 of itself, below a double's rounding.
    """
    # The dead time of the model is at most lag/ω (x → 1): the window must start after the delayed MV does.
    if dy == 0.0 or t[0] + lag / omega > ta:
        return x
    near_one = _X_MAX <= x < 1.0 / _X_MAX
    if not (0.0 < x < _X_MAX or near_one):
        return x

    def mismatch(v: float) -> float:
        """``v`` × the PV's mean response less ``|F|`` × the MV's mean as model ``v`` has passed it on."""
        _, tc, delay = first_order_model(v, gain, omega, lag)
        first = max(int(np.searchsorted(t, ta - delay - MEMORY * tc, side="right")) - 1, 0)
        end = int(np.searchsorted(t, tb - delay, side="right")) + 1
        seen = _lagged_mean(t[first:end] + delay, u[first:end] - u0, tc, ta, tb)
        left = tc / (tb - ta) * (math.exp(-(ta - t0) / tc) - math.exp(-(tb - t0) / tc))
        return v * (dy - slope * tc * (1.0 - left)) - gain * seen

    lo, hi = _X_MAX * 1e-3, _X_MAX
    if slope == 0.0:
        # From the plain ratio the refinement converges in a few steps where the correction is small: a
        # step of the plain ratio's refinement (v·dy − |F|·seen = 0 with seen held), then secant steps.
        v = x
        if 0.0 < v < _X_MAX:
            before, missed = v, mismatch(v)
            v -= missed / dy
            for _ in range(_SETTLE_ITERATIONS):
                if not 0.0 < v < _X_MAX:
                    break
                now = mismatch(v)
                if now == missed:
                    break
                step = now * (v - before) / (now - missed)
                before, missed = v, now
                v -= step
                if abs(step) <= _SETTLED * v:
                    return v
        # Not settled: a first estimate whose means are far from settled, or a plain ratio at or just above
        # 1 on a process with dead time whose shifted MV the window has not seen in full (exp(-s)/(0.2*s+1)
        # read 0.66, then 1.02 after the steps, true 0.93): the root within (0, 1) where there is one.
        if mismatch(lo) * mismatch(hi) > 0.0:
            return x if near_one else v
        return float(scipy.optimize.brentq(mismatch, lo, hi, xtol=_SETTLED * lo, rtol=_SETTLED))
    # A free response to take out moves the mean far more as x changes (through T) than the plain
    # ratio's refinement can follow: the root of the mismatch within (0, 1), bracketed.
    if near_one or mismatch(lo) * mismatch(hi) > 0.0:
        return x
    return float(scipy.optimize.brentq(mismatch, lo, hi, xtol=1e-5))


def lag_states(s: np.ndarray, u: np.ndarray, tc: float) -> np.ndarray:
    """The output of ``1/(tc·s + 1)`` (``tc``: s) at each of the times ``s`` (s) for the input ``u`` held from
    them, from zero at ``s[0]``.

    Exact for any spacing of ``s`` (a link samples unevenly): a product of
    exponentials, summed in chunks short enough not to overflow.
    """
    z = np.zeros(len(s))
    decay = np.exp(-np.diff(s) / tc)
    k = 0
    while k < len(s) - 1:
        # z[k+1:] from z[k] in one chunk of at most _CHUNK time constants.
        end = int(np.searchsorted(s, s[k] + _CHUNK * tc, side="right"))
        end = min(max(end, k + 2), len(s))
        grow = np.exp((s[k + 1:end] - s[k]) / tc)
        gains = (1.0 - decay[k:end - 1]) * u[k:end - 1] * grow
        z[k + 1:end] = (z[k] + np.cumsum(gains)) / grow
        k = end - 1
    return z


def lag_at(s: np.ndarray, u: np.ndarray, z: np.ndarray, tc: float, times: np.ndarray) -> np.ndarray:
    """The lag's output at ``times`` (s) from its ``z`` = :func:`lag_states` of ``u`` held from ``s`` (s), ``tc``
    in s; zero before ``s[0]``."""
    i = np.searchsorted(s, times, side="right") - 1
    before = i < 0
    i = np.maximum(i, 0)
    out = u[i] + (z[i] - u[i]) * np.exp(-(times - s[i]) / tc)
    return np.where(before, 0.0, out)


def _lagged_mean(s: np.ndarray, u: np.ndarray, tc: float, ta: float, tb: float) -> float:
    """Mean over ``[ta, tb]`` of ``u`` (held from the times ``s``, zero before) through ``1/(tc·s + 1)``.

    Exact for any spacing of ``s``: the lag ``z`` obeys ``z = u − tc·z'``, so
    its mean is the input's less ``tc`` times its change over the window, and
    ``z`` at the window's ends follows from its values at the switch times
    (:func:`lag_states`). The window starts at ``s[0]`` or later.
    """
    ends = lag_at(s, u, lag_states(s, u, tc), tc, np.array([ta, tb]))
    mean = held_coefficient(s, u, ta, tb, 0.0, hann=False).real
    return mean - tc * float(ends[1] - ends[0]) / (tb - ta)


def _average(columns: np.ndarray, n: int) -> np.ndarray:
    """One-period moving averages of each column (``n`` samples), every ``n/8`` samples.

    Averages closer than that are nearly the same number; leaving them out
    makes the fit several times cheaper without losing information.
    """
    total = _running_sum(columns)
    ends = _ends(n, len(columns))
    return (total[ends] - total[ends - n]) / n


def _running_sum(columns: np.ndarray) -> np.ndarray:
    """Sums of each column over its first 0, 1, … samples (one row more than ``columns``)."""
    return np.cumsum(np.vstack((np.zeros((1, columns.shape[1])), columns)), axis=0)


def _ends(n: int, length: int) -> np.ndarray:
    """Where the one-period averages of a record of ``length`` samples end: every ``n/8`` samples, or
    farther apart on a record so long that there would be more than ``_ROWS_MAX`` of them."""
    return np.arange(n, length + 1, max(n // 8, 1, -(-(length - n) // (_ROWS_MAX - 1))))


@dataclass(frozen=True)
class _Responses:
    """What one candidate x contributes to every fit, averaged: the target and the model's responses.

    A load step's response at any time is the step response from the start,
    shifted; its averages come from one running sum, so every step time
    costs an index lookup instead of a model run. (The free response of the
    lag is computed when a fit asks for it: the search leaves it out.)
    """

    target: np.ndarray
    ramp: np.ndarray
    step_sum: np.ndarray  # running sum of the step response from the start (length + 1)
    ends: np.ndarray  # where the averages end (samples: _ends)
    finite: bool  # all of the above finite (an unstable candidate's responses can overflow)

    def step(self, ks: np.ndarray, n: int) -> np.ndarray:
        """Averaged responses to unit load steps at samples ``ks`` (one column each)."""
        ends = self.ends[:, None]
        return (self.step_sum[np.maximum(ends - ks, 0)] - self.step_sum[np.maximum(ends - n - ks, 0)]) / n


def held_mean(s: np.ndarray, u: np.ndarray, u0: float, grid: np.ndarray, dt: float) -> np.ndarray:
    """Mean over each [``grid[j]``, ``grid[j]`` + ``dt``) (s) of the MV ``u`` held from the times ``s`` (``u0``
    before): the ``grid`` (s) and ``dt`` (s) of the fit.

    Exact for any spacing of ``s``: the MV's integral is piecewise linear
    between its switch times. Held onto the grid instead, a switch between
    grid points would reach the model up to a grid step late (on a record
    sampled with ±10 % jitter that biased |F|/K0 by a third); its mean keeps
    the switch's area where it was, and on a record sampled on the grid it is
    the MV itself.
    """
    end = grid[-1] + dt
    knots = np.concatenate(([min(grid[0], s[0])], s, [max(end, s[-1])]))
    area = np.concatenate(([0.0], np.cumsum(np.concatenate(([u0], u)) * np.diff(knots))))
    return np.diff(np.interp(np.append(grid, end), knots, area)) / dt


def _minimize(f: Callable[[float], float], a: float, b: float) -> float:
    """The x in [a, b] where ``f`` is least, to within ``_X_TOL``/2: Brent's method (parabolic steps where ``f`` is
    smooth, golden-section ones where not), at most ``_X_STEPS`` evaluations of ``f``."""
    found = scipy.optimize.minimize_scalar(f, bounds=(a, b), method="bounded",
                                           options={"xatol": 0.5 * _X_TOL, "maxiter": _X_STEPS})
    return float(found.x)


@dataclass(frozen=True)
class _Criterion:
    """The Bayesian information criterion of a fit of ``points`` effective averages, with residuals below
    ``floor`` (the sum of squares of the model's own mismatch) counting as none."""

    points: float
    floor: float

    def score(self, rss: float, terms: int) -> float:
        """The criterion of a model with ``terms`` coefficients and residual sum of squares ``rss``."""
        return self.points * math.log((rss + self.floor) / self.points) + terms * math.log(self.points) * 2.0

    def worth_a_term(self, rss: float) -> bool:
        """False when no model with one more term can score better than a residual ``rss`` does: even a
        residual of nothing would gain less than the term costs."""
        return rss + self.floor > self.floor * self.points ** (2.0 / self.points)


@dataclass(frozen=True)
class _Model:
    """One candidate explanation of the record: x, the load steps (grid samples), a ramp, the free
    response, its residual sum of squares and its information criterion."""

    rss: float
    score: float
    x: float
    steps: tuple[int, ...]
    ramp: bool
    free: bool = False


class LoadFitter:
    """Fits :class:`LoadFit` to a record: times ``t`` (s, increasing), PV ``y`` and the MV ``u`` held from each
    sample (``u0`` before the first), the relay started at sample ``start``.

    ``omega`` (rad/s), ``gain`` (|F|) and ``lag`` (radians): the latest estimate's point, which fixes the
    model with each |F|/K0; ``scale``: the PV's scale (|F|·amp), of which the fit resolves a share;
    ``max_steps``: the most load steps a model may hold.

    ``held_from``: when each MV reached the process, if later than its sample
    (s; default the sample times). ``runs`` counts the candidate models run so
    far (each filters the record once): the work of the fits. A full search
    (:meth:`fit`) runs at most :data:`SEARCH_RUNS` of them, a refit near an
    earlier fit at most :data:`NEAR_RUNS` (and the full search when it falls
    back to it) — whatever the record's length.
    """

    def __init__(self, t: np.ndarray, y: np.ndarray, u: np.ndarray, u0: float, start: int,
                 omega: float, gain: float, lag: float, scale: float, max_steps: int = 1,
                 held_from: np.ndarray | None = None) -> None:
        # Field samples come unevenly (a PLC's clock, a busy link): the model is
        # run on an even grid, the PV interpolated and the MV averaged onto it.
        self.dt = max(float(np.median(np.diff(t[-_INTERVALS - 1:]))), (t[-1] - t[0]) / (_GRID_MAX - 1))
        grid = t[0] + self.dt * np.arange(int((t[-1] - t[0]) / self.dt + 1e-9) + 1)
        self.t, self.y = grid, np.interp(grid, t, y)
        self.u = held_mean(t if held_from is None else held_from, u, u0, grid, self.dt)
        self.u0, self.start = u0, int(np.searchsorted(grid, t[min(start, len(t) - 1)]))
        self.omega, self.gain, self.lag = omega, gain, lag
        self.n = max(int(round(2.0 * math.pi / omega / self.dt)), 1)
        self.max_steps = max_steps
        self.scale = scale
        self.runs = 0
        self._cache: dict[float, _Responses] = {}
        self._ends = _ends(self.n, len(grid))
        self._ones = np.ones(len(self._ends))
        # The model's inputs (the MV, a ramp, a unit step) behind zeros as long as the longest dead time
        # of any candidate (lag/ω, see _model) and the hold's sample: each candidate's delayed inputs
        # are a view, and one filter call runs all three.
        self._pad = int(max(lag, 0.0) / omega / self.dt) + 2
        self._inputs = np.zeros((3, self._pad + len(grid)))
        self._inputs[:, self._pad:] = (self.u - u0, grid - grid[0], np.ones(len(grid)))

    # -- one candidate model ----------------------------------------------

    def _free(self, x: float) -> np.ndarray:
        tc = first_order_model(x, self.gain, self.omega, self.lag)[1]
        # An integrator's free response is a constant: the offset already.
        return np.exp(-(self.t - self.t[0]) / tc) if math.isfinite(tc) else np.zeros(len(self.t))

    # An unstable candidate's responses can overflow; such a candidate gets an infinite residual
    # (non-finite averages, or r @ r = inf) and loses the search, so numpy's warnings are noise
    # (they reached `autotuner tune`'s stderr on every unstable plant).
    @np.errstate(over="ignore", invalid="ignore")
    def _responses(self, x: float) -> _Responses:
        cached = self._cache.get(x)
        if cached is None:
            self.runs += 1
            b, a, m = _filter(self.dt, x, self.gain, self.omega, self.lag)
            # y[k] is the output at sample k, before u[k] acts: one sample of delay (as _respond).
            start = self._pad - m - 1
            runs = scipy.signal.lfilter(b, a, self._inputs[:, start:start + len(self.t)], axis=1)
            np.subtract(self.y, runs[0], out=runs[0])  # the target: the PV less the model's answer to the MV
            total = np.zeros((3, len(self.t) + 1))
            np.cumsum(runs, axis=1, out=total[:, 1:])
            ends = self._ends
            target, ramp_mean = (total[:2, ends] - total[:2, ends - self.n]) / self.n
            # (A running sum's last value is finite only if every term was.)
            finite = bool(np.isfinite(total[:, -1]).all() and np.isfinite(target).all() and np.isfinite(ramp_mean).all())
            cached = self._cache[x] = _Responses(target, ramp_mean, total[2], ends, finite)
        return cached

    def _base(self, x: float, steps: tuple[int, ...], ramp: bool, free: bool) -> tuple[np.ndarray, np.ndarray]:
        """(averaged target, averaged regressors) for model ``x`` with the chosen terms."""
        r = self._responses(x)
        cols = [self._ones[:, None]]
        if steps:
            cols.append(r.step(np.array(steps, dtype=int), self.n))
        if ramp:
            cols.append(r.ramp[:, None])
        if free:
            cols.append(_average(self._free(x)[:, None], self.n))
        return r.target, np.hstack(cols)

    def _fitted(self, x: float, b: np.ndarray, a: np.ndarray, extra: int = 0) -> bool:
        """True when the record is long enough for these terms and their averages are finite."""
        if len(self.t) <= self.n + a.shape[1] + extra:
            return False
        # (Averages of finite running sums can still overflow: checked where the sums were not all finite.)
        return self._responses(x).finite or bool(np.all(np.isfinite(a)) and np.all(np.isfinite(b)))

    @staticmethod
    def _scaled(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(columns scaled to a largest value of 1, the scales): unstable models grow without bound, and
        scaled columns keep the least-squares problem well conditioned."""
        scale = np.maximum(np.max(np.abs(a), axis=0), 1e-300)
        return a / scale, scale

    @np.errstate(over="ignore", invalid="ignore")
    def _solve(self, x: float, steps: tuple[int, ...], ramp: bool, free: bool) -> tuple[float, np.ndarray]:
        """(residual sum of squares, coefficients) of the fit with model ``x`` and the chosen terms."""
        b, a = self._base(x, steps, ramp, free)
        if not self._fitted(x, b, a):
            return math.inf, np.zeros(a.shape[1])
        scaled, scale = self._scaled(a)
        coef, *_ = np.linalg.lstsq(scaled, b, rcond=None)
        coef = coef / scale
        r = b - a @ coef
        return float(r @ r), coef

    def _rss(self, x: float, steps: tuple[int, ...], ramp: bool, free: bool = False) -> float:
        """The residual sum of squares of :meth:`_solve`, without the coefficients: what the search compares.

        The last diagonal element of the QR factor of the scaled regressors with
        the target beside them is the residual's norm (LAPACK's factorisation
        called directly: a tenth of lstsq's cost, which the search spent most of
        its time in).
        """
        b, a = self._base(x, steps, ramp, free)
        if not self._fitted(x, b, a):
            return math.inf
        terms = a.shape[1]
        if len(b) <= terms:
            return 0.0  # as many averages as terms: fitted exactly
        matrix = np.empty((len(b), terms + 1), order="F")  # LAPACK's own order: factored in place
        matrix[:, :terms] = self._scaled(a)[0]
        matrix[:, terms] = b
        r = lapack.dgeqrf(matrix, overwrite_a=1)[0]
        diagonal = np.abs(np.diag(r)[:terms])
        if np.min(diagonal) <= _RANK * np.max(diagonal):
            # Nearly dependent columns (an unstable candidate's responses all grow as one exponential): QR
            # would fit the target along their rounding noise, lstsq leaves that direction out.
            return self._solve(x, steps, ramp, free)[0]
        rss = float(r[terms, terms] ** 2)
        return rss if math.isfinite(rss) else math.inf

    @np.errstate(over="ignore", invalid="ignore", divide="ignore")
    def _scan_step(self, x: float, steps: tuple[int, ...], ramp: bool, free: bool, ks: np.ndarray) -> np.ndarray:
        """Residual sums of squares with one more load step at each sample of ``ks``, all at once.

        Each candidate adds one column to the same regressors: its residual
        is what is left of the target, the others projected out, after the
        new column's own remainder is fitted to it.
        """
        b, a = self._base(x, steps, ramp, free)
        s = self._responses(x).step(ks, self.n)
        if not self._fitted(x, b, a, extra=1):
            return np.full(len(ks), math.inf)
        finite = np.all(np.isfinite(s), axis=0)
        s = np.nan_to_num(s)
        a = self._scaled(a)[0]
        rhs = np.column_stack((b, s / np.maximum(np.max(np.abs(s), axis=0), 1e-300)))
        r, tau = lapack.dgeqrf(a)[:2]
        diagonal = np.abs(np.diag(r))
        if np.min(diagonal) > _RANK * np.max(diagonal):
            q = lapack.dorgqr(r, tau)[0]
            rest = rhs - q @ (q.T @ rhs)
        else:  # nearly dependent columns: lstsq leaves their rounding noise out (see _rss)
            rest = rhs - a @ np.linalg.lstsq(a, rhs, rcond=None)[0]
        rb, rs = rest[:, 0], rest[:, 1:]
        norm = np.einsum("ij,ij->j", rs, rs)
        coef = np.where(norm > 0.0, (rs.T @ rb) / np.where(norm > 0.0, norm, 1.0), 0.0)
        # Summed from the residual vectors, not as |rb|² less the explained part: an
        # unstable candidate's sums are huge and their difference would cancel to nothing.
        sums = np.einsum("ij,ij->j", rb[:, None] - rs * coef, rb[:, None] - rs * coef)
        return np.where(finite & np.isfinite(sums), sums, math.inf)

    def misfit(self, num: tuple[float, ...], den: tuple[float, ...], delay: float) -> float:
        """How far the model ``num/den·e^{−delay·s}`` (``delay`` in s) alone, no load, misses the record's slow
        part: the root mean square of the one-period averages of the PV less its response to the MV from rest,
        an offset fitted (PV units; compare :meth:`averaged_rms`)."""
        b, a, _ = scipy.signal.cont2discrete((num, den), self.dt, method="zoh")
        m = int(round(delay / self.dt))
        u = np.concatenate((np.zeros(m + 1), self.u - self.u0))[: len(self.t)]
        r = _average((self.y - scipy.signal.lfilter(np.ravel(b), a, u))[:, None], self.n)[:, 0]
        r = r - r.mean()
        return float(np.sqrt(r @ r / len(r)))

    def averaged_rms(self, fit: LoadFit) -> float:
        """The root mean square of ``fit``'s one-period averaged residual over this record (PV units)."""
        return fit.residual_std * math.sqrt(max(len(self.t) - self.n, 1) / len(self._ends))

    # -- model selection ----------------------------------------------------

    # (An unstable candidate's residual can overflow: see _responses. Set once here for the search's many calls.)
    @np.errstate(over="ignore", invalid="ignore", divide="ignore")
    def fit(self, unstable: bool = False, near: LoadFit | None = None) -> LoadFit:
        """The best-explaining model: its x, the disturbance terms it needs, and their sizes.

        ``unstable`` searches x in (−1, 0] (an open-loop unstable process), otherwise in [0, 1).
        ``near``: an earlier fit of this record's start (a refit as the record grows). Its terms are
        kept and x and the step time are searched near its own (:meth:`_Search.near`), unless the
        record has moved away from it — x beyond the search, or a residual grown beyond ``_MISFIT``
        times its own (a second load): then the full search runs, as without ``near``.
        """
        lo, hi = (-_X_MAX, 0.0) if unstable else (0.0, _X_MAX)
        points = max((len(self.t) - self.n) / self.n * _POINTS_PER_PERIOD, 1.0)
        # Residuals below this are the model's own imperfection, not a disturbance to explain.
        criterion = _Criterion(points, points * (_RESOLUTION * self.scale) ** 2)
        if near is not None:
            model = _Search(self, lo, hi, criterion).near(near)
            if model is not None:
                fit = self._result(model, points)
                mismatch = _RESOLUTION * self.scale * math.sqrt(len(_ends(self.n, len(self.t))) /
                                                                 max(len(self.t) - self.n, 1))
                if fit.residual_std <= _MISFIT * near.residual_std + mismatch:
                    return fit
        return self._result(_Search(self, lo, hi, criterion).full(), points)

    def _result(self, model: _Model, points: float) -> LoadFit:
        """The fit of ``model``: its coefficients, the standard error of x from the residual's curvature."""
        x, steps, ramp, free = model.x, model.steps, model.ramp, model.free
        s, coef = self._solve(x, steps, ramp, free)
        # Curvature of the residual at the optimum: σ² of x ≈ 2·σ̂²/S''.
        h = 0.01 * max(abs(x), 0.02)
        s_lo, s_hi = self._solve(x - h, steps, ramp, free)[0], self._solve(x + h, steps, ramp, free)[0]
        curvature = (s_lo + s_hi - 2.0 * s) / (h * h)
        dof = max(points - len(coef) - 1.0, 1.0)
        sigma2 = s / dof
        x_std = math.sqrt(2.0 * sigma2 / curvature) if curvature > 0.0 else math.inf
        residual_std = math.sqrt(s / max(len(self.t) - self.n, 1))
        step_time, step = (float(self.t[steps[-1]]), float(coef[len(steps)])) if steps else (None, 0.0)
        j = 1 + len(steps)
        ramp_rate = float(coef[j]) if ramp else 0.0
        free_size = float(coef[j + ramp]) if free else 0.0
        x_used = 0.0 if abs(x) < 1e-4 else x
        static = math.inf if x_used == 0.0 else self.gain / x_used
        return LoadFit(x_used, x_std, static, float(coef[0]), step_time, step, ramp_rate, free_size, residual_std,
                       model.score)


class _Search:
    """One search of a fitter's record for the model that explains it best: x over [``lo``, ``hi``] and the
    load terms that pay for themselves by the information ``criterion`` (``fitter``: whose candidate models'
    residuals it compares)."""

    def __init__(self, fitter: LoadFitter, lo: float, hi: float, criterion: _Criterion) -> None:
        self.fitter = fitter
        self.lo, self.hi = lo, hi
        self.criterion = criterion

    def full(self) -> _Model:
        """The full search: x over [lo, hi] without and with a ramp, then load steps at any time.

        A term is searched only where it could pay for itself (:meth:`_Criterion.worth_a_term`): a
        quiet record's search ends after the first scan of x, with the answer the whole search gives.
        """
        best = self._without_steps()
        # Load steps: scan their time with the current x, then refine x.
        for _ in range(self.fitter.max_steps):
            first = self.fitter.start + self.fitter.n // 4
            last = len(self.fitter.t) - self.fitter.n // 2
            if last <= first or not self.criterion.worth_a_term(best.rss):
                break
            steps, ramp = best.steps, best.ramp
            # Index 0: a load acting from the start (the PV was not at rest).
            spacing = max(self.fitter.n // _STEP_GRID, 1, -(-(last - first) // _STEPS_MAX))
            ks = np.array([0, *range(first, last, spacing)])
            # Step time and x together on a coarse grid: the best step time
            # for a wrong x can be far from the right one.
            scans = [self.fitter._scan_step(float(xg), steps, ramp, False, ks)
                     for xg in np.linspace(self.lo, self.hi, _X_GRID)]
            cell = int(np.argmin([float(np.min(sums)) for sums in scans]))
            trial = int(ks[int(np.argmin(scans[cell]))])
            # Then x near the scan's best with the step time near the scan's at each x, to the sample (so that
            # its time does not hop between grid points from fit to fit).
            x, trial = self._x_and_step(steps, ramp, cell, trial, last, spacing)
            model = self._scored(x, steps + (trial,), ramp)
            if model.score >= best.score:
                break
            best = model
        return best

    def near(self, near: LoadFit) -> _Model | None:
        """The full search's model, with the step's time and x searched near ``near``'s instead of over a
        coarse scan of both: the step time within a quarter period of ``near``'s, x from the scan's
        points next to ``near``'s (:meth:`_near_x`). The ramp is chosen as the full search chooses it
        (without the step: a ramp can mimic a settling PV once the step explains the rest), the step kept
        where it pays for itself. None when ``near``'s x is outside [lo, hi] or uncertain (``_NEAR_STD``), or
        the best x lies beyond the search."""
        if not (self.lo <= near.x <= self.hi and near.x_std <= _NEAR_STD):
            return None
        best = self._without_steps()
        if near.step_time is None or not self.criterion.worth_a_term(best.rss):
            return best
        k = int(round((near.step_time - self.fitter.t[0]) / self.fitter.dt))
        # Within a quarter period of it: as far as two fits that agree may put it (LoadFollowing._agree).
        last, spacing = len(self.fitter.t) - self.fitter.n // 2, max(self.fitter.n // 4, 1)
        x: float | None = near.x
        # The step time at the earlier x, x with it, the step time again at that x and x once more: the
        # full search's refinement after its scan. (A load from the start stays there: the full search
        # puts no step between it and the relay's start.)
        for _ in range(2):
            if k:
                k = self._step_near(x, (), best.ramp, k, last, spacing)
            x = self._near_x((k,), best.ramp, x)
            if x is None:
                return None
        model = self._scored(x, (k,), best.ramp)
        return model if model.score < best.score else best

    def _without_steps(self) -> _Model:
        """The best model without load steps: x over [lo, hi] without and with a ramp (the ramp only where it
        could pay for itself)."""
        # The free response of the lag (a PV still settling at the start) is
        # left out of the search: over a few periods it is nearly a ramp or an
        # offset, and with a long lag it is ill-conditioned against both.
        best = self._scored(self._best_x((), False, False)[0], (), False)
        if not self.criterion.worth_a_term(best.rss):
            return best
        ramp = self._scored(self._best_x((), True, False)[0], (), True)
        return ramp if ramp.score < best.score else best

    def _scored(self, x: float, steps: tuple[int, ...], ramp: bool) -> _Model:
        """The model ``x`` with these terms, its residual and criterion."""
        rss = self.fitter._rss(x, steps, ramp)
        return _Model(rss, self.criterion.score(rss, 1 + len(steps) + ramp), x, steps, ramp)

    def _best_x(self, steps: tuple[int, ...], ramp: bool, free: bool,
                best: int | None = None) -> tuple[float, float]:
        """The x in [lo, hi] of the least residual (a coarse scan, then a search near its best point;
        ``best``: the scan's best point when known already)."""
        grid = np.linspace(self.lo, self.hi, _X_GRID)
        i = int(np.argmin([self.fitter._rss(float(x), steps, ramp, free) for x in grid])) if best is None else best
        x = _minimize(lambda v: self.fitter._rss(v, steps, ramp, free), float(grid[max(i - 1, 0)]),
                      float(grid[min(i + 1, len(grid) - 1)]))
        return x, self.fitter._rss(x, steps, ramp, free)

    def _near_x(self, steps: tuple[int, ...], ramp: bool, x0: float) -> float | None:
        """The x of the least residual near ``x0``, found as the full search finds it but from the scan's
        points next to ``x0`` only; None when it lies at the edge of their cells (the least is beyond).

        The residual can have shallow minima a few thousandths apart (where the dead time crosses a
        sample); searched from the full search's cells, a refit settles in the minimum the full search
        would, instead of one near wherever the earlier fit had stopped.
        """
        grid = np.linspace(self.lo, self.hi, _X_GRID)
        nearest = int(np.argmin(np.abs(grid - x0)))
        i = min(range(max(nearest - 1, 0), min(nearest + 2, len(grid))),
                key=lambda j: self.fitter._rss(float(grid[j]), steps, ramp))
        a, b = float(grid[max(i - 1, 0)]), float(grid[min(i + 1, len(grid) - 1)])
        x = _minimize(lambda v: self.fitter._rss(v, steps, ramp), a, b)
        if (a > self.lo and x - a < _X_TOL) or (b < self.hi and b - x < _X_TOL):
            return None
        return x

    def _x_and_step(self, steps: tuple[int, ...], ramp: bool, cell: int, k: int, last: int,
                    spacing: int) -> tuple[float, int]:
        """(x, step sample) of the least residual with one more load step: x within the scan's cells next to
        ``cell``, the step within ``spacing`` of the scan's ``k`` (and before ``last``) at each x.

        Searched together, not in turn: x refined at the scan's step time and
        the step time then at that x stop in a valley's side (a step at 0.8
        periods on ``exp(-s)/(2*s+1)``, between the scan's grid points: 0.82
        and K0 0.947; together 0.80 and 1.000). A load from the start (``k`` 0)
        stays there.
        """
        near = np.arange(max(k - spacing, 0), min(k + spacing + 1, last)) if k else np.array([0])
        if not len(near):
            near = np.array([k])

        def least(v: float) -> float:
            return float(np.min(self.fitter._scan_step(v, steps, ramp, False, near)))

        grid = np.linspace(self.lo, self.hi, _X_GRID)
        x = _minimize(least, float(grid[max(cell - 1, 0)]), float(grid[min(cell + 1, len(grid) - 1)]))
        return x, int(near[int(np.argmin(self.fitter._scan_step(x, steps, ramp, False, near)))])

    def _step_near(self, x: float, steps: tuple[int, ...], ramp: bool, k: int, last: int, spacing: int) -> int:
        """The sample within ``spacing`` of ``k`` (and before ``last``) where a load step fits best."""
        near = np.arange(max(k - spacing, 0), min(k + spacing + 1, last))
        if not len(near):
            return k
        return int(near[int(np.argmin(self.fitter._scan_step(x, steps, ramp, False, near)))])
