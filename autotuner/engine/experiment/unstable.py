"""Open-loop unstable processes: recognised from the estimates, given a weaker bias and a phase they reach.

An unstable process shows a negative mean |F|/K0 from its first estimates on
(or ran away from a level already, runaway.py); one that turns negative later
is a load step or noise, which the load fit and the stopping rule deal with.
Its model ``K·e^{−Ds}/(Ts − 1)`` through the point (methods.md §6,
unstable_design) says where its lag is least; the filter then aims between
there and 180°, where the cycle holds.
"""

from __future__ import annotations

import math

from autotuner.engine.experiment.adaptation import Adaptation
from autotuner.engine.experiment.estimates import Estimates, lag
from autotuner.engine.experiment.levels import Levels
from autotuner.engine.experiment.load_following import LoadFollowing
from autotuner.engine.experiment.loop import Loop
from autotuner.engine.experiment.point import Point
from autotuner.engine.experiment.runaway import REACT_SAMPLES

# The phase target of an unstable process moves this share of the way from the least lag its
# model reaches to 180° (where the plain relay oscillates): a target near the least lag sits where
# the phase curve is flat and the cycle slides onto the low-frequency branch and runs away.
MARGIN = 0.4
# An open-loop unstable process is recognised from the mean |F|/K0 of the first this many estimates (the
# first one still carries the start's transient); one whose |F|/K0 turns negative later is a load step or
# noise, which the load fit and the stopping rule deal with.
HINT_ESTIMATES = 3
# A first half period at the weak level longer than this many reaction times (runaway.Runaway.reaction): the
# level barely held the PV, as on an unstable process whose dead time and lag are near what a relay holds;
# the describing function's lag in the next period would let it run away beyond the full amp (seen at 9.3 on
# exp(-0.3*s)/((s-1)*(0.1*s+1))). The batch's stable processes stay below 7.1.
SLOW_RETURN = 8.0
# The mean |F|/K0 over the first whole period below which the process may be open-loop unstable: it is
# then treated as unstable, as after a rescue, until the estimates decide. The start's transient takes a stable
# process's first period down to −0.31 (the batch); an unstable one whose dead time the first weak level
# does not reveal (D/T 0.25–0.34) shows −0.8 to −1.1, and the describing function's lag would make it run
# away in the next period.
SUSPECT_X = -0.5
# How much lower (information criterion) the unstable load fit must score than the stable one to call a
# process unstable: both ranges share x = 0, so an integrator with a load ties (differences of 1–3 seen);
# unstable processes score 20–250 lower. 10 is "very strong" evidence on the usual BIC scale.
EVIDENCE = 10.0


def model(point: Point, x: float) -> tuple[float, float] | None:
    """(ω·T, D/T) of ``K·e^{−Ds}/(Ts − 1)`` through ``point`` with ``x`` = |F|/K0 < 0, or None if none fits.

    ``K = |F|/|x|``, ``ωT = sqrt(1/x² − 1)``, ``ωD = lag − π + atan(ωT)``
    (methods.md §6, unstable_design).
    """
    if not -1.0 < x < 0.0:
        return None
    wt = math.sqrt(1.0 / (x * x) - 1.0)
    wd = lag(point.value) - math.pi + math.atan(wt)
    return wt, max(wd, 0.0) / wt


def on_rising_branch(point: Point, x: float) -> bool:
    """True when ``point`` with |F|/K0 ``x`` lies where the unstable model's lag rises with ω
    (``ωT > sqrt(T/D − 1)``).

    The lag ``π − atan(ωT) + ωD`` falls from 180° at ω = 0 to its least at
    ``ωT = sqrt(T/D − 1)`` and rises after it; a relay cycle needs the
    rising branch (on the falling one it slides away to ω → 0).
    """
    found = model(point, x)
    if found is None:
        return False
    wt, dead = found
    return 0.0 < dead and (dead >= 1.0 or wt * wt > 1.0 / dead - 1.0)


def reachable_deg(point: Point, x: float) -> float | None:
    """The phase target (degrees of lag) for the unstable model through ``point`` with |F|/K0 ``x``, or None.

    The model's lag ``π − atan(ωT) + ωD`` is least, ``π − atan(s) + s·D/T``,
    at ``ωT = s = sqrt(T/D − 1)``; the target is ``MARGIN`` of the way from
    there to 180°.
    """
    found = model(point, x)
    if found is None:
        return None
    dead = found[1]
    if dead >= 1.0:
        least = math.pi
    elif dead > 0.0:
        s = math.sqrt(1.0 / dead - 1.0)
        least = math.pi - math.atan(s) + s * dead
    else:
        least = math.pi / 2.0
    return math.degrees(least + MARGIN * (math.pi - least))


