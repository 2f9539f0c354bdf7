"""A lean Modbus TCP client: one connection, requests of many links multiplexed by MBAP transaction id.

:class:`TcpDevice` is the :class:`~drivers.modbus_device.Device` of a Modbus
TCP endpoint (:class:`TcpAddress`). Each request gets a transaction id not
outstanding on the connection and a future keyed by it; the answer carrying
that id completes it, whichever order answers come in. Up to ``pipeline``
requests are outstanding at once; the rest wait, in order, for a slot. No task
and no timer is made per request: the protocol's ``data_received`` completes
them, and one timer per device, set at the earliest deadline of the requests
outstanding, expires them (moved only when a request with an earlier deadline
comes — a link with a shorter timeout —, or when it rings: about once a timeout).

Timeouts (each request's own, counted from the call, waiting for a slot
included): a request that times out is forgotten; an answer that comes later
carries an id no request holds and is discarded (counted as ``late``), so it
is never taken for another request. If nothing at all was heard from the
device while the timed-out request was outstanding, the connection is taken
for dead (a device that restarted, a cable pulled, a NAT that forgot it) and
dropped: every request outstanding on it fails, and the next request
connects anew. A frame that is not Modbus TCP (protocol id ≠ 0, a length
outside 2..254) means the stream is out of step: the connection is dropped too.
"""

from __future__ import annotations

import asyncio
import math
import struct
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

from .modbus_device import Device, Unanswered, Unreachable

__all__ = ["TcpAddress", "TcpDevice", "MAX_PIPELINE"]

#: The largest ``pipeline`` a link may ask for (devices that take more than one request at a time take 4–16).
MAX_PIPELINE = 128
# MBAP header: transaction id, protocol id (0), length of what follows, unit id.
_MBAP = struct.Struct(">HHHB")
# What the length field may say: the unit id and a PDU of 1..253 bytes.
_LENGTHS = range(2, 255)
# A timer may ring this much before its time (asyncio runs what is due within the clock's resolution), seconds.
_EARLY = 1e-6


@dataclass(frozen=True)
class TcpAddress:
    """A Modbus TCP endpoint; links to the same ``host`` string and ``port`` share one connection."""

    host: str
    port: int

    @property
    def key(self) -> tuple[str, str, int]:
        return ("tcp", self.host, self.port)

    @property
    def name(self) -> str:
        """E.g. ``modbus tcp 10.0.0.5:502`` (an IPv6 host in brackets)."""
        shown = f"[{self.host}]" if ":" in self.host else self.host
        return f"modbus tcp {shown}:{self.port}"

    def open_device(self) -> TcpDevice:
        return TcpDevice(self)

    def check_compatible(self, device: Device) -> None:
        """Every link to a TCP endpoint can share its connection."""


@dataclass(eq=False)
class _Transaction:
    """One request: to ``unit``, its ``pdu``, its ``timeout`` and ``deadline`` (the loop's clock), the future of
    its answer; ``tid`` once sent (-1 while waiting for a slot), at ``sent`` (the loop's clock)."""

    unit: int
    pdu: bytes
    timeout: float
    deadline: float
    answer: asyncio.Future[bytes]
    tid: int = -1
    sent: float = 0.0


@dataclass(eq=False)
class _Wire(asyncio.Protocol):
    """One TCP connection of a device; what it receives goes to the device, if it is still the device's."""

    device: TcpDevice
    loop: asyncio.AbstractEventLoop
    transport: asyncio.Transport | None = None
    received: bytearray = field(default_factory=bytearray)

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def data_received(self, data: bytes) -> None:
        self.device._received(self, data)

    def connection_lost(self, exc: Exception | None) -> None:
        self.device._lost(self, exc)


