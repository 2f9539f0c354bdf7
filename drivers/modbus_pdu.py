"""Modbus PDUs of the requests the link makes, and the checks of their answers (Modbus application protocol 1.1b3).

A PDU is the function code and its data, without the transport's framing (MBAP header over TCP, unit id and
CRC over RTU). The link reads and writes four tables: coils (functions 1, 5, 15), discrete inputs (2),
holding registers (3, 6, 16) and input registers (4). :func:`read_pdu` and :func:`write_pdu` build the
request; :func:`answer_values` checks an answer against its request and returns what it carries — the values
read (16-bit words, or 0/1 bits), or nothing for a write — or raises :class:`Refused` for a Modbus exception
response (function code + 0x80 and an exception code) and :class:`BadAnswer` for anything that is not the
answer to that request.
"""

from __future__ import annotations

import struct

from .modbus_map import COIL, DISCRETE, HOLDING, INPUT

__all__ = ["BadAnswer", "Refused", "read_pdu", "write_pdu", "answer_values"]

_READ_FUNCTION = {COIL: 1, DISCRETE: 2, HOLDING: 3, INPUT: 4}
_BIT_READS = frozenset({1, 2})
_ECHOED_WRITES = frozenset({5, 6})  # single writes: the answer repeats the request
_MULTIPLE_WRITES = frozenset({15, 16})  # the answer repeats address and count
_EXCEPTION = 0x80


class Refused(Exception):
    """The device answered with Modbus exception ``code`` (its answer: not retried)."""

    def __init__(self, code: int) -> None:
        super().__init__(f"Modbus exception {code}")
        self.code = code


class BadAnswer(Exception):
    """An answer that does not answer its request (another function, a wrong length or echo)."""


def read_pdu(table: str, start: int, count: int) -> bytes:
    """Read ``count`` registers (or bits) of ``table`` from address ``start``."""
    return struct.pack(">BHH", _READ_FUNCTION[table], start, count)


def write_pdu(table: str, start: int, values: list[int]) -> bytes:
    """Write ``values`` (16-bit words of the holding registers, or 0/1 coils) from address ``start``: a single
    write (function 6 or 5) for one value, a multiple write (16 or 15) for more."""
    if table == HOLDING:
        if len(values) == 1:
            return struct.pack(">BHH", 6, start, values[0])
        return struct.pack(f">BHHB{len(values)}H", 16, start, len(values), 2 * len(values), *values)
    if table == COIL:
        if len(values) == 1:
            return struct.pack(">BHH", 5, start, 0xFF00 if values[0] else 0)
        packed = bytearray((len(values) + 7) // 8)
        for i, bit in enumerate(values):
            if bit:
                packed[i // 8] |= 1 << (i % 8)
        return struct.pack(">BHHB", 15, start, len(values), len(packed)) + bytes(packed)
    raise ValueError(f"table {table} cannot be written")


def answer_values(request: bytes, answer: bytes) -> list[int]:
    """The values an ``answer`` to a read ``request`` carries (words, or bits as 0/1), [] for a write's; raises
    Refused for an exception response, BadAnswer for an answer that does not fit the request."""
    function = request[0]
    if not answer:
        raise BadAnswer("an empty answer")
    if answer[0] == function | _EXCEPTION:
        if len(answer) != 2:
            raise BadAnswer(f"an exception response of {len(answer)} bytes")
        raise Refused(answer[1])
    if answer[0] != function:
        raise BadAnswer(f"function {answer[0]} answered a request of function {function}")
    if function in _ECHOED_WRITES:
        if answer != request:
            raise BadAnswer(f"the echo of a write of function {function} differs from the request")
        return []
    if function in _MULTIPLE_WRITES:
        if answer != request[:5]:
            raise BadAnswer(f"the answer to a write of function {function} names another address or count")
        return []
    count = struct.unpack_from(">H", request, 3)[0]
    size = (count + 7) // 8 if function in _BIT_READS else 2 * count
    if len(answer) != 2 + size or answer[1] != size:
        raise BadAnswer(f"{len(answer) - 2} bytes (byte count {answer[1] if len(answer) > 1 else '–'}) "
                        f"answered a read of {count}")
    if function in _BIT_READS:
        return [(answer[2 + i // 8] >> (i % 8)) & 1 for i in range(count)]
    return list(struct.unpack_from(f">{count}H", answer, 2))
