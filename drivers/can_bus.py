"""One python-can bus per CAN interface and channel, shared by every link of the process on it.

A CAN interface is one bus whatever the loops on it (each loop's node has
frame ids of its own, from its DBC), and some interfaces can be opened only
once per process (PCAN, Kvaser). :func:`hold` gives the :class:`SharedBus`
of an interface and channel on the running event loop — open already, or
opened now with one receive thread (a :class:`can.Notifier`) — and adds a
:class:`Receiver` to it; :func:`let_go` removes it, and the last one closes
the bus. Each frame received goes to the receivers that decode its id (an
error frame to all of them), in the event loop.
"""

from __future__ import annotations

import asyncio
from typing import Any, Protocol
from weakref import WeakKeyDictionary

import can

from .link import LinkError

__all__ = ["Receiver", "SharedBus", "open_bus", "hold", "let_go", "RX_POLL"]

# How often the notifier's receive thread wakes to see whether it is stopped (s); closing the bus waits for it, so
# this bounds the time the last link's close takes. The simulated node uses it too.
RX_POLL = 0.05


def open_bus(interface: str, channel: str, **kwargs: Any) -> can.BusABC:
    """A python-can bus; any failure (unknown interface, no device, driver missing) is a LinkError."""
    try:
        return can.Bus(interface=interface, channel=channel, **kwargs)
    except (can.CanError, ValueError, ImportError, OSError, TypeError) as exc:
        raise LinkError(f"cannot open CAN interface {interface!r} channel {channel!r}: {exc}") from exc


class Receiver(Protocol):
    """What a shared bus hands frames to (a :class:`~drivers.can_link.CanLink`)."""

    @property
    def frame_ids(self) -> frozenset[int]:
        """The arbitration ids it decodes."""

    def received(self, msg: can.Message) -> None:
        """A frame of one of its ids, or an error frame (in the event loop)."""

    def bus_error(self, exc: Exception) -> None:
        """The receive thread failed (in the event loop)."""


class SharedBus(can.Listener):
    """An open bus, its receive thread and the receivers of its frames (see the module's docstring)."""

    def __init__(self, interface: str, channel: str, kwargs: dict[str, Any]) -> None:
        self.interface, self.channel, self.kwargs = interface, channel, kwargs
        self.bus = open_bus(interface, channel, **kwargs)
        self.receivers: list[Receiver] = []
        self._by_id: dict[int, list[Receiver]] = {}
        try:
            self.notifier = can.Notifier(self.bus, [self], timeout=RX_POLL, loop=asyncio.get_running_loop())
        except (can.CanError, ValueError, OSError) as exc:
            self.bus.shutdown()
            raise LinkError(f"cannot receive on {interface}/{channel}: {exc}") from exc

    def add(self, receiver: Receiver) -> None:
        self.receivers.append(receiver)
        for frame_id in receiver.frame_ids:
            self._by_id.setdefault(frame_id, []).append(receiver)

    def remove(self, receiver: Receiver) -> None:
        self.receivers.remove(receiver)
        for frame_id in receiver.frame_ids:
            self._by_id[frame_id].remove(receiver)

    def on_message_received(self, msg: can.Message) -> None:
        for receiver in list(self.receivers if msg.is_error_frame else self._by_id.get(msg.arbitration_id, ())):
            receiver.received(msg)

    def on_error(self, exc: Exception) -> None:
        for receiver in list(self.receivers):
            receiver.bus_error(exc)

    def stop(self) -> None:
        pass

    def close(self) -> None:
        """Stop receiving and release the interface; never raises."""
        try:
            self.notifier.stop(timeout=RX_POLL + 1.0)
        except Exception:  # noqa: BLE001 - close never raises
            pass
        try:
            self.bus.shutdown()
        except Exception:  # noqa: BLE001
            pass


# The buses open on each event loop (the notifier hands frames to one loop), by (interface, channel).
_OPEN: WeakKeyDictionary[asyncio.AbstractEventLoop, dict[tuple[str, str], SharedBus]] = WeakKeyDictionary()


def hold(interface: str, channel: str, kwargs: dict[str, Any], receiver: Receiver) -> SharedBus:
    """The bus of ``interface``/``channel`` on the running event loop (opened with ``kwargs`` if none is), with
    ``receiver`` added; LinkError if it cannot be opened, or is open with other ``kwargs`` (e.g. a bit rate)."""
    buses = _OPEN.setdefault(asyncio.get_running_loop(), {})
    shared = buses.get((interface, channel))
    if shared is None:
        shared = buses[(interface, channel)] = SharedBus(interface, channel, dict(kwargs))
    elif shared.kwargs != kwargs:
        raise LinkError(f"CAN interface {interface!r} channel {channel!r} is open with {shared.kwargs or 'defaults'} "
                        f"by other loops; this link asks for {kwargs or 'defaults'}")
    shared.add(receiver)
    return shared


def let_go(shared: SharedBus, receiver: Receiver) -> None:
    """``receiver`` leaves ``shared``; the last one closes the bus."""
    shared.remove(receiver)
    if shared.receivers:
        return
    for buses in _OPEN.values():
        if buses.get((shared.interface, shared.channel)) is shared:
            del buses[(shared.interface, shared.channel)]
    shared.close()
