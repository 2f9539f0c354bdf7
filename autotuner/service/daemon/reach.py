"""How a loop is reached: its simulated PLC or its link, and the fresh check before a TUNE touches it."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from drivers.link import BadValue, Link, LinkError
from drivers.simlink import SimLink
from drivers.simplc import SimulatedPlc

from autotuner.engine.outcome import Code
from autotuner.service.config import LoopConfig
from autotuner.service.daemon.refused import Refused
from autotuner.service.remote_tuning import PLANT_TICKS_PER_SAMPLE, open_link


def simulated_plc(loop: LoopConfig) -> SimulatedPlc | None:
    """The simulated PLC of a ``sim:`` loop (its gains, mode and faults as configured; its plant ticks its
    ``sim.ts``, else ``PLANT_TICKS_PER_SAMPLE`` times per sample), else None."""
    if loop.sim is None:
        return None
    return loop.sim.plc(loop.ts / PLANT_TICKS_PER_SAMPLE)


def connector(loop: LoopConfig, plc: SimulatedPlc | None) -> Callable[[], Link]:
    """How to reach ``loop``: a new link to ``plc`` if it is simulated, else to its configured URL."""
    if plc is not None:
        return lambda: SimLink(plc)

    def connect() -> Link:
        try:
            return open_link(str(loop.link), _str(loop.map), _str(loop.dbc))
        except ValueError as exc:  # load_config checked it; a map file removed since is a link fault, not a crash
            raise LinkError(f"cannot open the link {loop.link}: {exc}") from None

    return connect


async def fresh_check(config: LoopConfig, connect: Callable[[], Link]) -> None:
    """Before a TUNE touches the loop: read its PV and handshake bits on a new link (``connect()``), and close it.

    Refused — with the code a device's TUNE is answered with (``ite``) — if the
    PV is not finite or stale (pv_invalid, 24), the link fails or reports
    itself disconnected (``Link.health``; link_unhealthy, 25), the PV is
    outside ``config.limits.pv`` (pv_out_of_limits, 23), or the device already
    shows TBSY (device_busy, 26: another tuner owns the loop). Nothing is
    written. The one check of the daemon's TUNE and of ``tune --config``.
    """
    loop_id = config.id
    link: Link | None = None
    try:
        link = connect()
        await link.open()
        pv = await link.read_pv()
        flags = await link.read_flags()
        health = link.health()
    except BadValue as exc:
        raise Refused("pv_invalid", f"loop {loop_id!r} not tuned: {exc}", Code.REFUSED_BAD_PV) from None
    except LinkError as exc:
        raise Refused("link_unhealthy", f"loop {loop_id!r} not tuned: {exc}", Code.REFUSED_LINK) from None
    finally:
        if link is not None:
            await link.close()
    if not health.get("connected", True):
        raise Refused("link_unhealthy", f"loop {loop_id!r} not tuned: its link reports {health}", Code.REFUSED_LINK)
    low, high = config.limits.pv
    if not low <= pv <= high:
        raise Refused("pv_out_of_limits", f"loop {loop_id!r} not tuned: PV {pv:g} is outside its limits "
                      f"[{low:g}, {high:g}]", Code.REFUSED_PV_LIMITS)
    if flags.tbsy:
        raise Refused("device_busy", f"loop {loop_id!r} not tuned: the device already shows TBSY (another "
                      "tuner owns the loop)", Code.REFUSED_DEVICE_BUSY)


def _str(path: Any) -> str | None:
    return None if path is None else str(path)
