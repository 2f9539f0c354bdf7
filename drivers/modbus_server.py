"""Simulated PLCs (:class:`~drivers.simplc.SimulatedPlc`) served over Modbus TCP (pymodbus 3.16), one per unit id.

The datastore is *live*: pymodbus 3.16 stores registers in a
:class:`pymodbus.simulator.SimDevice`, whose ``action`` coroutine is called on
every request before it is served, with the table's register list to modify
in place. The action here

* on every request rewrites from the PLC the registers of the signals it
  touches (``plc.read_pv()``, ``plc.mv``, ``plc.sp`` — also as ``sp_in`` —,
  ``plc.hv``, ``plc.mode`` — also as ``mode_in`` —, ``plc.gains``, ``plc.flags``), so a read returns the PLC's values at the
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

The fence of a fleet (docs/fleet.md): each PLC keeps the newest lease
epoch written to its ``epoch`` register (``plc.epoch``, 0 at its start),
each client connection the epoch it last wrote to each unit; the writes of a
connection whose epoch is older than the PLC's are refused (exception 3 for
an older epoch itself, 4 for any other write) and change nothing, counted in
``plc.fenced`` and logged once per connection and unit. A connection that
never wrote an epoch is not fenced. With RTU framing one connection is one
serial line, which has one master: the rule holds per line.

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

Pipelined requests (a client sending the next requests before the first
answer, told apart by their MBAP transaction ids) are each answered, with
their own transaction id, as soon as they are served — out of order when one
waits (a hung unit). pymodbus 3.16.1's own request handler cannot: it keeps
one request at a time (the last one decoded), handles only the first frame
of what it received, clears what it received when it answers and discards
more than 264 bytes received at once, so of three requests sent together it
answered the first only (measured; tests/test_modbus_share.py). The server
here hands each connection to :class:`_PipelinedHandler` instead.

Fault hooks for tests: :meth:`ModbusPlcServer.fail_with_exception` (requests
answer a Modbus exception), :meth:`ModbusPlcServer.hang` (requests, or those
to one unit, get no answer) and :meth:`ModbusPlcServer.close` (the server
stops; its clients are disconnected). NaN PV is the PLC's own fault
(``plc.nan_pv = True``). :attr:`ModbusPlcServer.connections` and
:attr:`ModbusPlcServer.accepted` count the clients' TCP connections,
:attr:`ModbusPlcServer.held` the requests a hang holds.
"""

from __future__ import annotations

import asyncio
import contextvars
import dataclasses
import functools
import logging
import math
from collections.abc import Mapping
from contextlib import suppress

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusIOException, NoSuchIdException
from pymodbus.logging import Log
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
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
# Bytes a connection may have received and not yet decoded: requests pipelined by a client, a few hundred at
# most (pymodbus's own limit, 264 bytes, is one frame: more is discarded).
_RECEIVE_BUFFER = 65536
log = logging.getLogger("drivers.modbus_server")


