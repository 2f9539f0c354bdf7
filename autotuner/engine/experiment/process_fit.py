"""A process model fitted to the record by least squares: two lags and a dead time, to aim the phase filter.

``K0·e^{−Ls}/((T1·s + 1)(T2·s + 1))`` (``T1 ≥ T2 ≥ 0``) from
the MV as the process held it to the PV as measured, over the whole record
(the noise stage's rest and the relay's first period and a half: the start's
transient is what tells the lags from the dead time). K0 and the PV's level
enter linearly and are solved for at each trial of the three others (variable
projection); those three by a bounded least-squares search from the first
period's scale. The model only aims the filter (adaptation.py): the point is
still estimated from the PV as measured and judged by the stopping rules.

:func:`fit_load` explains a load at the process input too, for the model rule
(model_rule.py), where the plain model misfits: a ramp from the record's start
(with a step there) or a step at a time of its own, through the same lags and
dead time, each one more linear regressor (its coefficient K0 × the load); the
step's time one more parameter of the search, started from a scan.

Times in s, gains in PV per MV unit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from autotuner.engine.experiment.record import Samples

DOUBLE = 0.999  # lags closer than this ratio are one double pole
# A PV that first moves against the MV's step by more than this share of its swing has an inverse response (the
# batch's (1-a*s)/(s+1)^3: 0.1 % at a = 0.1, 3.2 % at 0.5, 7.8 % at 0.9; every other process 0).
INVERSE = 0.01
# ... and by more than this many of the noise's standard deviations: the PV is compared with one noisy sample, so the
# differences scatter by σ·√2, and a hundred of them reach 3σ one run in two (the fit under noise gave up on a
# first-order process that often); this many, one in a thousand.
NOISE_SIGMAS = 6.0
# The most changes of the held MV the fit takes (each relay switch makes two: its blended sample and the level;
# an MV rate limit's ramps make more): the fit's cost grows with them.
MAX_STEPS = 40
ITERATIONS = 12  # Levenberg–Marquardt's at most (each about five runs of the model over the record)
SETTLED = 1e-3  # a step gaining less than this share of the cost ends the search
# A search started from an earlier switch's model stands where it misfits by at most this share of the swing (over
# three times the model rule's bound: model_rule.py); elsewhere the search from the period's scale does, as without
# an earlier model (the filter's aim on the batch's higher orders is the same).
WARM = 1e-3
# The spread's covariance leaves out the directions whose singular values are below this share of the largest (of
# the Jacobian's normal matrix, its columns scaled to unit length).
RCOND = 1e-7
# The candidate times of a load step a scan tries at most (fit_load: each a column of the record's length).
SCAN = 200


@dataclass(frozen=True)
class ProcessModel:
    """``K0·e^{−Ls}/((T1·s + 1)(T2·s + 1))``: ``k0`` (PV per MV unit), ``t1`` ≥ ``t2`` ≥ 0 and ``delay`` (s);
    ``misfit``: the fit's RMS residual as a share of the PV's swing over the record. A load at the process input
    the fit explained too (:func:`fit_load`): a ramp from the record's ``start`` (s) of ``ramp`` MV units per s
    and a step of ``step`` MV units at ``step_time`` (s: the start where the ramp is fitted, its own time
    elsewhere); none on a plain fit (``step_time`` None)."""

    k0: float
    t1: float
    t2: float
    delay: float
    misfit: float
    start: float = 0.0
    ramp: float = 0.0
    step: float = 0.0
    step_time: float | None = None

    @property
    def loaded(self) -> bool:
        """True when the fit explained a load at the process input."""
        return self.ramp != 0.0 or self.step_time is not None

    def load_at(self, t: float) -> float:
        """The fitted load at the process input at time ``t`` (s), MV units."""
        load = self.ramp * (t - self.start)
        return load + self.step if self.step_time is not None and t >= self.step_time else load

    def response(self, w: np.ndarray) -> np.ndarray:
        """F(jω) at the frequencies ``w`` (rad/s)."""
        jw = 1j * w
        return self.k0 * np.exp(-jw * self.delay) / ((1.0 + jw * self.t1) * (1.0 + jw * self.t2))

    def lag(self, omega: float) -> float:
        """The phase lag at ``omega`` (rad/s), radians (K0 > 0)."""
        return math.atan(omega * self.t1) + math.atan(omega * self.t2) + omega * self.delay

    def frequency(self, lag: float) -> float | None:
        """The frequency (rad/s) where the model lags by ``lag`` (radians), or None where it never does."""
        if self.delay <= 0.0 and lag >= (math.pi if self.t2 > 0.0 else math.pi / 2.0):
            return None
        lo, hi = 0.0, 1.0 / max(self.t1, self.delay, 1e-12)
        for _ in range(200):  # (a dead time of a hair lags by π only far up: bounded)
            if self.lag(hi) >= lag:
                break
            lo, hi = hi, 2.0 * hi
        else:
            return None
        for _ in range(60):  # bisection: the lag rises with ω
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if self.lag(mid) < lag else (lo, mid)
        return 0.5 * (lo + hi)


def step_response(t: np.ndarray, t1: float, t2: float) -> np.ndarray:
    """The unit step response of ``1/((t1·s + 1)(t2·s + 1))`` (``t1`` > ``t2`` ≥ 0, s) at the times ``t`` (s)
    after the step (zero before it)."""
    t = np.maximum(t, 0.0)
    if t2 <= 1e-9 * t1:
        return -np.expm1(-t / t1)
    if t2 >= DOUBLE * t1:  # (a double pole: the difference below would lose its digits)
        tc = 0.5 * (t1 + t2)
        return 1.0 - (1.0 + t / tc) * np.exp(-t / tc)
    return 1.0 - (t1 * np.exp(-t / t1) - t2 * np.exp(-t / t2)) / (t1 - t2)


def ramp_response(t: np.ndarray, t1: float, t2: float) -> np.ndarray:
    """The response of ``1/((t1·s + 1)(t2·s + 1))`` (``t1`` > ``t2`` ≥ 0, s) to a ramp of unit rate at its input,
    at the times ``t`` (s) after the ramp's start (zero before it): the integral of :func:`step_response`."""
    t = np.maximum(t, 0.0)
    if t2 <= 1e-9 * t1:
        return t + t1 * np.expm1(-t / t1)
    if t2 >= DOUBLE * t1:
        tc = 0.5 * (t1 + t2)
        return t - 2.0 * tc + (t + 2.0 * tc) * np.exp(-t / tc)
    return t - (t1 + t2) + (t1 * t1 * np.exp(-t / t1) - t2 * t2 * np.exp(-t / t2)) / (t1 - t2)