class Unstable:
    """Whether the process is taken for open-loop unstable, and whether its target was set from an estimate.

    ``loop``, ``levels``, ``adaptation``, ``estimates``, ``load``: the loop under test, the relay's levels (the
    bias), the filter's adaptation (the target), the estimates and the load following (its fits).
    """

    def __init__(self, loop: Loop, levels: Levels, adaptation: Adaptation, estimates: Estimates,
                 load: LoadFollowing) -> None:
        self.loop = loop
        self.levels = levels
        self.adaptation = adaptation
        self.estimates = estimates
        self.load = load
        self.unstable = False
        self.aimed = False  # the target has been set from an estimate

    def enter(self) -> None:
        """An open-loop unstable process: the weaker bias, levels changed (estimates from now on)."""
        self.unstable = True
        self.levels.weaken_bias(self.loop.record.time(-1))

    def slow_return(self, half: float, react: float) -> bool:
        """True when the first half period (``half``, s) took over SLOW_RETURN times the first switch's
        reaction time (``react``, s), where that tells the process's (runaway.REACT_SAMPLES)."""
        return react > REACT_SAMPLES * self.loop.dt and half > SLOW_RETURN * react

    def suspect(self, first_x: float, omega: float) -> None:
        """Take the process for unstable (no filter lag at ``omega``, rad/s) when the first whole period's
        mean |F|/K0, ``first_x``, is below SUSPECT_X."""
        if first_x < SUSPECT_X:
            self.enter()
            self.adaptation.set(0.0, omega)

    def recognise(self, since: float) -> None:
        """Enter or leave the unstable mode from the estimates whose windows do not span ``since`` (s: the
        latest change of the relay's levels or a stall)."""
        negative = self._negative(since)
        recognised = self.unstable or (len(self.estimates) <= HINT_ESTIMATES and self._hint(since))
        # (Asked once, when the process would first be taken for unstable: the load fit costs two fits.)
        if negative and recognised and self.load.fit is None and (self.unstable or not self._stable_with_load()):
            # An open-loop unstable process: a weaker bias, and a phase it reaches.
            self.enter()
            latest = self.estimates.latest
            wanted = reachable_deg(latest.point, latest.wide_x)
            if wanted is not None:
                self.aimed = True
                self.adaptation.aim(wanted)
        elif negative is False:
            self.unstable = False  # a rescued level (runaway.py) on a process the estimates call stable

    def _negative(self, since: float) -> bool | None:
        """True when the mean Hann |F|/K0 of the latest two estimates not spanning ``since`` (s) is below
        −static_tol; None while there is none."""
        wide = self.estimates.wide_xs(since)[-2:]
        if not wide:
            return None
        return bool(sum(wide) / len(wide) < -self.loop.config.static_tol)

    def _hint(self, since: float) -> bool:
        """True when the estimates say the process is open-loop unstable (``since``: see :meth:`recognise`).

        The simple mean ratio of the latest two estimates is negative, and the
        unstable model that the latest estimate fixes has its point on the
        rising branch of its phase curve, where a relay cycle sits. An
        integrating or stable process with a load at the process input from the
        start shows a negative mean ratio too (the relay's mean MV balances the
        load, not the PV's mean), but the model it implies puts the point on
        the falling branch: that is no unstable process.
        """
        if not self._negative(since):
            return False
        latest = self.estimates.latest
        x = latest.wide_x
        return x < 0.0 and on_rising_branch(latest.point, x)

    def _stable_with_load(self) -> bool:
        """True unless an unstable model explains the record clearly better than a stable one with a load.

        A load step early in the experiment shifts the relay's mean MV against
        the PV's mean and makes the mean ratio negative, as an unstable process
        does; the load fit tells them apart: the growth of an unstable process
        is no stable model's response to a step, and a stable process's
        response to a load is no unstable model's.
        """
        if not self.loop.config.follow_loads:
            return False
        unstable, stable = (self.load.load_fit(mode) for mode in (True, False))
        if unstable is None or stable is None:
            return False
        return unstable.score > stable.score - EVIDENCE