class _PipelinedHandler(ServerRequestHandler):
    """One client connection of the server: every request received is answered, with its own transaction id,
    however many arrive before the first answer (see the module's docstring). ``epochs``: the lease epoch this
    connection last wrote to each unit (the fence of a fleet: :meth:`ModbusPlcServer._fenced`)."""

    def __init__(self, owner: ModbusTcpServer) -> None:
        super().__init__(owner, owner.trace_packet, owner.trace_pdu, owner.trace_connect)
        self.max_buffer_size = _RECEIVE_BUFFER
        self._serving: set[asyncio.Task[None]] = set()
        self.epochs: dict[int, int] = {}
        self.fenced: set[int] = set()  # the units that have refused this connection's writes (logged once each)

    @property
    def peer(self) -> str:
        """The client's address, e.g. ``127.0.0.1:40312``."""
        address = self.transport.get_extra_info("peername") if self.transport else None  # type: ignore[attr-defined]
        return "a client" if not address else f"{address[0]}:{address[1]}"

    def callback_data(self, data: bytes, addr: tuple | None = None) -> int:
        """Decode every complete frame of ``data`` and serve each in a task of its own; the bytes used."""
        used = 0
        while used < len(data):
            try:
                length, pdu = self.framer.handleFrame(data[used:], 0, 0)
            except ModbusIOException as exc:  # undecodable: answered as pymodbus answers it
                code = 0 if exc.fcode is None else exc.fcode
                self.server_send(ExceptionResponse(code, exception_code=ExcCodes.ILLEGAL_FUNCTION,
                                                   device_id=exc.dev_id, transaction=exc.transaction_id), addr)
                return len(data)
            used += length
            if pdu is None:
                break
            task = self.loop.create_task(self._serve(pdu, addr))
            self._serving.add(task)
            task.add_done_callback(self._serving.discard)
        return used

    async def _serve(self, pdu: ModbusPDU, addr: tuple | None) -> None:
        """Answer ``pdu`` from the datastore (pymodbus's ``handle_request`` for one request of its own)."""
        _CLIENT.set(self)  # (this task's own context: the datastore's action knows whose request it serves)
        try:
            response = await pdu.datastore_update(self.server.context, pdu.dev_id)
        except NoSuchIdException:
            Log.error("requested device id does not exist: {}", pdu.dev_id)
            response = ExceptionResponse(pdu.function_code, ExcCodes.GATEWAY_NO_RESPONSE)
        except Exception as exc:  # noqa: BLE001 - the client gets exception 4, as from pymodbus's handler
            Log.error("Datastore unable to fulfill request: {}", exc)
            response = ExceptionResponse(pdu.function_code, ExcCodes.DEVICE_FAILURE)
        response.transaction_id = pdu.transaction_id
        response.dev_id = pdu.dev_id
        self.server_send(response, addr)

    def send(self, data: bytes, addr: tuple | None = None) -> None:
        """Write an answer; unlike pymodbus's ``send``, what was received and not yet decoded is kept."""
        if self.transport:
            self.transport.write(data)  # type: ignore[attr-defined]


# The connection whose request is being served (set in each request's task; None outside one).
_CLIENT: contextvars.ContextVar[_PipelinedHandler | None] = contextvars.ContextVar("modbus_client", default=None)


class _PipelinedTcpServer(ModbusTcpServer):
    """pymodbus's TCP server with a :class:`_PipelinedHandler` per connection; counts the connections accepted."""

    accepted = 0

    def callback_new_connection(self) -> ServerRequestHandler:
        self.accepted += 1
        return _PipelinedHandler(self)


