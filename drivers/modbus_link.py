"""The :class:`~drivers.link.Link` over Modbus TCP or RTU, one connection per device shared by its links.

Every link of the process to the same device — the same Modbus TCP host and
port, or the same serial port — sends through one connection
(:mod:`drivers.modbus_device`): :class:`~drivers.modbus_tcp.TcpDevice`, a
lean client multiplexing the links' requests by MBAP transaction id with up
to ``pipeline`` outstanding at once, or :class:`~drivers.modbus_rtu.RtuDevice`,
one pymodbus client per serial line, one request at a time. :meth:`ModbusLink.open`
takes the link's share of the device (and connects), :meth:`ModbusLink.close`
gives it back; the last link closed closes the connection.

Every call is bounded: connecting and each request wait at most ``timeout``
seconds, and a call makes at most ``1 + retries`` attempts, so a call returns
or raises :class:`~drivers.link.LinkError` within about
``(1 + retries) · 2 · timeout``. A request that times out is forgotten (a
late answer is discarded by its transaction id, never taken for another
request); a connection lost, or silent for a whole timeout, is dropped and
the next attempt (or the next call) connects anew — a PLC that restarts is
picked up again without the caller doing anything. A Modbus exception
response is the device's answer and is not retried. A NaN or infinite value
is never returned as data: it raises LinkError naming the signal.

Requests per call: signals of the same table whose addresses are adjacent
(or separated only by other mapped signals) are read or written in one
request, so with :data:`~drivers.modbus_map.DEFAULT_MAP` ``read_pv`` and
``read_sample`` are one request each, ``read_state`` two, ``write_gains``
one, ``read_flags`` and ``write_flags`` two each.

A daemon of a fleet sets :attr:`ModbusLink.epoch`, its lease's epoch: the
link then writes it to the map's ``epoch`` register before its first write
on each connection (and again when the epoch changes), as a request of its
own on the very connection the write goes on, and with every heartbeat,
pipelined with it. A write the device refuses while the device holds a
newer epoch than the link's raises :class:`~drivers.link.Fenced`
(docs/fleet.md).
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qs, unquote, urlsplit

from pymodbus.constants import ExcCodes

from autotuner.engine.control.gains import Gains

from .link import BadValue, Fenced, LinkError, LoopState, Mode, Sample, TuneFlags, Watchdog
from .modbus_device import Device, Endpoint, Unanswered, Unreachable, hold, let_go
from .modbus_map import (
    COIL,
    DEFAULT_MAP,
    DISCRETE,
    HOLDING,
    INPUT,
    ModbusMap,
    Register,
    load_map,
    ti_from_wire,
    ti_to_wire,
)
from .modbus_pdu import BadAnswer, Refused, answer_values, read_pdu, write_pdu
from .modbus_rtu import SerialLine
from .modbus_tcp import MAX_PIPELINE, TcpAddress

__all__ = ["ModbusLink"]

# Protocol limits per request (Modbus application protocol spec 1.1b3).
_MAX_READ = {HOLDING: 125, INPUT: 125, COIL: 2000, DISCRETE: 2000}
_MAX_WRITE = {HOLDING: 123, COIL: 1968}
# Defaults of the optional signals when the map lacks them.
_OPTIONAL_GAIN_DEFAULTS = {"td": 0.0, "nd": 10.0, "b": 1.0, "c": 0.0}

DEFAULT_PORT = 502


def _exc_name(code: int) -> str:
    try:
        return ExcCodes(code).name.lower().replace("_", " ")
    except ValueError:
        return "unknown"


def _spans(items: list[tuple[str, Register]], table_regs: Iterable[Register], limit: int
           ) -> list[tuple[int, int, list[tuple[str, Register]]]]:
    """Group signals of one table into requests: (start, count, members).

    Two signals share a request when every address between them belongs to a
    mapped signal of the table (so no request touches an address the device
    may not have) and the request stays within ``limit`` entries.
    """
    mapped: set[int] = set()
    for r in table_regs:
        mapped.update(range(r.address, r.end))
    spans: list[tuple[int, int, list[tuple[str, Register]]]] = []
    for name, reg in sorted(items, key=lambda e: e[1].address):
        if spans:
            start, count, members = spans[-1]
            end = start + count
            gap_ok = all(a in mapped for a in range(end, reg.address))
            new_end = max(end, reg.end)
            if gap_ok and new_end - start <= limit:
                spans[-1] = (start, new_end - start, members + [(name, reg)])
                continue
        spans.append((reg.address, reg.size, [(name, reg)]))
    return spans


@dataclass(frozen=True)
class _Request:
    """One read request of a plan: what it reads (for messages), its PDU, its first address and its signals."""

    where: str
    pdu: bytes
    start: int
    members: tuple[tuple[str, Register], ...]


@dataclass(frozen=True)
class _Write:
    """One write request of a plan: what it writes (for messages), its table, first address and signals."""

    where: str
    table: str
    start: int
    signals: tuple[str, ...]


def _where(verb: str, table: str, start: int, count: int, members: list[tuple[str, Register]]) -> str:
    """E.g. ``reading pv (input register 0 (float32))`` or ``reading pv, mv (input 0..3)``."""
    names = ", ".join(n for n, _ in members)
    place = members[0][1].describe() if len(members) == 1 else f"{table} {start}..{start + count - 1}"
    return f"{verb} {names} ({place})"


class ModbusLink:
    """A loop in a Modbus device (TCP or RTU) at ``endpoint``, addressed by ``unit``, laid out by ``map``.

    ``pipeline`` (TCP): how many requests the device may have outstanding at once on its one connection, all
    its links together (the smallest any of them asks for is used; a serial line takes one).
    """

    #: A Modbus value is taken while the request is served: no timestamp of its own.
    pv_age: float | None = None

    def __init__(self, endpoint: TcpAddress | SerialLine, unit: int = 1, map: ModbusMap = DEFAULT_MAP,
                 timeout: float = 1.0, retries: int = 2, pipeline: int = 1) -> None:
        if not 0 <= unit <= 255:
            raise ValueError(f"unit id must be 0..255, got {unit}")
        if not timeout > 0:
            raise ValueError(f"timeout must be > 0 seconds, got {timeout}")
        if retries < 0:
            raise ValueError(f"retries must be >= 0, got {retries}")
        if not 1 <= pipeline <= MAX_PIPELINE:
            raise ValueError(f"pipeline must be 1..{MAX_PIPELINE}, got {pipeline}")
        self.endpoint: Endpoint = endpoint
        self.name = endpoint.name
        self.unit = unit
        self.map = map
        self.timeout = float(timeout)
        self.retries = int(retries)
        self.pipeline = int(pipeline)
        self._device: Device | None = None  # held from open (or the first call) until close
        self._read_plans: dict[tuple[str, ...], tuple[_Request, ...]] = {}
        self._write_plans: dict[tuple[str, ...], tuple[_Write, ...]] = {}
        self.epoch: int | None = None  # the lease epoch the writes carry (a fleet's daemon sets it; None: none)
        self._epoch_sent: tuple[int, int] | None = None  # (the device's connection number, the epoch) written last
        self.requests = 0  # requests sent (for tests and statistics)
        self.failures = 0  # calls that failed (no answer after every attempt, exception response)
        self.last_error = ""

    def __repr__(self) -> str:
        return f"ModbusLink({self.name}, unit {self.unit})"

    # -- constructors ----------------------------------------------------------

    @classmethod
    def tcp(cls, host: str, port: int = DEFAULT_PORT, unit: int = 1, map: ModbusMap = DEFAULT_MAP,
            timeout: float = 1.0, retries: int = 2, pipeline: int = 1) -> "ModbusLink":
        """Modbus TCP to ``host:port`` (the connection shared with every other link to the same host and port)."""
        return cls(TcpAddress(host, port), unit, map, timeout, retries, pipeline)

    @classmethod
    def rtu(cls, port: str, baudrate: int = 19200, unit: int = 1, map: ModbusMap = DEFAULT_MAP,
            timeout: float = 1.0, retries: int = 2, parity: str = "N", stopbits: int = 1,
            bytesize: int = 8) -> "ModbusLink":
        """Modbus RTU on serial ``port`` (e.g. ``/dev/ttyUSB0``, ``COM3``; the line shared with every other link
        to a unit on it)."""
        if parity not in ("N", "E", "O"):
            raise ValueError(f"parity must be N, E or O, got {parity!r}")
        return cls(SerialLine(port, baudrate, parity, stopbits, bytesize), unit, map, timeout, retries)

    @classmethod
    def from_url(cls, url: str, map_path: str | None = None) -> "ModbusLink":
        """A link from a URL (``map_path``: a YAML register map, else DEFAULT_MAP).

        * ``modbus://HOST[:PORT][/UNIT]`` — TCP, port 502 and unit 1 by default
          (``modbus+tcp://`` also accepted; IPv6 as ``modbus://[::1]:5020/1``);
          option ``pipeline`` (1..128, default 1): requests outstanding at once on the device's connection;
        * ``modbus+rtu://DEVICE[?baudrate=19200&unit=1&parity=N&stopbits=1]`` —
          serial RTU, e.g. ``modbus+rtu:///dev/ttyUSB0?baudrate=9600&unit=3``;
        * query options for both: ``timeout`` (seconds), ``retries``.
        """
        try:
            parts = urlsplit(url)
        except ValueError as exc:
            raise ValueError(f"bad Modbus URL {url!r}: {exc}") from None
        scheme = parts.scheme.lower()
        query = {k: v[-1] for k, v in parse_qs(parts.query, keep_blank_values=True).items()}

        def take(key: str, conv: Callable[[str], Any], default: Any) -> Any:
            if key not in query:
                return default
            raw = query.pop(key)
            try:
                return conv(raw)
            except ValueError:
                raise ValueError(f"bad Modbus URL {url!r}: {key}={raw!r} is not valid") from None

        timeout = take("timeout", float, 1.0)
        retries = take("retries", int, 2)
        mp = load_map(map_path) if map_path else DEFAULT_MAP
        if scheme in ("modbus", "modbus+tcp"):
            if not parts.hostname:
                raise ValueError(f"bad Modbus URL {url!r}: no host (expected modbus://HOST[:PORT][/UNIT])")
            try:
                port = parts.port or DEFAULT_PORT
            except ValueError:
                raise ValueError(f"bad Modbus URL {url!r}: the port is not a number in 0..65535") from None
            path = parts.path.strip("/")
            unit = take("unit", int, 1)
            if path:
                if not path.isdigit():
                    raise ValueError(f"bad Modbus URL {url!r}: the unit id {path!r} is not a number "
                                     "(expected modbus://HOST[:PORT][/UNIT])")
                unit = int(path)
            if not 0 <= unit <= 255:
                raise ValueError(f"bad Modbus URL {url!r}: unit id {unit} is outside 0..255")
            pipeline = take("pipeline", int, 1)
            if not 1 <= pipeline <= MAX_PIPELINE:
                raise ValueError(f"bad Modbus URL {url!r}: pipeline={pipeline} is outside 1..{MAX_PIPELINE}")
            if query:
                raise ValueError(f"bad Modbus URL {url!r}: unknown option(s) {', '.join(sorted(query))}")
            return cls.tcp(parts.hostname, port, unit, mp, timeout, retries, pipeline)
        if scheme == "modbus+rtu":
            device = unquote(parts.netloc + parts.path)
            if not device:
                raise ValueError(f"bad Modbus URL {url!r}: no serial device (expected modbus+rtu:///dev/ttyUSB0)")
            baudrate = take("baudrate", int, 19200)
            unit = take("unit", int, 1)
            parity = take("parity", str, "N").upper()
            stopbits = take("stopbits", int, 1)
            if not 0 <= unit <= 255:
                raise ValueError(f"bad Modbus URL {url!r}: unit id {unit} is outside 0..255")
            if "pipeline" in query:
                raise ValueError(f"bad Modbus URL {url!r}: pipeline is for Modbus TCP (a serial line carries one "
                                 "request at a time)")
            if query:
                raise ValueError(f"bad Modbus URL {url!r}: unknown option(s) {', '.join(sorted(query))}")
            return cls.rtu(device, baudrate, unit, mp, timeout, retries, parity=parity, stopbits=stopbits)
        raise ValueError(f"bad Modbus URL {url!r}: scheme must be modbus:// (TCP) or modbus+rtu:// (serial)")

    # -- connection ---------------------------------------------------------------

    async def open(self) -> None:
        """Take the link's share of the device and connect; LinkError if the device cannot be reached within the
        timeout (the share is given back then)."""
        device = self._hold()
        try:
            await device.connect(self.timeout)
        except Unreachable as exc:
            self._let_go()
            raise LinkError(f"{self.name}: connecting: {exc}") from None

    async def close(self) -> None:
        """Give the link's share of the device back (the last link's closes the connection); never raises."""
        self._let_go()

    async def __aenter__(self) -> "ModbusLink":
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def _hold(self) -> Device:
        if self._device is None:
            try:
                self._device = hold(self.endpoint, self.pipeline)
            except ValueError as exc:
                raise LinkError(f"{self.name}: {exc}") from None
        return self._device

    def _let_go(self) -> None:
        device, self._device = self._device, None
        self._epoch_sent = None  # (a device opened again counts its connections afresh)
        if device is not None:
            let_go(self.endpoint, device, self.pipeline)

    def _failed(self, text: str) -> None:
        self.failures += 1
        self.last_error = text

    def health(self) -> dict[str, Any]:
        """Connection state and request counters of the link, and of its device's connection (``links`` sharing
        it, its ``pipeline``, ``connects``, ``dropped`` connections, ``late_answers`` discarded)."""
        device = self._device
        shared = {} if device is None else device.health()
        return {"transport": "modbus", "device": self.name, "connected": device is not None and device.connected,
                "requests": self.requests, "failures": self.failures, "last_error": self.last_error, **shared}

    @property
    def carries_epoch(self) -> bool:
        """Whether the map has an ``epoch`` register (the device-side fence of a fleet)."""
        return "epoch" in self.map

    def _epoch_due(self, connection: int) -> int | None:
        """The epoch to write on connection number ``connection`` before a write: the link's, unless written on it
        already (None: nothing to write — no epoch, no register, or written)."""
        epoch = self.epoch
        if epoch is None or not self.carries_epoch or self._epoch_sent == (connection, epoch):
            return None
        return epoch

    async def _send(self, device: Device, pdu: bytes, write: bool) -> list[int]:
        """One attempt of a request on the device's connection, connected first; a write preceded, on the same
        connection, by the link's epoch where it is due (:meth:`_epoch_due`)."""
        if not device.connected:
            await device.connect(self.timeout)
        connection = device.connects
        epoch = self._epoch_due(connection) if write else None
        if epoch is not None:
            reg = self.map["epoch"]
            try:
                fence = write_pdu(reg.table, reg.address, reg.encode(epoch))
            except ValueError as exc:  # (a map's epoch register too narrow for it)
                raise LinkError(f"{self.name}: cannot write epoch {epoch} to {reg.describe()}: {exc}") from None
            self.requests += 1
            answer_values(fence, await device.request(self.unit, fence, self.timeout, connection))
            self._epoch_sent = (connection, epoch)
        self.requests += 1
        return answer_values(pdu, await device.request(self.unit, pdu, self.timeout, connection))

    async def _refusal(self, text: str, write: bool) -> LinkError:
        """The error of a request the device refused (``text`` says how): :class:`Fenced` if it is a write and the
        device holds a newer epoch than the link's (read now), else a LinkError."""
        epoch = self.epoch
        if not write or epoch is None or not self.carries_epoch:
            return LinkError(text)
        try:
            newest = int((await self._read(("epoch",)))["epoch"])
        except LinkError:
            return LinkError(text)
        if newest <= epoch:
            return LinkError(text)
        return Fenced(f"{text}: the device was written lease epoch {newest}, newer than this daemon's epoch "
                      f"{epoch} (another daemon took the loop over): nothing more is written to it")

    async def _exchange(self, what: str, pdu: bytes, write: bool = False) -> list[int]:
        """One request with retries and reconnection: the values of its answer (none for a ``write``), or LinkError
        (:class:`Fenced`: a write refused by a device that holds a newer epoch)."""
        device = self._hold()
        last = ""
        for _ in range(1 + self.retries):
            try:
                return await self._send(device, pdu, write)
            except (Unreachable, Unanswered) as exc:
                last = f"{self.name}: {what}: {exc}"
            except BadAnswer as exc:
                last = f"{self.name}: {what}: a bad answer: {exc}"
            except Refused as exc:
                text = (f"{self.name}: {what}: unit {self.unit} answered Modbus exception {exc.code} "
                        f"({_exc_name(exc.code)})")
                self._failed(text)
                raise await self._refusal(text, write) from None
        attempts = 1 + self.retries
        self._failed(last)
        raise LinkError(f"{last} (gave up after {attempts} attempt{'s' if attempts > 1 else ''})")

    # -- generic reads and writes -------------------------------------------------

    def _read_plan(self, signals: tuple[str, ...]) -> tuple[_Request, ...]:
        """The read requests of ``signals`` (those in the map), in as few requests as the map allows; made once
        per link and tuple of signals (a sample's PV read is the same request every time)."""
        plan = self._read_plans.get(signals)
        if plan is None:
            by_table: dict[str, list[tuple[str, Register]]] = {}
            for s in signals:
                reg = self.map.get(s)
                if reg is not None:
                    by_table.setdefault(reg.table, []).append((s, reg))
            plan = self._read_plans[signals] = tuple(
                _Request(_where("reading", table, start, count, members), read_pdu(table, start, count), start,
                         tuple(members))
                for table, items in by_table.items()
                for start, count, members in _spans(items, [r for r in self.map.registers.values()
                                                            if r.table == table], _MAX_READ[table]))
        return plan

    async def _read(self, signals: tuple[str, ...]) -> dict[str, float]:
        """Engineering values of ``signals`` (those in the map), in as few requests as the map allows."""
        out: dict[str, float] = {}
        for request in self._read_plan(signals):
            data = await self._exchange(request.where, request.pdu)
            for name, reg in request.members:
                i = reg.address - request.start
                try:
                    value = reg.decode(data[i:i + reg.size])
                except ValueError as exc:
                    raise LinkError(f"{self.name}: {name}: cannot decode: {exc}") from None
                if not math.isfinite(value):
                    raise BadValue(f"{self.name}: {name} is not a number ({value}) in {reg.describe()}")
                out[name] = value
        return out

    def _write_plan(self, signals: tuple[str, ...]) -> tuple[_Write, ...]:
        """The write requests of ``signals`` (all in the map): adjacent ones of a table share a request — only the
        signals being written (no read-modify-write); made once per link and tuple of signals."""
        plan = self._write_plans.get(signals)
        if plan is None:
            by_table: dict[str, list[tuple[str, Register]]] = {}
            for s in signals:
                by_table.setdefault(self.map[s].table, []).append((s, self.map[s]))
            plan = self._write_plans[signals] = tuple(
                _Write(_where("writing", table, start, count, members), table, start, tuple(n for n, _ in members))
                for table, items in by_table.items()
                for start, count, members in _spans(items, [r for _, r in items], _MAX_WRITE[table]))
        return plan

    async def _write(self, values: dict[str, float]) -> None:
        """Write engineering values (signals in the map), adjacent ones of a table in one request."""
        raw: dict[str, list[int]] = {}
        for s, v in values.items():
            reg = self.map[s]
            if not reg.is_bit and not math.isfinite(v):
                raise LinkError(f"{self.name}: refusing to write {s} = {v} (not a number)")
            try:
                raw[s] = reg.encode(v)
            except ValueError as exc:
                raise LinkError(f"{self.name}: cannot write {s} to {reg.describe()}: {exc}") from None
        for request in self._write_plan(tuple(values)):
            words = [w for n in request.signals for w in raw[n]]
            await self._exchange(request.where, write_pdu(request.table, request.start, words), write=True)

    # -- the Link protocol ------------------------------------------------------

    async def read_pv(self) -> float:
        """The PV (one request); LinkError if unreadable or not a finite number."""
        return (await self._read(("pv",)))["pv"]

    async def write_mv(self, mv: float) -> None:
        """Write the manual MV (``hv``)."""
        await self._write({"hv": float(mv)})

    async def read_state(self) -> LoopState:
        """Mode, actual MV, SP and gains."""
        v = await self._read(("mode", "mv", "sp", "k", "ti", "td", "nd", "b", "c"))
        mode = self._mode(v["mode"])
        g = {s: v.get(s, d) for s, d in _OPTIONAL_GAIN_DEFAULTS.items()}
        try:
            gains = Gains(k=v["k"], ti=ti_from_wire(v["ti"]), **g)
        except ValueError as exc:
            raise LinkError(f"{self.name}: the controller's gains are not usable: {exc}") from None
        return LoopState(mode=mode, mv=v["mv"], sp=v["sp"], gains=gains)

    async def read_sample(self) -> Sample:
        """PV, actual MV, SP, mode and the device's boot token: one request with the default map (``pv``, ``mv``,
        ``sp_in``, ``mode_in``, ``boot`` in input registers 0..7); a map without ``sp_in``/``mode_in`` reads ``sp``
        and ``mode`` instead (with the default map's layout otherwise: two requests), one without ``boot`` no
        token."""
        sp = "sp_in" if "sp_in" in self.map else "sp"
        mode = "mode_in" if "mode_in" in self.map else "mode"
        v = await self._read(("pv", "mv", sp, mode, "boot"))
        boot = v.get("boot")
        return Sample(pv=v["pv"], mv=v["mv"], sp=v[sp], mode=self._mode(v[mode]),
                      boot=None if boot is None else int(boot))

    def _mode(self, raw: float) -> Mode:
        try:
            return Mode(int(raw)) if raw == int(raw) else Mode(-1)
        except ValueError:
            raise LinkError(f"{self.name}: mode reads {raw:g}, neither {Mode.MAN.value} (MAN) "
                            f"nor {Mode.AUTO.value} (AUTO)") from None

    async def write_mode(self, mode: Mode) -> None:
        await self._write({"mode": float(int(Mode(mode)))})

    async def write_gains(self, gains: Gains) -> None:
        """Write k, ti (inf as 0), td, nd, b, c; a non-default value for a signal the map lacks is a LinkError."""
        values = {"k": gains.k, "ti": ti_to_wire(gains.ti), "td": gains.td,
                  "nd": gains.nd, "b": gains.b, "c": gains.c}
        for s, default in _OPTIONAL_GAIN_DEFAULTS.items():
            if s not in self.map:
                if values[s] != default:
                    raise LinkError(f"{self.name}: the map has no {s}, cannot write {s} = {values[s]:g}")
                del values[s]
        await self._write(values)

    async def read_flags(self) -> TuneFlags:
        """TUNE, TBRK, TBSY, TE and ite (False/0 for those the map lacks)."""
        v = await self._read(("tune", "tbrk", "tbsy", "te", "ite"))
        return TuneFlags(tune=bool(v.get("tune", 0.0)), tbrk=bool(v.get("tbrk", 0.0)),
                         tbsy=bool(v.get("tbsy", 0.0)), te=bool(v.get("te", 0.0)),
                         ite=v.get("ite", 0.0))

    async def write_flags(self, flags: TuneFlags) -> None:
        """TBSY, TE and ite (those the map has; the handshake is optional)."""
        values = {"tbsy": float(flags.tbsy), "te": float(flags.te), "ite": float(flags.ite)}
        await self._write({s: v for s, v in values.items() if s in self.map})

    def mv_resolution(self, mv: float) -> float:
        """The coding step of ``hv`` (written) plus that of ``mv`` (read back) near ``mv``."""
        return self.map["hv"].resolution(mv) + self.map["mv"].resolution(mv)

    async def write_watchdog(self, watchdog: Watchdog) -> None:
        """``wd_mv`` and ``wd_mode`` (when arming), then ``wd_time``: two requests, so the timeout is never armed
        with the fallback of before, whatever the map's addresses; nothing if the map has no ``wd_time``."""
        if "wd_time" not in self.map:
            return
        if watchdog.timeout > 0.0:
            fallback = {"wd_mv": float(watchdog.mv), "wd_mode": float(int(Mode(watchdog.mode)))}
            await self._write({s: v for s, v in fallback.items() if s in self.map})
        await self._write({"wd_time": float(watchdog.timeout)})

    async def write_heartbeat(self, counter: int) -> None:
        """``heartbeat`` = ``counter`` mod 65536 (nothing if the map has none), and the link's epoch with it, the two
        writes pipelined (when the link has an epoch and the map a register for it)."""
        if "heartbeat" not in self.map:
            return
        beat = self._write({"heartbeat": float(counter % 65536)})
        if self.epoch is None or not self.carries_epoch:
            await beat
            return
        await asyncio.gather(beat, self._write({"epoch": float(self.epoch)}))