class TcpDevice:
    """The shared connection to one Modbus TCP endpoint (see the module's docstring)."""

    def __init__(self, address: TcpAddress) -> None:
        self.address = address
        self.holders: Counter[int] = Counter()
        self._wire: _Wire | None = None
        self._connecting: asyncio.Task[None] | None = None
        self._sent: dict[int, _Transaction] = {}
        self._waiting: deque[_Transaction] = deque()
        self._tid = 0
        self._heard = 0.0  # the loop's clock when the device last sent anything
        self._alarm: asyncio.TimerHandle | None = None  # rings at the earliest deadline outstanding
        self._alarm_at = math.inf
        self.connects = 0  # connections made
        self.dropped = 0  # connections dropped: the device silent for a request's timeout, or out of step
        self.late = 0  # answers to no outstanding request (timed out or cancelled), discarded

    def __repr__(self) -> str:
        return f"TcpDevice({self.address.name}, {sum(self.holders.values())} links)"

    @property
    def connected(self) -> bool:
        return self._wire is not None

    @property
    def pipeline(self) -> int:
        return min(self.holders, default=1)

    def health(self) -> dict[str, Any]:
        return {"links": sum(self.holders.values()), "pipeline": self.pipeline, "outstanding": len(self._sent),
                "waiting": len(self._waiting), "connects": self.connects, "dropped": self.dropped,
                "late_answers": self.late}

    # -- connecting ------------------------------------------------------------------------

    async def connect(self, timeout: float) -> None:
        if self._wire is not None:
            return
        if self._connecting is None:  # one connection attempt, whoever else waits for it
            self._connecting = asyncio.ensure_future(self._open(timeout))
            self._connecting.add_done_callback(_retrieved)
        try:
            await asyncio.wait_for(asyncio.shield(self._connecting), timeout)
        except asyncio.TimeoutError:
            raise Unreachable(f"cannot connect (TimeoutError) within {timeout:g} s") from None

    async def _open(self, timeout: float) -> None:
        loop = asyncio.get_running_loop()
        try:
            _, wire = await asyncio.wait_for(
                loop.create_connection(lambda: _Wire(self, loop), self.address.host, self.address.port), timeout)
        except asyncio.TimeoutError:
            raise Unreachable(f"cannot connect (TimeoutError) within {timeout:g} s") from None
        except OSError as exc:
            raise Unreachable(f"cannot connect ({type(exc).__name__} {exc}) within {timeout:g} s") from None
        finally:
            self._connecting = None
        if wire.transport is None or wire.transport.is_closing():
            raise Unreachable("cannot connect (the device closed the connection at once)")
        self._wire = wire
        self._heard = loop.time()
        self.connects += 1

    # -- requests --------------------------------------------------------------------------

    async def request(self, unit: int, pdu: bytes, timeout: float, connection: int | None = None) -> bytes:
        if connection is not None and (self._wire is None or self.connects != connection):
            raise Unanswered("connection lost")  # (not sent on another: a link's epoch was written on that one)
        if self._wire is None:
            await self.connect(timeout)
        wire = self._wire
        if wire is None:  # lost between the connection made and this line
            raise Unanswered("connection lost")
        loop = wire.loop
        t = _Transaction(unit, pdu, timeout, loop.time() + timeout, loop.create_future())
        if t.deadline < self._alarm_at:
            self._set_alarm(loop, t.deadline)
        if len(self._sent) < self.pipeline:
            self._send(wire, t)
        else:
            self._waiting.append(t)
        try:
            return await t.answer
        except asyncio.CancelledError:
            self._forget(t)  # the caller gave up: its answer, if it comes, is late
            raise

    def _send(self, wire: _Wire, t: _Transaction) -> None:
        tid = self._tid
        while True:
            tid = tid % 0xFFFF + 1
            if tid not in self._sent:
                break
        self._tid = t.tid = tid
        t.sent = wire.loop.time()
        self._sent[tid] = t
        assert wire.transport is not None
        wire.transport.write(_MBAP.pack(tid, 0, len(t.pdu) + 1, t.unit) + t.pdu)

    def _fill(self) -> None:
        """Send waiting requests while the pipeline has room."""
        wire = self._wire
        while wire is not None and self._waiting and len(self._sent) < self.pipeline:
            self._send(wire, self._waiting.popleft())

    def _received(self, wire: _Wire, data: bytes) -> None:
        if wire is not self._wire:
            return  # a connection dropped already
        self._heard = wire.loop.time()
        buffer = wire.received
        buffer += data
        while len(buffer) >= _MBAP.size:
            tid, protocol, length, unit = _MBAP.unpack_from(buffer)
            if protocol != 0 or length not in _LENGTHS:
                self._drop(f"connection dropped: the device sent a frame that is not Modbus TCP (protocol id "
                           f"{protocol}, length {length})")
                return
            end = 6 + length
            if len(buffer) < end:
                break
            answer = bytes(buffer[_MBAP.size:end])
            del buffer[:end]
            t = self._sent.pop(tid, None)
            if t is None:
                self.late += 1
                continue
            _settle(t, None if unit == t.unit or not t.unit else
                    Unanswered(f"the answer came from unit {unit}, not {t.unit}"), answer)
        self._fill()

    def _set_alarm(self, loop: asyncio.AbstractEventLoop, deadline: float) -> None:
        if self._alarm is not None:
            self._alarm.cancel()
        self._alarm, self._alarm_at = loop.call_at(deadline, self._ring, loop), deadline

    def _ring(self, loop: asyncio.AbstractEventLoop) -> None:
        """The earliest deadline: every request past its own fails — if one was sent and the device was silent
        all the while it waited, the connection is dropped —, and the alarm is set for the next deadline."""
        self._alarm, self._alarm_at = None, math.inf
        now = loop.time() + _EARLY
        for t in [t for t in self._waiting if t.deadline <= now]:  # first: a slot freed below must not take them
            self._waiting.remove(t)
            _settle(t, Unanswered(f"no answer within {t.timeout:g} s (not sent: {len(self._sent)} requests waiting "
                                  f"for their answers, pipeline {self.pipeline})"))
        silent = None
        for t in [t for t in self._sent.values() if t.deadline <= now]:
            del self._sent[t.tid]
            _settle(t, Unanswered(f"no answer within {t.timeout:g} s"))
            if self._heard < t.sent:
                silent = t
        if silent is not None:
            self._drop(f"connection dropped: no answer within {silent.timeout:g} s to another request and nothing "
                       "heard from the device since it was sent")
        else:
            self._fill()
        deadline = min((t.deadline for t in (*self._sent.values(), *self._waiting)), default=math.inf)
        if deadline < math.inf:
            self._set_alarm(loop, deadline)

    def _forget(self, t: _Transaction) -> None:
        if self._sent.get(t.tid) is t:
            del self._sent[t.tid]
            self._fill()
        elif t in self._waiting:
            self._waiting.remove(t)

    # -- losing the connection --------------------------------------------------------------

    def _fail_all(self, error: str) -> None:
        pending = [*self._sent.values(), *self._waiting]
        self._sent.clear()
        self._waiting.clear()
        for t in pending:
            _settle(t, Unanswered(error))

    def _drop(self, error: str) -> None:
        wire, self._wire = self._wire, None
        if wire is not None and wire.transport is not None:
            wire.transport.abort()
            self.dropped += 1
        self._fail_all(error)

    def _lost(self, wire: _Wire, exc: Exception | None) -> None:
        if wire is self._wire:
            self._wire = None
            self._fail_all(f"connection lost ({'closed by the device' if exc is None else f'{type(exc).__name__}: {exc}'})")

    def close(self) -> None:
        if self._connecting is not None:
            self._connecting.cancel()
        if self._alarm is not None:
            self._alarm.cancel()
            self._alarm, self._alarm_at = None, math.inf
        wire, self._wire = self._wire, None
        if wire is not None and wire.transport is not None:
            wire.transport.close()
        self._fail_all("the link was closed")


def _settle(t: _Transaction, error: Exception | None, answer: bytes = b"") -> None:
    """Complete ``t`` with ``answer`` or ``error`` (if not done: a cancelled caller's is)."""
    if t.answer.done():
        return
    if error is None:
        t.answer.set_result(answer)
    else:
        t.answer.set_exception(error)


def _retrieved(task: asyncio.Task[None]) -> None:
    """Mark the outcome of a connection attempt seen (its waiters may all have timed out)."""
    if not task.cancelled():
        task.exception()