def _plc_value(plc: SimulatedPlc, signal: str) -> float:
    """The engineering value the PLC serves for ``signal`` (on the wire convention: ti inf → 0)."""
    if signal == "pv":
        return plc.read_pv()
    if signal in ("mv", "hv", "sp"):
        return float(getattr(plc, signal))
    if signal == "sp_in":
        return float(plc.sp)
    if signal in ("mode", "mode_in"):
        return float(int(plc.mode))
    if signal == "ti":
        return ti_to_wire(plc.gains.ti)
    if signal in ("k", "td", "nd", "b", "c"):
        return float(getattr(plc.gains, signal))
    if signal == "heartbeat":
        return float(plc.heartbeat)
    if signal == "boot":
        return float(plc.boot)
    if signal == "epoch":
        return float(plc.epoch)
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
        self._hang_unit: int | None = None
        self.held = 0  # requests held unanswered by hang() now
        self._release = asyncio.Event()
        self._server: _PipelinedTcpServer | None = None
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
                         action=functools.partial(self._action, unit, plc))

    async def start(self) -> None:
        framer = FramerType.RTU if self.rtu_framing else FramerType.SOCKET
        devices = [self._device(unit, plc) for unit, plc in self.plcs.items()]
        server = _PipelinedTcpServer(devices, framer=framer, address=(self.host, self._requested_port))
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

    @property
    def connections(self) -> int:
        """Client connections open now."""
        return 0 if self._server is None else len(self._server.active_connections)

    @property
    def accepted(self) -> int:
        """Client connections accepted since the server started."""
        return 0 if self._server is None else self._server.accepted

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

    def hang(self, on: bool = True, unit: int | None = None) -> None:
        """While ``on``, requests — to ``unit`` only, if given — get no answer (the client times out); off answers
        the requests held."""
        self._hang, self._hang_unit = on, unit
        if on:
            self._release.clear()
        else:
            self._release.set()

    async def _hold_if_hung(self, unit: int) -> None:
        """While hung (for ``unit``), wait for the release, counted in :attr:`held`."""
        if self._hang and self._hang_unit in (None, unit):
            self.held += 1
            try:
                await self._release.wait()
            finally:
                self.held -= 1

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
                await self._hold_if_hung(device_id)
                return ExcCodes.ILLEGAL_ADDRESS
            return await served(device_id, func_code, address, count)

        async def set_values(device_id: int, func_code: int, address: int, values: list[int] | list[bool]) -> object:
            if not self._serves(device_id):
                raise NoSuchIdException(f"unit {device_id}")
            return await stored(device_id, func_code, address, values)

        core.async_getValues = get_values  # type: ignore[method-assign]
        core.async_setValues = set_values  # type: ignore[method-assign]

    async def _action(self, unit: int, plc: SimulatedPlc, func_code: int, start: int, address: int, count: int,
                      registers: list[int], values: list[int] | list[bool] | None) -> ExcCodes | None:
        await self._hold_if_hung(unit)
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
            return self._apply(unit, plc, table, start, address, registers, list(values))  # type: ignore[arg-type]
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

    def _apply(self, unit: int, plc: SimulatedPlc, table: str, start: int, address: int, registers: list[int],
               values: list[int] | list[bool]) -> ExcCodes | None:
        """Decode what a write to ``unit`` changes and apply it to ``plc``."""
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
        return self._set_plc(unit, plc, written)

    def _fenced(self, unit: int, plc: SimulatedPlc, written: dict[str, float]) -> ExcCodes | None:
        """The fence of a fleet (docs/fleet.md): whether the connection writing ``written`` to ``unit`` is refused.

        The PLC keeps the newest lease epoch written to it (``plc.epoch``), each connection the epoch it last wrote
        to each unit. A write of an epoch older than the PLC's is refused with exception 3 (illegal data value: the
        value is refused) and leaves the connection fenced; any write from a connection whose epoch is older than
        the PLC's is refused with exception 4 (server device failure: the device will not do it, and a retry will
        not help — the writer was superseded). Nothing of a refused write is applied. A connection that never
        wrote an epoch (an HMI, a tuner outside a fleet) is not fenced. An epoch accepted becomes the PLC's.
        """
        client = _CLIENT.get()
        epochs = {} if client is None else client.epochs
        if "epoch" in written:
            epochs[unit] = int(written["epoch"])
        own = epochs.get(unit)
        if own is None or own >= plc.epoch:
            if own is not None:
                plc.epoch = own
            return None
        plc.fenced += 1
        if client is not None and unit not in client.fenced:
            client.fenced.add(unit)
            log.warning("unit %d: refused the writes of %s: its lease epoch %d is older than the unit's %d (another "
                        "tuner took the loop over); %d write(s) refused so far", unit, client.peer, own, plc.epoch,
                        plc.fenced)
        return ExcCodes.ILLEGAL_VALUE if "epoch" in written else ExcCodes.DEVICE_FAILURE

    def _set_plc(self, unit: int, plc: SimulatedPlc, written: dict[str, float]) -> ExcCodes | None:
        """Apply the decoded ``written`` signals to ``unit``'s ``plc``, or refuse them all: exception 3 if one is
        invalid, or a fenced writer (:meth:`_fenced`)."""
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
        fenced = self._fenced(unit, plc, written)
        if fenced is not None:
            return fenced
        # Everything checked (and the epoch written, if any, taken): apply.
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
