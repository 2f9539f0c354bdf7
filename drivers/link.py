"""What the tuning session needs from a loop in the field, whatever the transport.

One implementation per transport (Modbus, CAN, in-process simulation); none
of their details reach the engine. All calls are async and raise
:class:`LinkError` on any failure — a timeout, an exception response, a bus
error, or a value that must not be used as data (NaN, infinity, stale).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, Protocol

from autotuner.engine.control.gains import Gains


class LinkError(Exception):
    """The loop cannot be read or written right now; the message says why."""


class Fenced(LinkError):
    """The writer no longer holds the loop's lease: nothing more may be written to it (its new owner restores it).

    Raised before a write by a daemon whose lease has run out on its own clock, and by a link whose device refused a
    write because it was written a newer lease epoch than the link's (a CAN node, which cannot answer a frame:
    reported a newer epoch; docs/fleet.md)."""


class BadValue(LinkError):
    """The device answered, but the value is not data: NaN, infinity, or (a time-stamped transport) stale."""


class Mode(IntEnum):
    """Controller mode of the loop: MAN holds the manual MV, AUTO runs the PID."""

    MAN = 0
    AUTO = 1


@dataclass(frozen=True)
class LoopState:
    """A snapshot of the loop: mode, MV and SP (engineering units) and the PID gains."""

    mode: Mode
    mv: float
    sp: float
    gains: Gains


@dataclass(frozen=True)
class Sample:
    """What the monitor of an idle loop shows, read together: PV, actual MV and SP (engineering units) and mode;
    ``boot``: the device's boot token — it changes whenever the device starts again, its registers back at their
    defaults (None: the device has none)."""

    pv: float
    mv: float
    sp: float
    mode: Mode
    boot: int | None = None


@dataclass(frozen=True)
class TuneFlags:
    """The autotuner handshake of the PIDAT block: TUNE/TBRK in, TBSY/TE/ite out."""

    tune: bool = False
    tbrk: bool = False
    tbsy: bool = False
    te: bool = False
    ite: float = 0.0


@dataclass(frozen=True)
class Watchdog:
    """The device-side watchdog of the hand-back (docs/handback.md).

    While ``timeout`` > 0 the device expects the tuner's heartbeat; when the
    heartbeat counter has not changed for ``timeout`` seconds of the device's
    clock, the device falls back on its own: it holds ``mv`` in MAN until its
    PID unit tracks it, then switches to ``mode``, clears TBSY and shows TE
    with ite :attr:`autotuner.engine.outcome.Code.WATCHDOG_FALLBACK`.
    ``timeout`` 0 disarms it.
    """

    timeout: float = 0.0
    mv: float = 0.0
    mode: Mode = Mode.AUTO


def float32_step(value: float) -> float:
    """The spacing of IEEE float32 numbers at ``value`` (what a float32 register or signal can resolve)."""
    exponent = math.frexp(abs(value))[1] if value != 0.0 and math.isfinite(value) else -125
    return math.ldexp(1.0, max(exponent, -125) - 24)


def checked(name: str, value: float) -> float:
    """``value`` if finite, else a :class:`BadValue` naming the signal (a NaN is never data)."""
    if not math.isfinite(value):
        raise BadValue(f"{name} is not a number ({value})")
    return value


class Link(Protocol):
    """A loop reachable through some transport.

    ``pv_age``: seconds since the value last returned by :meth:`read_pv` was
    acquired, when the transport time-stamps it (a cyclic CAN frame); None
    for request/response transports, whose value is taken while the request
    is served. The session dates its samples with it.
    """

    @property
    def pv_age(self) -> float | None: ...

    #: The lease epoch the link's writes carry to the device (a daemon of a fleet sets it before each write; None:
    #: no fleet, no epoch written). A device that was written a newer epoch refuses the writes: :class:`Fenced`.
    epoch: int | None

    @property
    def carries_epoch(self) -> bool:
        """Whether the device has a place for the epoch (a Modbus map's ``epoch``, a DBC's ``Epoch`` signals): without
        one, nothing fences the writes of a superseded daemon on the device's side."""

    def health(self) -> dict[str, Any]:
        """Transport, device, whether it is connected, and the transport's counters (never raises)."""

    async def open(self) -> None:
        """Connect; raises LinkError if the device cannot be reached."""

    async def close(self) -> None:
        """Disconnect; never raises."""

    async def read_pv(self) -> float:
        """The current PV (engineering units)."""

    async def write_mv(self, mv: float) -> None:
        """Set the manual MV (used while the loop is in MAN)."""

    async def read_state(self) -> LoopState:
        """Mode, MV, SP and gains of the loop."""

    async def read_sample(self) -> Sample:
        """PV, MV, SP and mode of the loop, in as few requests as the transport allows (a monitor's reading)."""

    async def write_mode(self, mode: Mode) -> None:
        """Switch the loop to MAN or AUTO."""

    async def write_gains(self, gains: Gains) -> None:
        """Write PID gains (standard form) to the controller."""

    async def read_flags(self) -> TuneFlags:
        """The handshake bits as the device holds them."""

    async def write_flags(self, flags: TuneFlags) -> None:
        """Publish TBSY, TE and ite to the device (TUNE and TBRK are the device's inputs)."""

    def mv_resolution(self, mv: float) -> float:
        """How far an MV read back may be from ``mv`` written, near ``mv`` (engineering units): the coding's step
        of the manual MV plus that of the actual MV."""

    async def write_watchdog(self, watchdog: Watchdog) -> None:
        """Arm (timeout > 0: fallback MV and mode) or disarm the device's watchdog; nothing if the device has none."""

    async def write_heartbeat(self, counter: int) -> None:
        """The heartbeat of the device's watchdog (a counter, mod 65536); nothing if the device has none."""
