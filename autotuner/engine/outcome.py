"""The outcome codes of a tuning: the value ``ite`` shows once a session has ended.

Defined here once, for the engine, the service, the API (served to the operator page
at ``GET /api/v1/codes``) and the CLI. Ranges: 0–10 the original block's outcomes,
11–19 the field-grade experiment and design (warnings and refusals), 20–29 the
hand-back. A *warning* code comes with ``te`` false: the gains are usable but the
result missed something it was asked for, and the message says what.
"""

from __future__ import annotations

from enum import IntEnum


class Code(IntEnum):
    """Outcome of a tuning; the value is what ``ite`` shows when it has ended."""

    OK = 0
    ABORTED = 1
    PV_OUT_OF_LIMITS = 2
    NO_OSCILLATION = 3
    NOT_CONVERGED = 4
    BAD_SAMPLE = 5
    MV_RANGE = 6
    LINK_FAULT = 7
    NO_DESIGN = 8
    GROUP_BUSY = 10
    # Field-grade experiment (refusals, te true): 11, 12.
    DISTURBANCE = 11
    NOISE_TOO_HIGH = 12
    # Field-grade design (taken from 19 downwards): 15, 18, 19 warnings (te false), 16, 17 refusals.
    DERIVATIVE_LIMITED = 15
    NOT_STABILISABLE = 16
    UNSTABLE_DEAD_TIME_TOO_LONG = 17
    DERIVATIVE_DROPPED = 18
    ROBUSTNESS_MISSED = 19
    # The hand-back (te true): 20-22.
    LOOP_NOT_RESTORED = 20
    OPERATOR_INTERVENTION = 21
    WATCHDOG_FALLBACK = 22
    # TUNE refused on a fresh read before the loop is touched (te true, the loop untouched): 23-26.
    REFUSED_PV_LIMITS = 23
    REFUSED_BAD_PV = 24
    REFUSED_LINK = 25
    REFUSED_DEVICE_BUSY = 26
    # The session's start: the saved state could not be recorded durably, so the loop is not touched.
    HISTORY_UNAVAILABLE = 27
    # The tuner's own capacity (te true): its sampling fell behind mid-session (the loop handed back), or TUNE was
    # refused up front because the daemon is at its capacity (the loop untouched).
    OVERLOADED = 28
    REFUSED_OVERLOADED = 29


MESSAGES: dict[Code, str] = {
    Code.OK: "ok",
    Code.ABORTED: "aborted (TBRK)",
    Code.PV_OUT_OF_LIMITS: "PV left its safety limits",
    Code.NO_OSCILLATION: "no oscillation: the relay did not make the PV cross the set point repeatedly",
    Code.NOT_CONVERGED: "the identified point did not converge within the time limit",
    Code.BAD_SAMPLE: "invalid sample (non-finite PV or timestamps not increasing)",
    Code.MV_RANGE: "the relay cannot move the MV within its limits",
    Code.LINK_FAULT: "link to the loop failed",
    Code.NO_DESIGN: "no robust PI/PID design from the identified data",
    Code.GROUP_BUSY: "refused: another loop of the exclusion group is tuning (the loop is untouched)",
    Code.REFUSED_PV_LIMITS: "refused: the PV is outside its safety limits (the loop is untouched)",
    Code.REFUSED_BAD_PV: "refused: the PV is not a finite, fresh value (the loop is untouched)",
    Code.REFUSED_LINK: "refused: the link to the loop is not healthy (the loop is untouched)",
    Code.REFUSED_DEVICE_BUSY: "refused: the device already shows TBSY, another tuner owns the loop (untouched)",
    Code.HISTORY_UNAVAILABLE: "refused: the loop's saved state could not be recorded in the history (the loop is "
                              "untouched)",
    Code.OVERLOADED: "the tuner fell behind its own sampling schedule (a loaded machine, not the process): the loop "
                     "was handed back",
    Code.REFUSED_OVERLOADED: "refused: the daemon is at its capacity of loops tuned at once (the loop is untouched)",
    Code.DISTURBANCE: (
        "a load disturbance or drift too large for the experiment: following it needs more than ±amp "
        "of MV shift, or it never settled within the time limit"
    ),
    Code.NOISE_TOO_HIGH: "the measurement noise is too high for this amp (the message says by how much to raise amp)",
    Code.DERIVATIVE_LIMITED: "warning: derivative action reduced so the measured noise stays within the MV noise budget",
    Code.NOT_STABILISABLE: "refused: no PI/PID stabilises this process robustly",
    Code.UNSTABLE_DEAD_TIME_TOO_LONG: "refused: the dead time is too long for this controller on an unstable process",
    Code.DERIVATIVE_DROPPED: "warning: PID was asked for but the design has no derivative action",
    Code.ROBUSTNESS_MISSED: "warning: the design misses its Ms target on the model",
    Code.LOOP_NOT_RESTORED: "LOOP NOT RESTORED: the loop could not be handed back yet; the restore is retried",
    Code.OPERATOR_INTERVENTION: "the loop was changed by someone else (by hand, another tuner): left as found, not "
                                "restored",
    Code.WATCHDOG_FALLBACK: "the device's watchdog handed the loop back (the tuner's heartbeat stopped)",
}

# Codes reported with te false: gains computed, but a target was missed (the message names it).
WARNINGS: frozenset[Code] = frozenset({Code.DERIVATIVE_LIMITED, Code.DERIVATIVE_DROPPED, Code.ROBUSTNESS_MISSED})


def is_failure(code: Code) -> bool:
    """True when the outcome carries no usable gains (``te`` true).

    ``code``: the outcome.
    """
    return code is not Code.OK and code not in WARNINGS