def _unit_response(times: np.ndarray, steps: tuple[np.ndarray, np.ndarray], params: np.ndarray) -> np.ndarray:
    """The unit-gain model's output at ``times`` (s) for the input's ``steps`` (their times, s, and sizes) and
    ``params`` = (ln Ta, ln Tb, L), the lags in either order: a sum of step responses, one per change of the held
    input."""
    t1, t2 = _lags(params)
    at, size = steps
    # (A sum over the few steps, not a matrix product: BLAS's threads cost more than the sum on so few.)
    return (step_response(times[None, :] - at[:, None] - params[2], t1, t2) * size[:, None]).sum(axis=0)


def _project(y: np.ndarray, unit: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(residual, K0, level) of the best ``level + K0·unit`` through ``y``."""
    du = unit - unit.mean()
    spread = float(du @ du)
    k0 = float(du @ y) / spread if spread > 0.0 else 0.0
    level = float(y.mean()) - k0 * float(unit.mean())
    return y - level - k0 * unit, k0, level


def inverse_response(y: np.ndarray, size: np.ndarray, noise: float) -> bool:
    """True when the PV ``y`` (PV units, a sample per held MV) moved against the MV's first step (``size``: the
    held MV's change at each sample, MV units, the relay's start first) before the relay's first switch, by more
    than INVERSE of its swing and NOISE_SIGMAS noise standard deviations (``noise``, PV units): a zero in the right
    half-plane, which lags and dead time cannot model (the cycle's phase balance came out 0.8° off on
    ``(1-0.9*s)/(s+1)^3``, where the secant's first step landed within 0.2°)."""
    changes = np.nonzero(size)[0]
    first = changes[0]
    # (The first switch: the next change but the start's own; a switch is its blended sample and the level.)
    later = changes[changes > first + 1]
    before = y[first:later[0] if len(later) else len(y)] - y[first]
    against = float(np.max(-np.sign(size[first]) * before))
    return against > max(INVERSE * float(np.ptp(y)), NOISE_SIGMAS * noise)


def fit(history: Samples, mv0: float, period: float, noise: float = 0.0,
        start: ProcessModel | None = None, enough: float = WARM) -> ProcessModel | None:
    """The model through the record ``history`` (the MV's deviations from ``mv0``, MV units, as held), the
    first whole period ``period`` (s) setting the search's scale; None where the record does not move or shows
    an inverse response (:func:`inverse_response`, ``noise``: the PV's noise standard deviation, PV units).

    ``start``: a model fitted to the same record at an earlier switch. The search starts from it first, and
    its result stands where it misfits by at most ``enough`` (a share of the PV's swing; WARM by default: a slow
    process's cold searches settle in a local minimum one switch in two, ``exp(-s)/(10*s+1)^2`` misfit 1e-7, then
    2e-2, then 1e-7; under noise, about the earlier model's misfit); elsewhere the search starts from the period's
    scale as without one."""
    problem = _Problem.of(history, mv0, period)
    if problem is None or inverse_response(history.y, np.diff(history.u, prepend=mv0), noise):
        return None
    y, t, steps = problem.y, problem.t, problem.steps

    def residual(params: np.ndarray) -> np.ndarray:
        return _project(y, _unit_response(t, steps, params))[0]

    lower, upper, step = problem.lower, problem.upper, problem.step

    def search(x: np.ndarray) -> ProcessModel:
        found = _levenberg_marquardt(residual, np.clip(x, lower, upper), lower, upper, step)
        res, k0, _ = _project(y, _unit_response(t, steps, found))
        t1, t2 = _lags(found)
        return ProcessModel(k0, t1, t2, float(found[2]), problem.misfit(res))

    if start is not None and start.t1 > 0.0:
        warm = search(_params(start))
        if warm.misfit <= enough:
            return warm
    scale = problem.scale
    return search(np.array([math.log(scale), math.log(0.3 * scale), 0.25 * period]))


@dataclass(frozen=True)
class _Problem:
    """A record to fit: sample times ``t`` (s) and PV ``y``, the held input's ``steps`` (their times, s, and sizes,
    MV units) from mv0, the PV's ``swing`` (its range) and the search's scale (s) and bounds on (ln Ta, ln Tb, L)
    and its difference steps."""

    t: np.ndarray
    y: np.ndarray
    steps: tuple[np.ndarray, np.ndarray]
    swing: float
    scale: float
    period: float

    @staticmethod
    def of(history: Samples, mv0: float, period: float) -> _Problem | None:
        """The problem of the record ``history`` (the MV's deviations from ``mv0``, MV units, as held), its first
        whole ``period`` (s); None where the record does not move or its input changed too often (MAX_STEPS)."""
        swing = float(np.ptp(history.y))
        # The held input as steps from mv0 (the relay's switches and their blended samples).
        size = np.diff(history.u, prepend=mv0)
        moved = size != 0.0
        if swing <= 0.0 or not 0 < int(np.count_nonzero(moved)) <= MAX_STEPS:
            return None
        return _Problem(history.t, history.y, (history.s[moved], size[moved]), swing, period / (2.0 * math.pi),
                        period)

    @property
    def lower(self) -> np.ndarray:
        """The lower bounds of (ln Ta, ln Tb, L)."""
        return np.array([math.log(self.scale) - 8.0, math.log(self.scale) - 8.0, 0.0])

    @property
    def upper(self) -> np.ndarray:
        """The upper bounds of (ln Ta, ln Tb, L)."""
        return np.array([math.log(self.scale) + 8.0, math.log(self.scale) + 8.0, self.period])

    @property
    def step(self) -> np.ndarray:
        """The forward differences' steps of (ln Ta, ln Tb, L)."""
        return np.array([1e-4, 1e-4, 1e-4 * self.scale])

    def misfit(self, residual: np.ndarray) -> float:
        """The RMS of ``residual`` (PV units) as a share of the swing."""
        return float(np.sqrt(np.mean(residual * residual))) / self.swing


def _lags(params: np.ndarray) -> tuple[float, float]:
    """(T1, T2), T1 ≥ T2 (s), of ``params`` = (ln Ta, ln Tb, …)."""
    t1, t2 = sorted((math.exp(params[0]), math.exp(params[1])), reverse=True)
    return t1, t2


def _params(model: ProcessModel) -> np.ndarray:
    """(ln T1, ln T2, L) of ``model`` (a pure lag's T2 a hair above zero)."""
    return np.array([math.log(model.t1), math.log(max(model.t2, 1e-9 * model.t1)), model.delay])


def fit_load(history: Samples, mv0: float, period: float, plain: ProcessModel, enough: float,
             start: ProcessModel | None = None) -> ProcessModel | None:
    """The model with a load at the process input through the record ``history`` (the MV's deviations from ``mv0``,
    MV units, as :func:`fit`; ``period``: the latest whole period, s, the search's scale), where the ``plain``
    model (:func:`fit`'s, on the same record) misfits: a ramp from the record's start, or a step at a time of its
    own, through the model's lags and dead time; None where the record cannot be fitted.

    Each load is one more linear regressor (the model's response to it, its coefficient K0 × the load), solved
    for with K0 and the PV's level at each trial; the step's time is one more nonlinear parameter, started from
    the best of a scan of candidate times at the plain model's lags. The searches start from ``start`` (a model
    fitted to the same record at an earlier switch) where it has a load, then the ramp, then the scanned step
    (both from the plain model's lags or ``start``'s, whichever explains more), until one misfits by at most
    ``enough`` (a share of the PV's swing); the best of them."""
    problem = _Problem.of(history, mv0, period)
    if problem is None:
        return None

    def cost(x: np.ndarray) -> float:
        return float(np.sum(_loaded_residual(problem, x)[0] ** 2))

    # The lags and dead time to start from: the plain model's, or the earlier model's where they explain more (a
    # plain search that lost the earlier switch's exact model to a load settles far from it).
    bases = [_params(plain)] + ([_params(start)] if start is not None else [])
    tries = [lambda: min(bases, key=cost), lambda: min((np.append(b, _scan_step(problem, b)) for b in bases), key=cost)]
    if start is not None and start.loaded:
        warm = _params(start)
        # (A fitted ramp is never exactly nought: the ramp's model, else the step's.)
        tries.insert(0, lambda: warm if start.ramp != 0.0 else np.append(warm, start.step_time))
    best: ProcessModel | None = None
    for x in tries:
        model = _search_load(problem, x())
        if model is not None and (best is None or model.misfit < best.misfit):
            best = model
        if best is not None and best.misfit <= enough:
            break
    return best


def _search_load(problem: _Problem, x: np.ndarray) -> ProcessModel | None:
    """The load model (:func:`fit_load`) the search from ``x`` (ln Ta, ln Tb, L[, t_s]) finds; None where it has
    no gain."""
    lower, upper, step = problem.lower, problem.upper, problem.step
    if len(x) == 4:  # (the step's time: from the record's start to its end)
        lower = np.append(lower, problem.t[0])
        upper = np.append(upper, problem.t[-1])
        step = np.append(step, 1e-4 * problem.scale)
    found = _levenberg_marquardt(lambda p: _loaded_residual(problem, p)[0], np.clip(x, lower, upper), lower, upper,
                                 step)
    res, coef = _loaded_residual(problem, found)
    k0 = float(coef[0])
    if k0 == 0.0:
        return None
    t1, t2 = _lags(found)
    start = float(problem.t[0])
    model = ProcessModel(k0, t1, t2, float(found[2]), problem.misfit(res), start=start)
    if len(found) == 4:
        return replace(model, step=float(coef[1]) / k0, step_time=float(found[3]))
    return replace(model, ramp=float(coef[1]) / k0, step=float(coef[2]) / k0, step_time=start)


def _load_columns(problem: _Problem, params: np.ndarray) -> np.ndarray:
    """The unit-gain model's responses to its load's parts at the record's times: with ``params`` = (ln Ta, ln Tb,
    L), a ramp of unit rate from the record's start and a unit step there (the ramp's start is known to a sample:
    a load held at each sample is a ramp half a sample late, and a drift's phase in its samples is unknown); with
    (…, t_s), a unit step at t_s (s)."""
    t1, t2 = _lags(params)
    if len(params) == 3:
        since = problem.t - problem.t[0] - params[2]
        return np.vstack((ramp_response(since, t1, t2), step_response(since, t1, t2)))
    return step_response(problem.t - params[3] - params[2], t1, t2)[None, :]


def _loaded_residual(problem: _Problem, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(residual, coefficients) of the best ``level + K0·unit + K0·Σ loadᵢ·columnᵢ`` through the PV at ``params``
    (:func:`_load_columns`); the coefficients K0 and K0·loadᵢ."""
    columns = np.vstack((_unit_response(problem.t, problem.steps, params[:3]), _load_columns(problem, params)))
    centred = columns - columns.mean(axis=1)[:, None]
    y = problem.y - problem.y.mean()
    # (lstsq: a step after the record's end leaves its column zero.)
    coef = np.linalg.lstsq(centred @ centred.T, centred @ y, rcond=1e-12)[0]
    return y - coef @ centred, coef


def _scan_step(problem: _Problem, params: np.ndarray) -> float:
    """The time (s) of a load step at the input that best explains what the model of ``params`` (ln Ta, ln Tb, L)
    leaves of the record, among at most SCAN of the sample times (those whose step reaches the PV before the
    record's end)."""
    t, y = problem.t, problem.y
    candidates = t[t < t[-1] - params[2]]
    if len(candidates) == 0:
        return float(t[-1])
    candidates = candidates[::max(1, math.ceil(len(candidates) / SCAN))]
    t1, t2 = _lags(params)
    columns = step_response(t[None, :] - candidates[:, None] - params[2], t1, t2)
    # Project the level and the relay's response out of the PV and of each candidate's column: what each explains
    # of the rest is (column · rest)² / |column|².
    unit = _unit_response(t, problem.steps, params)
    unit = unit - unit.mean()
    unit /= math.sqrt(float(unit @ unit)) or 1.0
    rest = y - y.mean()
    rest = rest - unit * float(unit @ rest)
    columns -= columns.mean(axis=1)[:, None]
    columns -= np.outer(columns @ unit, unit)
    norms = np.einsum("ij,ij->i", columns, columns)
    explained = np.where(norms > 0.0, (columns @ rest) ** 2 / np.where(norms > 0.0, norms, 1.0), 0.0)
    return float(candidates[int(np.argmax(explained))])


def _levenberg_marquardt(residual: Callable[[np.ndarray], np.ndarray], x: np.ndarray, lower: np.ndarray,
                         upper: np.ndarray, step: np.ndarray) -> np.ndarray:
    """The parameters within [``lower``, ``upper``] that least-squares minimise ``residual``, from ``x``:
    Levenberg–Marquardt with forward differences of ``step``, at most ITERATIONS iterations (a few residuals
    each; scipy's general solver costs ten times as much on three parameters)."""
    r = residual(x)
    cost, damping = float(r @ r), 1e-3
    floor = 1e-24 * cost
    for _ in range(ITERATIONS):
        jac = np.empty((len(r), len(x)))
        for i in range(len(x)):
            moved = x.copy()
            moved[i] += step[i] if moved[i] + step[i] <= upper[i] else -step[i]
            jac[:, i] = (residual(moved) - r) / (moved[i] - x[i])
        normal, gradient = jac.T @ jac, jac.T @ r
        while damping < 1e4:
            trial = np.clip(x - np.linalg.solve(normal + damping * np.diag(np.diag(normal) + 1e-12), gradient),
                            lower, upper)
            r_trial = residual(trial)
            cost_trial = float(r_trial @ r_trial)
            if cost_trial < cost:
                # (Settled: a step that gains less than SETTLED of the cost moves the aim far less than the
                # stopping rule's phase tolerance; or a fit within rounding.)
                done = cost - cost_trial < SETTLED * cost or cost_trial < floor
                x, r, cost, damping = trial, r_trial, cost_trial, damping / 3.0
                break
            damping *= 4.0
        else:
            return x
        if done:
            return x
    return x


@dataclass(frozen=True)
class Spread:
    """How surely a fit's point stands under measurement noise (:func:`spread`): ``point``, the standard error of F
    at the target lag relative to |F| (its real and imaginary parts' together); ``correlation``, the residual's
    lag-1 autocorrelation (a model that holds the process leaves the noise, near 0 where it is white, within a
    few of 1/√``samples``; one that misses it leaves a smooth residual, near 1); ``samples``, the record's."""

    point: float
    correlation: float
    samples: int


def spread(history: Samples, mv0: float, period: float, model: ProcessModel, lag: float) -> Spread | None:
    """The :class:`Spread` of the point at ``lag`` (radians) of ``model``, fitted (:func:`fit` or :func:`fit_load`)
    to the record ``history`` (the MV's deviations from ``mv0``, MV units; ``period``: the fit's scale, s); None
    where the record is not a problem (:func:`_Problem.of`) or the model never lags that much.

    The standard error is the linearised least squares': the covariance σ²(JᵀJ)⁻¹ of every parameter (the lags,
    the dead time, a load step's time, K0, the loads' coefficients, the PV's level), σ² the residual's variance,
    carried to F through its gradient in the lags, the dead time and K0."""
    problem = _Problem.of(history, mv0, period)
    omega = model.frequency(lag)
    if problem is None or omega is None:
        return None
    # (In the lags themselves, not their logarithms: a lag near nought moves the PV and F by a derivative the
    # logarithm's scales to nothing, and the covariance of its logarithm, which its gradient's scale cancels,
    # comes out of a near-singular matrix.)
    physical = np.concatenate(([model.t1, model.t2, model.delay], _search_params(model)[3:]))
    loaded = model.loaded

    def columns(x: np.ndarray) -> np.ndarray:
        search = np.concatenate((np.log(np.maximum(x[:2], 1e-12 * x[0])), x[2:]))
        unit = _unit_response(problem.t, problem.steps, search[:3])[None, :]
        return np.vstack((unit, _load_columns(problem, search))) if loaded else unit

    coef = np.array([model.k0] + _load_coefficients(model))
    fitted = coef @ columns(physical)
    step = 1e-4 * problem.scale
    moved = [np.where(np.arange(len(physical)) == i, step, 0.0) for i in range(len(physical))]
    jac = np.vstack([(coef @ columns(physical + m) - fitted) / step for m in moved]
                    + list(columns(physical)) + [np.ones(len(problem.t))]).T
    residual = problem.y - fitted
    residual = residual - residual.mean()  # (the level: solved for with the others)
    dof = max(len(residual) - jac.shape[1], 1)
    # (Directions the record cannot tell apart — two lags and the dead time all short of a sample interval — are
    # left out: F at the cycle's frequencies does not tell them apart either, and the inverse of a near-singular
    # matrix carried rounding to it, 3-10 times its error.)
    norm = np.linalg.norm(jac, axis=0)
    norm[norm == 0.0] = 1.0
    cov = float(residual @ residual) / dof * np.linalg.pinv((jac / norm).T @ (jac / norm), rcond=RCOND,
                                                             hermitian=True) / np.outer(norm, norm)
    value = complex(model.response(np.array([omega]))[0])
    gradient = np.zeros((2, jac.shape[1]))
    for i in range(3):  # (a load step's time does not move F)
        t1, t2, delay = physical[:3] + moved[i][:3]
        w = replace(model, t1=t1, t2=t2, delay=delay).frequency(lag)
        d = (complex(replace(model, t1=t1, t2=t2, delay=delay).response(np.array([w]))[0]) - value) / step \
            if w is not None else 0.0
        gradient[:, i] = d.real, d.imag
    gradient[:, len(physical)] = (value / model.k0).real, (value / model.k0).imag
    point = math.sqrt(max(float(np.trace(gradient @ cov @ gradient.T)), 0.0)) / abs(value)
    correlation = float(residual[1:] @ residual[:-1]) / max(float(residual @ residual), 1e-300)
    return Spread(point, correlation, len(residual))


def _search_params(model: ProcessModel) -> np.ndarray:
    """The search's parameters of ``model``: (ln T1, ln T2, L), and a load step's time where it fitted one at a
    time of its own (not a ramp's)."""
    if model.loaded and model.ramp == 0.0:
        return np.append(_params(model), model.step_time)
    return _params(model)


def _load_coefficients(model: ProcessModel) -> list[float]:
    """The load columns' coefficients (K0 × the load's parts, :func:`_load_columns`) of ``model``."""
    if not model.loaded:
        return []
    if model.ramp == 0.0:
        return [model.k0 * model.step]
    return [model.k0 * model.ramp, model.k0 * model.step]
