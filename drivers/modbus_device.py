"""One connection per Modbus device, shared by every link of the process to it.

A :class:`Device` is the connection to one Modbus TCP endpoint (host, port:
:class:`drivers.modbus_tcp.TcpAddress`) or one serial line
(:class:`drivers.modbus_rtu.SerialLine`), whatever the units and loops
behind it. :func:`hold` gives the device of an endpoint — the one already
open on this event loop, else a new one — and counts the link as one of its
holders; :func:`let_go` uncounts it, and the last holder's let-go closes the
connection. A device connects on demand (:meth:`Device.connect`, shared by
every holder that asks while it connects) and carries each holder's requests
(:meth:`Device.request`: a request PDU to a unit, its answer PDU).

Per holder the device keeps the ``pipeline`` it asked for (how many requests
it lets be outstanding at once on the connection); the device uses the
smallest of its holders' — a device some loop's URL says takes one request
at a time gets one at a time from every loop.
"""

from __future__ import annotations

import asyncio
from collections import Counter
from collections.abc import Hashable
from typing import Any, Protocol
from weakref import WeakKeyDictionary

__all__ = ["Unreachable", "Unanswered", "Device", "Endpoint", "hold", "let_go"]


class Unreachable(Exception):
    """The device cannot be connected to; the message says why (the link tries again)."""


class Unanswered(Exception):
    """A request got no answer to use — a timeout, the connection lost, an answer from another unit; the message
    says which (the link tries again)."""


class Device(Protocol):
    """The connection to one Modbus device, shared by its :attr:`holders`."""

    #: The ``pipeline`` each holder asked for → how many holders asked for it.
    holders: Counter[int]
    #: Connections made so far: the number of the connection up now (a link's epoch is written per connection).
    connects: int

    @property
    def connected(self) -> bool:
        """Whether the connection is up now."""

    @property
    def pipeline(self) -> int:
        """Requests outstanding at once, at most: the smallest of the holders'."""

    async def connect(self, timeout: float) -> None:
        """Connect unless connected, within ``timeout`` seconds; :class:`Unreachable` if it cannot."""

    async def request(self, unit: int, pdu: bytes, timeout: float, connection: int | None = None) -> bytes:
        """Send ``pdu`` to ``unit`` (connected first: :meth:`connect`) and return the answer's PDU, within
        ``timeout`` seconds from the call; :class:`Unanswered` if there is none to use. ``connection``: send it on
        that connection (:attr:`connects`) only — :class:`Unanswered` if it is not up any more."""

    def health(self) -> dict[str, Any]:
        """Counters of the connection (never raises)."""

    def close(self) -> None:
        """Close the connection; requests still outstanding fail with :class:`Unanswered` (never raises)."""


class Endpoint(Protocol):
    """Where a device is: the key its holders share it by, and how to open it."""

    @property
    def key(self) -> Hashable:
        """Equal for every link to the same device (the same connection)."""

    @property
    def name(self) -> str:
        """How messages name the device, e.g. ``modbus tcp 10.0.0.5:502``."""

    def open_device(self) -> Device:
        """A new, unconnected device at this endpoint."""

    def check_compatible(self, device: Device) -> None:
        """Raise ValueError, saying why, if a link to this endpoint cannot share ``device`` (another setting)."""


# The devices open on each event loop (a device's connection and futures belong to one loop), by endpoint key.
_OPEN: WeakKeyDictionary[asyncio.AbstractEventLoop, dict[Hashable, Device]] = WeakKeyDictionary()


def hold(endpoint: Endpoint, pipeline: int) -> Device:
    """The device of ``endpoint`` on the running event loop (open it if none is), held by one more link asking for
    ``pipeline`` requests outstanding at once; ValueError if the link cannot share the open device."""
    devices = _OPEN.setdefault(asyncio.get_running_loop(), {})
    device = devices.get(endpoint.key)
    if device is None:
        device = devices[endpoint.key] = endpoint.open_device()
    else:
        endpoint.check_compatible(device)
    device.holders[pipeline] += 1
    return device


def let_go(endpoint: Endpoint, device: Device, pipeline: int) -> None:
    """One link holding ``device`` (asking for ``pipeline``) no longer does; the last one closes it."""
    device.holders[pipeline] -= 1
    if device.holders[pipeline] <= 0:
        del device.holders[pipeline]
    if device.holders:
        return
    device.close()
    for devices in _OPEN.values():
        if devices.get(endpoint.key) is device:
            del devices[endpoint.key]
