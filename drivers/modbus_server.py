"""Simulated PLCs (:class:`~drivers.simplc.SimulatedPlc`) served over Modbus TCP (pymodbus 3.16), one per unit id.

The datastore is *live*: pymodbus 3.16 stores registers in a
:class:`pymodbus.simulator.SimDevice`, whose ``action`` coroutine is called on
every request before it is served, with the table's register list to modify
in place. The action here

* on every request rewrites from the PLC the registers of the signals it
  touches (``plc.read_pv()``, ``plc.mv``, ``plc.sp``, ``plc.hv``, ``plc.mode``,
  ``plc.gains``, ``plc.flags``), so a read returns the PLC's values at the
  moment it is answered; the PLC ticks in the same event loop, so one
  request is a consistent snapshot (all its registers from the same sample);
* on a write, decodes the written signals (any signal the written range
  touches, completed from the current values) and applies them to the PLC:
  ``sp``, ``hv`` (manual MV), ``mode``, the gains (through ``set_gains``,
  bumpless), ``tune``, ``tbrk``, ``tbsy``, ``te``, ``ite``. ``pv`` and ``mv``
  are the PLC's own and writes to them (if a map puts them in a holding
  register) are ignored. A mode other than 0/1 or gains that
  :class:`~autotuner.engine.control.gains.Gains` rejects are refused with exception 3
  (illegal data value), like a PLC refusing a bad parameter.

Addresses outside the map answer exception 2 (illegal data address),
unmapped coils next to mapped ones included. One server serves one PLC per
unit id (a pymodbus ``SimDevice`` each, the list handed to one
``ModbusTcpServer``, as pymodbus simulates an RS485 line); a request to a
unit id it does not serve answers exception 11 (gateway target device failed
to respond), what pymodbus's request handler answers when the datastore
raises ``NoSuchIdException`` and what a Modbus TCP gateway answers for a
device that is not there. (pymodbus's own SimDevice datastore would answer
exception 4 and log a traceback: it looks the id up without a check.)
There is no separate sync step after ``plc.tick()``: nothing is cached, so
nothing can be stale.

Fault hooks for tests: :meth:`ModbusPlcServer.fail_with_exception` (requests
answer a Modbus exception), :meth:`ModbusPlcServer.hang` (requests get no
answer) and :meth:`ModbusPlcServer.close` (the server stops; its clients are
disconnected). NaN PV is the PLC's own fault (``plc.nan_pv = True``).
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import math
from collections.abc import Mapping
from contextlib import suppress

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import NoSuchIdException
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice


from .link import Mode
from .modbus_map import (
    BIT_TABLES,
    COIL,
    DEFAULT_MAP,
    DISCRETE,
    HOLDING,
    INPUT,
    ModbusMap,
    Register,
    ti_from_wire,
    ti_to_wire,
)
from .simplc import SimulatedPlc

__all__ = ["ModbusPlcServer", "serve_modbus", "serve_units"]

# Function code → table (pymodbus calls the action with the request's function code).
_FC_TABLE = {1: COIL, 5: COIL, 15: COIL, 2: DISCRETE, 4: INPUT, 3: HOLDING, 6: HOLDING, 16: HOLDING,
             22: HOLDING, 23: HOLDING}
# Order of the four blocks of a non-shared SimDevice.
_BLOCK_ORDER = (COIL, DISCRETE, HOLDING, INPUT)
# Watchdog signals → fields of :class:`drivers.link.Watchdog`.
_WATCHDOG_FIELDS = {"wd_time": "timeout", "wd_mv": "mv", "wd_mode": "mode"}
# An unused bit at the top of the address space keeps an empty bit table valid for pymodbus.
_FILLER_BIT = 65535
# Unit ids a SimDevice may have (0: every id not served otherwise, pymodbus's convention).
_UNIT_IDS = range(256)


def _plc_value(plc: SimulatedPlc, signal: str) -> float:
    """The engineering value the PLC serves for ``signal`` (on the wire convention: ti inf → 0)."""
    if signal == "pv":
        return plc.read_pv()
    if signal in ("mv", "hv", "sp"):
        return float(getattr(plc, signal))
    if signal == "mode":
        return float(int(plc.mode))
    if signal == "ti":
        return ti_to_wire(plc.gains.ti)
    if signal in ("k", "td", "nd", "b", "c"):
        return float(getattr(plc.gains, signal))
    if signal == "heartbeat":
        return float(plc.heartbeat)
    if signal in _WATCHDOG_FIELDS:
        return float(getattr(plc.watchdog, _WATCHDOG_FIELDS[signal]))
    flag = getattr(plc.flags, signal)
    return float(flag)


def _raw(reg: Register, value: float) -> list[int]:
    """``reg.encode`` that never fails: a value the type cannot hold is served as NaN / 0."""
    try:
        return reg.encode(value, strict=False)
    except ValueError:
        return reg.encode(math.nan, strict=False) if reg.type.startswith("float") else [0] * reg.size


class ModbusPlcServer:
    """A running Modbus TCP server in front of ``plcs`` (unit id → PLC); start one with :func:`serve_modbus` or
    :func:`serve_units`."""

    def __init__(self, plcs: Mapping[int, SimulatedPlc], host: str, port: int, map: ModbusMap,
                 rtu_framing: bool = False) -> None:
        bad = sorted(u for u in plcs if u not in _UNIT_IDS)
        if not plcs or bad:
            raise ValueError(f"unit ids must be 0..255 and at least one, got {bad or 'none'}")
        self.plcs = dict(plcs)
        self.rtu_framing = rtu_framing
        self.map = map
        self.host = host
        self._requested_port = port
        self.port = 0
        self._fail: ExcCodes | None = None
        self._fail_writes = False
        self._hang = False
        self._release = asyncio.Event()
        self._server: ModbusTcpServer | None = None
        self._by_table: dict[str, list[tuple[str, Register]]] = {t: [] for t in _BLOCK_ORDER}
        for name, reg in map.registers.items():
            self._by_table[reg.table].append((name, reg))
        self._bits = {t: {r.address for _, r in self._by_table[t]} for t in BIT_TABLES}

    # -- lifecycle -----------------------------------------------------------

    def _device(self, unit: int, plc: SimulatedPlc) -> SimDevice:
        blocks: list[list[SimData]] = []
        for table in _BLOCK_ORDER:
            entries = self._by_table[table]
            if table in BIT_TABLES:
                data = [SimData(r.address, values=False, datatype=DataType.BITS) for _, r in entries]
                if not data:
                    data = [SimData(_FILLER_BIT, values=False, datatype=DataType.BITS)]
            else:
                data = [SimData(r.address, values=[0] * r.size, datatype=DataType.REGISTERS) for _, r in entries]
                if not data:
                    data = [SimData(0, datatype=DataType.INVALID)]
            blocks.append(data)
        return SimDevice(unit, simdata=tuple(blocks),  # type: ignore[arg-type]
                         action=functools.partial(self._action, plc))

    async def start(self) -> None:
        framer = FramerType.RTU if self.rtu_framing else FramerType.SOCKET
        devices = [self._device(unit, plc) for unit, plc in self.plcs.items()]
        server = ModbusTcpServer(devices, framer=framer, address=(self.host, self._requested_port))
        self._guard_datastore(server)
        await server.serve_forever(background=True)
        self._server = server
        sockets = getattr(server.transport, "sockets", None) or []
        self.port = sockets[0].getsockname()[1] if sockets else self._requested_port

    async def close(self) -> None:
        """Stop serving and drop every client connection (idempotent)."""
        self._release.set()
        server, self._server = self._server, None
        if server is not None:
            with suppress(Exception):
                await server.shutdown()
            await asyncio.sleep(0)  # let the handlers see their connections closed

    @property
    def serving(self) -> bool:
        return self._server is not None

    async def __aenter__(self) -> "ModbusPlcServer":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # -- fault hooks -----------------------------------------------------------

    def fail_with_exception(self, on: bool = True, code: ExcCodes = ExcCodes.DEVICE_FAILURE,
                            writes: bool = False) -> None:
        """While ``on``, reads (and writes too if ``writes``) answer Modbus exception ``code``."""
        self._fail = code if on else None
        self._fail_writes = writes

    def hang(self, on: bool = True) -> None:
        """While ``on``, requests get no answer (the client times out)."""
        self._hang = on
        if on:
            self._release.clear()
        else:
            self._release.set()

    # -- the live datastore ------------------------------------------------------

    def _mapped_bits(self, table: str, address: int, count: int) -> bool:
        """Whether every bit ``address`` .. ``address + count - 1`` of ``table`` is a signal of the map."""
        return count > 0 and all(a in self._bits[table] for a in range(address, address + count))

    def _serves(self, unit: int) -> bool:
        """Whether requests to ``unit`` reach a PLC (unit 0 of :attr:`plcs` takes every id)."""
        return unit in self.plcs or 0 in self.plcs

    def _guard_datastore(self, server: ModbusTcpServer) -> None:
        """Refuse, at the server's datastore entry points, what the SimDevices' actions cannot see.

        A unit id no PLC answers on raises ``NoSuchIdException``, which pymodbus answers with exception 11
        (module docstring). A read of coils or discrete inputs that runs into an unmapped bit answers exception 2
        (docs/modbus.md): pymodbus keeps bits in 16-bit words and tells the action only the words a read touches,
        so the action cannot see how many bits were asked for; the entry point still has the request's bit count
        (writes carry their bits: the action checks those).
        """
        core = server.context
        served, stored = core.async_getValues, core.async_setValues

        async def get_values(device_id: int, func_code: int, address: int, count: int = 1) -> object:
            if not self._serves(device_id):
                raise NoSuchIdException(f"unit {device_id}")
            table = _FC_TABLE.get(func_code)
            if table in BIT_TABLES and not self._mapped_bits(table, address, count):
                if self._hang:
                    await self._release.wait()
                return ExcCodes.ILLEGAL_ADDRESS
            return await served(device_id, func_code, address, count)

        async def set_values(device_id: int, func_code: int, address: int, values: list[int] | list[bool]) -> object:
            if not self._serves(device_id):
                raise NoSuchIdException(f"unit {device_id}")
            return await stored(device_id, func_code, address, values)

        core.async_getValues = get_values  # type: ignore[method-assign]
        core.async_setValues = set_values  # type: ignore[method-assign]

    async def _action(self, plc: SimulatedPlc, func_code: int, start: int, address: int, count: int,
                      registers: list[int], values: list[int] | list[bool] | None) -> ExcCodes | None:
        if self._hang:
            await self._release.wait()
        table = _FC_TABLE.get(func_code)
        if table is None:
            return ExcCodes.ILLEGAL_FUNCTION
        if table in BIT_TABLES:
            # pymodbus keeps bits in 16-bit words, so the neighbours of a mapped bit would answer: the map's don't.
            # (A read's bit count is checked before, in _guard_datastore: here it is in words.)
            bits = len(values) if values is not None else 1
            if not self._mapped_bits(table, address, bits):
                return ExcCodes.ILLEGAL_ADDRESS
        writing = values is not None
        if self._fail is not None and (not writing or self._fail_writes):
            return self._fail
        self._refresh(plc, table, start, address, count, registers)
        if writing:
            return self._apply(plc, table, start, address, registers, list(values))  # type: ignore[arg-type]
        return None

    def _refresh(self, plc: SimulatedPlc, table: str, start: int, address: int, count: int,
                 registers: list[int]) -> None:
        """Rewrite from ``plc`` the registers of every signal a request of ``count`` registers from ``address``
        touches (of a bit table: all its bits, a handful); the rest of the table is never answered by it."""
        if table in BIT_TABLES:
            for name, reg in self._by_table[table]:
                _set_bit(registers, start, reg.address, bool(_plc_value(plc, name)))
            return
        end = address + count
        for name, reg in self._by_table[table]:
            if reg.address < end and reg.end > address:
                i = reg.address - start
                registers[i:i + reg.size] = _raw(reg, _plc_value(plc, name))

    def _apply(self, plc: SimulatedPlc, table: str, start: int, address: int, registers: list[int],
               values: list[int] | list[bool]) -> ExcCodes | None:
        """Decode what a write changes and apply it to ``plc``."""
        end = address + len(values)
        written: dict[str, float] = {}
        for name, reg in self._by_table[table]:
            if reg.end <= address or reg.address >= end:
                continue
            if table in BIT_TABLES:
                written[name] = float(bool(values[reg.address - address]))
            else:
                words = list(registers[reg.address - start:reg.end - start])
                for a in range(max(reg.address, address), min(reg.end, end)):
                    words[a - reg.address] = int(values[a - address])
                written[name] = reg.decode(words)
        return self._set_plc(plc, written)

    def _set_plc(self, plc: SimulatedPlc, written: dict[str, float]) -> ExcCodes | None:
        """Apply the decoded ``written`` signals to ``plc``, or refuse them all (exception 3) if one is invalid."""
        if any(not math.isfinite(v) for v in written.values()):
            return ExcCodes.ILLEGAL_VALUE
        for name in ("mode", "wd_mode"):
            if name in written and written[name] not in (0.0, 1.0):
                return ExcCodes.ILLEGAL_VALUE
        if written.get("wd_time", 0.0) < 0.0:
            return ExcCodes.ILLEGAL_VALUE
        gains = {s: written[s] for s in ("k", "ti", "td", "nd", "b", "c") if s in written}
        new_gains = None
        if gains:
            if "ti" in gains:
                gains["ti"] = ti_from_wire(gains["ti"])
            try:
                new_gains = dataclasses.replace(plc.gains, **gains)
            except (TypeError, ValueError):
                return ExcCodes.ILLEGAL_VALUE
        # Everything checked: apply.
        if "mode" in written:
            plc.mode = Mode(int(written["mode"]))
        if "sp" in written:
            plc.sp = written["sp"]
        if "hv" in written:
            plc.hv = written["hv"]
        if new_gains is not None and new_gains != plc.gains:
            plc.set_gains(new_gains)
        if "heartbeat" in written:
            plc.heartbeat = int(written["heartbeat"])
        watchdog = {f: written[s] for s, f in _WATCHDOG_FIELDS.items() if s in written}
        if watchdog:
            if "mode" in watchdog:
                watchdog["mode"] = Mode(int(watchdog["mode"]))
            plc.watchdog = dataclasses.replace(plc.watchdog, **watchdog)
        flags = {s: written[s] for s in ("tune", "tbrk", "tbsy", "te") if s in written}
        update: dict[str, object] = {s: bool(v) for s, v in flags.items()}
        if "ite" in written:
            update["ite"] = written["ite"]
        if update:
            plc.flags = dataclasses.replace(plc.flags, **update)
        return None


def _set_bit(registers: list[int], start: int, bit_address: int, value: bool) -> None:
    """Set one bit of a pymodbus bit block (16 bits per word, bit 0 first; ``start`` in words)."""
    i, b = divmod(bit_address, 16)
    i -= start
    if value:
        registers[i] |= 1 << b
    else:
        registers[i] &= ~(1 << b) & 0xFFFF


async def serve_modbus(plc: SimulatedPlc, host: str = "127.0.0.1", port: int = 0,
                       map: ModbusMap = DEFAULT_MAP, unit: int = 1,
                       rtu_framing: bool = False) -> ModbusPlcServer:
    """Serve ``plc`` over Modbus TCP at ``host:port`` (port 0: an ephemeral port, see ``.port``).

    ``unit`` (default 1, the unit of the URLs the CLI prints) is the only id
    answered with data, like a real device (requests to other ids get
    exception 11); 0 answers every unit id (a gateway-like test setup).
    ``rtu_framing`` serves RTU frames over the TCP socket ("RTU over TCP"),
    which an RTU client reaches with the pyserial URL ``socket://HOST:PORT``
    (how the RTU link is tested without a serial port).
    Close with ``await server.close()``.
    """
    return await serve_units({unit: plc}, host, port, map, rtu_framing)


async def serve_units(plcs: Mapping[int, SimulatedPlc], host: str = "127.0.0.1", port: int = 0,
                      map: ModbusMap = DEFAULT_MAP, rtu_framing: bool = False) -> ModbusPlcServer:
    """Serve every PLC of ``plcs`` (unit id 0..255 → PLC) with ``map`` from one Modbus TCP server at ``host:port``.

    Each unit id answers with its own PLC; other ids get exception 11 (unit 0
    among ``plcs`` answers every id not otherwise served). ``port`` 0: an
    ephemeral port (``.port``); ``rtu_framing`` as in :func:`serve_modbus`.
    ValueError for an empty mapping or a unit id outside 0..255.
    """
    server = ModbusPlcServer(plcs, host, port, map, rtu_framing)
    await server.start()
    return server
