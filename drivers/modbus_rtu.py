"""A Modbus RTU serial line shared by every unit on it: one pymodbus client per port, one request at a time.

A serial line has one master: two clients on one port would talk over each
other. :class:`RtuDevice` is the :class:`~drivers.modbus_device.Device` of a
line (:class:`SerialLine`): every link to a unit on that port sends through
its one pymodbus 3.16 client, one request at a time in the order asked. A
request's timeout counts from the call, the wait for the line included; a
request that times out once sent drops the client (RTU frames carry no
transaction id: a late answer must not meet the next request), and the next
request opens the port anew.
"""

from __future__ import annotations

import asyncio
from collections import Counter
from contextlib import suppress
from dataclasses import dataclass
from typing import Any

from pymodbus.client import AsyncModbusSerialClient
from pymodbus.exceptions import ModbusException
from pymodbus.pdu import DecodePDU

from .modbus_device import Device, Unanswered, Unreachable

__all__ = ["SerialLine", "RtuDevice"]

# Request PDUs → pymodbus request objects (the client sends those).
_REQUESTS = DecodePDU(True)


@dataclass(frozen=True)
class SerialLine:
    """A serial port and its settings; every link to a unit on ``port`` shares its one client."""

    port: str
    baudrate: int = 19200
    parity: str = "N"
    stopbits: int = 1
    bytesize: int = 8

    @property
    def key(self) -> tuple[str, str]:
        return ("rtu", self.port)

    @property
    def name(self) -> str:
        """E.g. ``modbus rtu /dev/ttyUSB0@19200``."""
        return f"modbus rtu {self.port}@{self.baudrate}"

    @property
    def settings(self) -> str:
        """E.g. ``19200 baud 8N1``."""
        return f"{self.baudrate} baud {self.bytesize}{self.parity}{self.stopbits}"

    def open_device(self) -> RtuDevice:
        return RtuDevice(self)

    def check_compatible(self, device: Device) -> None:
        """ValueError if the line is open with other settings (one port, one baud rate and framing)."""
        line = device.line if isinstance(device, RtuDevice) else None
        if line is not None and line != self:
            raise ValueError(f"serial port {self.port} is open at {line.settings} by other loops; this link asks "
                             f"for {self.settings}")


class RtuDevice:
    """The shared client of one serial line (see the module's docstring)."""

    #: One request at a time, whatever the holders ask.
    pipeline = 1

    def __init__(self, line: SerialLine) -> None:
        self.line = line
        self.holders: Counter[int] = Counter()
        self._client: Any = None
        self._turn = asyncio.Lock()  # the line: one request (or connection attempt) at a time
        self.connects = 0
        self.dropped = 0  # clients dropped after a timeout or a failure

    def __repr__(self) -> str:
        return f"RtuDevice({self.line.name}, {sum(self.holders.values())} links)"

    @property
    def connected(self) -> bool:
        return self._client is not None and bool(self._client.connected)

    def health(self) -> dict[str, Any]:
        return {"links": sum(self.holders.values()), "pipeline": 1, "connects": self.connects,
                "dropped": self.dropped}

    async def connect(self, timeout: float) -> None:
        if self.connected:
            return
        try:
            async with asyncio.timeout(timeout), self._turn:
                if not self.connected:
                    await self._open(timeout)
        except TimeoutError:
            raise Unreachable(f"cannot connect (TimeoutError) within {timeout:g} s") from None

    async def _open(self, timeout: float) -> None:
        self.close()  # a client the line lost
        line = self.line
        try:
            # reconnect_delay=0: no background reconnection, the device reconnects on demand; retries=0: the link
            # retries.
            client = AsyncModbusSerialClient(line.port, baudrate=line.baudrate, parity=line.parity,
                                             stopbits=line.stopbits, bytesize=line.bytesize, timeout=timeout,
                                             retries=0, reconnect_delay=0)
        except Exception as exc:  # bad serial port name, pyserial missing, ...
            raise Unreachable(f"cannot create the client: {exc}") from exc
        try:
            ok = await client.connect()
        except (OSError, ModbusException) as exc:
            ok, reason = False, f"{type(exc).__name__} {exc}".strip()
        else:
            reason = "the port cannot be opened"
        if not ok or not client.connected:
            with suppress(Exception):
                client.close()
            raise Unreachable(f"cannot connect ({reason}) within {timeout:g} s")
        self._client = client
        self.connects += 1

    async def request(self, unit: int, pdu: bytes, timeout: float, connection: int | None = None) -> bytes:
        message = _REQUESTS.decode(pdu)
        if message is None:
            raise ValueError(f"not a request PDU: {pdu.hex()}")
        message.dev_id = unit
        sent = False
        try:
            async with asyncio.timeout(timeout), self._turn:
                if not self.connected or connection not in (None, self.connects):
                    raise Unanswered("not connected")
                sent = True
                answer = await self._client.execute(False, message)
        except TimeoutError:
            if not sent:
                raise Unanswered(f"no answer within {timeout:g} s (not sent: the line was busy)") from None
            self._drop()  # the late answer must not meet the next request
            raise Unanswered(f"no answer within {timeout:g} s") from None
        except asyncio.CancelledError:
            if sent:
                self._drop()
            raise
        except (ModbusException, OSError) as exc:
            self._drop()
            raise Unanswered(f"{type(exc).__name__}: {exc}") from None
        return bytes([answer.function_code]) + answer.encode()

    def _drop(self) -> None:
        """Close the client after a failure (counted)."""
        if self._client is not None:
            self.dropped += 1
        self.close()

    def close(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            with suppress(Exception):
                client.close()
