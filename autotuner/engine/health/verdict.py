"""Verdicts in plain words: the flags of a loop, each with a severity and a one-line reason, and one
recommendation.

Flags: ``manual``, ``saturated``, ``oscillating``, ``stiction``, ``sluggish``, ``noisy``, ``frozen_pv``,
``poor_tracking``. Recommendations: ``retune``, ``check_valve``, ``check_sensor``, ``put_in_auto``, ``none``.
A loop whose oscillation comes from its valve is sent to the valve, never to retuning: new gains do not cure a
sticking valve, and tighter ones make its cycle worse.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from autotuner.engine.described import described
from autotuner.engine.health.indices import Indices
from autotuner.engine.health.oscillation import Oscillation
from autotuner.engine.health.sluggish import OFFSET, SLOW_RECOVERY, SLUGGISH
from autotuner.engine.health.stiction import HORCH_EVEN, SHAPE_SINE, SHAPE_TRIANGLE

FLAGS = ("manual", "saturated", "oscillating", "stiction", "sluggish", "noisy", "frozen_pv", "poor_tracking")
RECOMMENDATIONS = ("retune", "check_valve", "check_sensor", "put_in_auto", "none")

MANUAL = 0.9  # utilization below this: flagged manual
SATURATED = 0.05  # share at a limit above this: flagged saturated
FROZEN = 0.25  # PV unchanged over this share of the window: flagged frozen
NOISY = 0.01  # noise σ above this share of the span (PV's or MV's): flagged noisy
OVERSHOOT = 30.0  # mean overshoot above this, %: poor tracking
SETTLING_PERIODS = 10.0  # settling slower than this many ultimate periods: poor tracking


class Severity(str, Enum):
    LOW = "low"
    MEDIUM = "medium"
    HIGH = "high"


def _grade(value: float, medium: float, high: float) -> Severity:
    """LOW below ``medium``, MEDIUM below ``high``, HIGH from there on."""
    return Severity.HIGH if value >= high else Severity.MEDIUM if value >= medium else Severity.LOW


@dataclass(frozen=True)
class Flag:
    """One thing wrong with the loop."""

    name: str = described("the flag: manual, saturated, oscillating, stiction, sluggish, noisy, frozen_pv or "
                          "poor_tracking", example="stiction")
    severity: Severity = described("low, medium or high", example="medium")
    reason: str = described("why, in one line", example="oscillates with period 42 s and amplitude 1.8: PV "
                            "half-cycles triangular, as a sticking valve makes")


@dataclass(frozen=True)
class Context:
    """What the verdicts weigh the indices against: ``a`` the significant deviation (PV units), ``pv_span``
    (PV units, None: unknown), ``mv_span`` (MV units), ``tu`` the ultimate period (s, None: no model),
    ``integrating`` (None: unknown), ``window`` the assessed duration (s), ``pv_unit`` for the reasons."""

    a: float
    pv_span: float | None
    mv_span: float
    tu: float | None
    integrating: bool | None
    window: float
    pv_unit: str = ""


def is_stiction(ind: Indices, integrating: bool | None) -> bool:
    """The valve sticks. Around an integrating process (the model says so): the PV's half-cycles are
    triangular (the shape test). Otherwise: MV and PV do not correlate evenly (Horch: the loop's own
    oscillation through aggressive gains correlates evenly) and the PV is no sine (an external sinusoid, the
    other cause of an uneven correlation, is).

    ``ind``: the indices; ``integrating``: the model is integrating (None: no model).
    """
    shape, horch = ind.shape_index, ind.ccf_zero_lag
    if shape is None:
        return False
    if integrating:
        return shape > SHAPE_TRIANGLE
    return horch is not None and horch < HORCH_EVEN and shape > SHAPE_SINE


def _n(x: float) -> str:
    return f"{x:.3g}"


def _oscillation_reason(ind: Indices, ctx: Context, stiction: bool) -> str:
    unit = f" {ctx.pv_unit}" if ctx.pv_unit else ""
    head = (f"oscillates with period {_n(ind.oscillation_period or 0.0)} s and amplitude "
            f"{_n(ind.oscillation_amplitude or 0.0)}{unit}")
    if stiction and ctx.integrating:
        return f"{head}: PV half-cycles triangular (shape index {ind.shape_index:.2f}), as a sticking valve makes"
    if stiction:
        return (f"{head}: MV and PV cross-correlation not even (ρ0 {ind.ccf_zero_lag:.2f}) and the PV no sine "
                f"(shape index {ind.shape_index:.2f}), as a sticking valve makes")
    if ind.ccf_zero_lag is not None and ind.ccf_zero_lag >= HORCH_EVEN:
        return (f"{head}: MV and PV cross-correlation even (ρ0 {ind.ccf_zero_lag:.2f}), as aggressive tuning "
                "makes")
    if ind.shape_index is None:
        return f"{head}: too few samples per cycle to tell a sticking valve from aggressive tuning"
    return (f"{head}: PV sinusoidal (shape index {ind.shape_index:.2f}), as an external disturbance or aggressive "
            "tuning makes")


def flags(ind: Indices, osc: Oscillation | None, ctx: Context) -> list[Flag]:
    """The flags the indices raise (``osc``: the error's oscillation, None when never in automatic).

    ``ind``: the indices; ``ctx``: what the record says of the loop.
    """
    out: list[Flag] = []
    if ind.utilization < MANUAL:
        out.append(Flag("manual", _grade(1.0 - ind.utilization, 0.25, 0.5),
                        f"in manual {100.0 * (1.0 - ind.utilization):.0f} % of the window"))
    if ind.frozen_share >= FROZEN:
        out.append(Flag("frozen_pv", _grade(ind.frozen_share, 0.5, 0.9),
                        f"the PV did not change at all for {ind.frozen_share * ctx.window:.0f} s "
                        f"({100.0 * ind.frozen_share:.0f} % of the window): a frozen sensor or transmission"))
    saturated = ind.saturation is not None and ind.saturation > SATURATED
    if saturated:
        out.append(Flag("saturated", _grade(ind.saturation or 0.0, 0.2, 0.5),
                        f"the MV sat at a limit {100.0 * (ind.saturation or 0.0):.0f} % of the time in automatic"))
    oscillating = osc is not None and osc.oscillating
    if oscillating:
        out += _oscillation(ind, ctx)
    else:
        if not saturated:  # a saturated valve makes any loop slow: not the tuning's fault
            out += _sluggish(ind, ctx)
        out += _noisy(ind, ctx)  # (a fast oscillation's samples look like noise)
    out += _tracking(ind, ctx)
    return out


def _oscillation(ind: Indices, ctx: Context) -> list[Flag]:
    """``oscillating``, and ``stiction`` when the valve is its cause."""
    severity = _grade((ind.oscillation_amplitude or 0.0) / ctx.a, 3.0, 10.0)
    stiction = is_stiction(ind, ctx.integrating)
    out = [Flag("oscillating", severity, _oscillation_reason(ind, ctx, stiction))]
    if stiction:
        band = "" if ind.stiction_band is None else (
            f"; the MV swings {_n(ind.stiction_band)} ({100.0 * ind.stiction_band / ctx.mv_span:.2g} % of its "
            "span) per cycle, about the valve's deadband plus stickband")
        out.append(Flag("stiction", severity, f"a sticking valve keeps the loop in a limit cycle{band}"))
    return out


def _sluggish(ind: Indices, ctx: Context) -> list[Flag]:
    """Hägglund's idle index around a process not known to integrate; the recovery time against Tu where the
    model gives one; an offset the integral action leaves."""
    if ctx.integrating is not True and ind.idle_index is not None and ind.idle_index > SLUGGISH:
        return [Flag("sluggish", _grade(ind.idle_index, 0.6, 0.8),
                     f"after load disturbances the MV kept moving the way the PV recovered (idle index "
                     f"{ind.idle_index:.2f}): slow control")]
    if ctx.tu is not None and ind.load_recovery is not None and ind.load_recovery > SLOW_RECOVERY * ctx.tu:
        periods = ind.load_recovery / ctx.tu
        return [Flag("sluggish", _grade(periods / SLOW_RECOVERY, 1.5, 3.0),
                     f"load disturbances take {_n(ind.load_recovery)} s to recover, {periods:.0f} ultimate "
                     "periods of the process: slow control")]
    if ind.error_mean is not None and abs(ind.error_mean) > OFFSET * ctx.a:
        unit = f" {ctx.pv_unit}" if ctx.pv_unit else ""
        return [Flag("sluggish", _grade(abs(ind.error_mean) / (OFFSET * ctx.a), 2.0, 5.0),
                     f"the error averaged {_n(ind.error_mean)}{unit} over the window: the controller does not "
                     "remove it")]
    return []


def _noisy(ind: Indices, ctx: Context) -> list[Flag]:
    shares = [ind.mv_noise / ctx.mv_span]
    if ctx.pv_span is not None:
        shares.append(ind.pv_noise / ctx.pv_span)
    if max(shares) <= NOISY:
        return []
    unit = f" {ctx.pv_unit}" if ctx.pv_unit else ""
    pv = f"PV noise σ {_n(ind.pv_noise)}{unit}" + (
        "" if ctx.pv_span is None else f" ({100.0 * ind.pv_noise / ctx.pv_span:.2g} % of its span)")
    return [Flag("noisy", _grade(max(shares) / NOISY, 2.0, 5.0),
                 f"{pv} moves the MV by σ {100.0 * shares[0]:.2g} % of its span")]


def _tracking(ind: Indices, ctx: Context) -> list[Flag]:
    problems = []
    if ind.overshoot is not None and ind.overshoot > OVERSHOOT:
        problems.append(f"overshoots set-point steps by {ind.overshoot:.0f} %")
    if ind.setpoint_steps and ind.settling_time is None:
        problems.append("did not settle after a set-point step")
    elif ctx.tu is not None and ind.settling_time is not None and ind.settling_time > SETTLING_PERIODS * ctx.tu:
        problems.append(f"settles in {_n(ind.settling_time)} s, {ind.settling_time / ctx.tu:.0f} ultimate periods")
    if not problems:
        return []
    worst = max((ind.overshoot or 0.0) / OVERSHOOT, 2.0 if ind.settling_time is None else 1.0)
    return [Flag("poor_tracking", _grade(worst, 1.5, 3.0), "; ".join(problems))]


def recommendation(found: list[Flag], utilization: float) -> str:
    """The one thing to do first: a frozen sensor makes every other index meaningless; a loop mostly in manual
    must run in automatic to be judged; a sticking valve needs the valve, never new gains; then retuning for
    oscillation, sluggishness or poor tracking; a saturated valve; a noisy sensor; any manual time.

    ``found``: the flags raised; ``utilization``: the share of the record in automatic, 0–1.
    """
    names = {f.name for f in found}
    if "frozen_pv" in names:
        return "check_sensor"
    if "manual" in names and utilization < 0.5:
        return "put_in_auto"
    if "stiction" in names:
        return "check_valve"
    if names & {"oscillating", "sluggish", "poor_tracking"}:
        return "retune"
    for wanted, action in (("saturated", "check_valve"), ("noisy", "check_sensor"), ("manual", "put_in_auto")):
        if wanted in names:
            return action
    return "none"
