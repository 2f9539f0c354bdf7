"""A request the loop's state does not allow: :class:`Refused`, with a machine code the API answers with."""

from __future__ import annotations

from autotuner.engine.outcome import Code


class Refused(Exception):
    """A request the loop's state does not allow.

    ``code``: not_found, busy, group_busy, idle, nothing_to_apply, not_restored
    (the loop is not handed back yet), stopping (the daemon shuts down), link
    (the device could not be written), history_unavailable (a gains intent
    could not be recorded first), invalid (a setting outside the loop's
    bounds, e.g. ``amp`` above its largest relay amplitude), overloaded (the
    daemon tunes as many loops at once as it can), or — TUNE on a fresh read of
    the loop (:func:`~autotuner.service.daemon.reach.fresh_check`) —
    pv_out_of_limits, pv_invalid (not finite, or stale), link_unhealthy,
    device_busy (the device already shows TBSY: another tuner owns the loop).
    ``ite``: what a refused TUNE from the device shows it (TE set); None:
    nothing is written to the device.
    """

    def __init__(self, code: str, message: str, ite: Code | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.ite = ite

    def __reduce__(self) -> tuple[type[Refused], tuple[str, str, Code | None]]:
        # Refusals cross the channel to a sampler process: pickled with their three arguments.
        return Refused, (self.code, self.message, self.ite)
