"""How an experiment ends: the :class:`Ended` signal and the texts of its codes.

Any part of the analysis may find that the experiment is over (a runaway no
relay holds, a load beyond amp, a cycle that died out, a converged point);
it raises :class:`Ended`, which the experiment turns into its code and
message. The texts say what was seen and what to do about it.
"""

from __future__ import annotations

import math

from autotuner.engine.experiment.stopping import Tolerances, amp_factor
from autotuner.engine.experiment.point import Point
from autotuner.engine.outcome import MESSAGES, Code


class Ended(Exception):
    """The experiment ends with ``code`` and ``message``."""

    def __init__(self, code: Code, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


PUSHED_AWAY = (f"{MESSAGES[Code.DISTURBANCE]}: the relay stayed at one level while the PV moved away from the set "
               "point (a load or drift larger than amp)")
DIED_OUT = "the oscillation died out (increase amp or reduce hysteresis)"
NO_OSCILLATION_IN_TIME = MESSAGES[Code.NO_OSCILLATION] + " within the time limit"


def mv_range(mv0: float, low: float, high: float, amp: float, limits: tuple[float, float]) -> Ended:
    """The relay's levels ``low`` and ``high`` (MV units) do not straddle ``mv0``: it cannot move the MV
    (``amp``, ``limits``: the settings, MV units)."""
    return Ended(Code.MV_RANGE, f"the relay cannot move the MV from {mv0:g}: the levels {low:g} and {high:g} "
                                f"(amp {amp:g} within the limits {limits}) do not straddle it")


def load_too_large(load: float, amp: float) -> Ended:
    """The fitted ``load`` at the process input (MV units) is beyond ``amp`` (MV units)."""
    return Ended(Code.DISTURBANCE,
                 f"{MESSAGES[Code.DISTURBANCE]}: the load at the process input has moved by {load:+.3g} MV units "
                 f"({abs(load) / amp:.2f} × amp); the relay follows a load within ±amp of the starting MV only")


def unsettled_through_load(when: str, step: float, ramp: float) -> Ended:
    """The estimates did not settle ``when`` through a followed load (its fitted ``step``, MV units, and
    ``ramp``, MV units per s)."""
    return Ended(Code.DISTURBANCE, f"{MESSAGES[Code.DISTURBANCE]}: the estimates did not settle {when} through "
                 f"the load the experiment detected (last fit: step {step:+.3g}, ramp {ramp:+.3g}/s in MV units)")


def noise_too_high(when: str, usable: list[tuple[Point, float]], tol: Tolerances, noise: float,
                   amp: float) -> Ended | None:
    """NOISE_TOO_HIGH when the averaged rule needs a larger amp over the ``usable`` (point, x) estimates, else
    None. ``when``: when the estimates did not settle; ``tol``: the tolerances; ``noise``: σ, PV units;
    ``amp``: MV units."""
    factor = amp_factor(usable, tol)
    if not math.isfinite(factor):
        return None
    share = noise / (usable[-1][0].gain * amp)
    return Ended(Code.NOISE_TOO_HIGH,
                 f"the measurement noise (σ = {noise:.3g} PV units, {100 * share:.1f} % of |F|·amp) is too "
                 f"high for amp {amp:g}: the estimates did not settle {when}; raise amp to at least "
                 f"{math.ceil(factor * amp * 100) / 100:g} (× {factor:.2f}) or allow more periods")


def not_converged(when: str, stalls: list[float], stall: float, latest: Point | None, phase_deg: float,
                  target_deg: float) -> Ended:
    """NOT_CONVERGED ``when``, saying why: the ``stalls`` (longest gap of each left-out window, s; ``stall``:
    the share of a period that leaves one out), else where the ``latest`` point lags against the requested
    ``phase_deg`` and the ``target_deg`` aimed at (degrees)."""
    text = f"no convergence {when}"
    if stalls:
        # Not the process's fault: say what kept the estimates out.
        text += (f": {len(stalls)} estimates were left out because their windows held a time without "
                 f"samples of more than {stall:.0%} of a period (the longest {max(stalls):.3g} s): the "
                 "link or the machine is too slow for this sample time")
    elif latest is not None:
        text += (
            f": the process lags {-latest.phase_deg:.1f}° where {phase_deg:g}° was requested"
            + (f" and {target_deg:.1f}° aimed at (an unstable process: the requested phase is out of "
               "its reach)" if target_deg != phase_deg else " (out of reach of this process?)")
        )
    return Ended(Code.NOT_CONVERGED, text)


def runaway_at_full_amp(amp: float, reach: float, largest_lag: float, reach_one_pole: float,
                        stalled: str) -> Ended:
    """The PV runs away from a level at full ``amp`` (MV units): no relay holds this process.

    ``reach``: the time the process takes to answer the relay times the
    runaway's growth rate — for ``K·e^{−Ds}/(Ts − 1)``, D/T. A single
    unstable pole defeats a full-amp relay only from D/T ≈ 0.5–0.7 on, and
    its lag stays below 180° at any frequency where a relay oscillates; a
    runaway with ``reach`` below ``reach_one_pole`` or a ``largest_lag``
    (radians, over the periods measured) beyond 180° means more than one
    unstable pole: NOT_STABILISABLE, as the design says of such a process.
    Otherwise the dead time is too long for a relay to hold the process, so
    too long for a PI/PID as well: UNSTABLE_DEAD_TIME_TOO_LONG. ``stalled``:
    what a stall of the samples adds (:func:`stalled_note`).
    """
    what = (f"the PV runs away from the set point faster and faster while the relay pushes back with its full "
            f"amplitude ({amp:g})")
    if largest_lag > math.pi or reach < reach_one_pole:
        if largest_lag > math.pi:
            evidence = (f"the process lagged {math.degrees(largest_lag):.0f}° (more than 180°) at the relay's "
                        "frequency — an open-loop unstable process with more than one unstable pole")
        else:
            # A runaway this fast from a level the dead time alone would let a relay hold: more than one
            # unstable pole, or stable lags that add to the dead time (the growth is then measured while
            # the full level is still arriving through them).
            evidence = (f"the relay's answer reached it within {reach:.2f} × the runaway's time constant (a "
                        "relay holds a single unstable pole with so short a dead time) — an open-loop unstable "
                        "process with more than one unstable pole, or lags that add to its dead time beyond "
                        "what a relay holds")
        return Ended(Code.NOT_STABILISABLE,
                     f"{MESSAGES[Code.NOT_STABILISABLE]}: {what}, and {evidence}: no relay holds it and no PI/PID "
                     f"stabilises it robustly, so no relay experiment tunes it{stalled}")
    return Ended(Code.UNSTABLE_DEAD_TIME_TOO_LONG,
                 f"{MESSAGES[Code.UNSTABLE_DEAD_TIME_TOO_LONG]}: {what} — an open-loop unstable process whose dead "
                 f"time is too long for a relay to hold it (about {reach:.2f} × the runaway's time constant; a relay "
                 f"holds up to about 0.5–0.7), so too long for a PI/PID as well{stalled}")


def stalled_note(gap: float) -> str:
    """What a stall of the samples of up to ``gap`` s over the last period adds to a runaway's refusal."""
    # The relay cannot switch without a sample: on an unstable process a stall acts as extra dead time.
    return (f"; but the samples stopped for up to {gap:.2g} s meanwhile (a slow link or a loaded machine), "
            "which acts as extra dead time: retry where the tuner samples without stalls")
