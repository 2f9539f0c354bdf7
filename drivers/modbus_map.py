"""Where each loop signal lives in a Modbus device, and how its value is coded.

A :class:`ModbusMap` gives, for every signal the tuner uses, a
:class:`Register`: the table (holding register, input register, coil,
discrete input), the address (0-based, as on the wire), the data type, the
word and byte order, and the scaling from the raw number to engineering
units, ``eng = raw · scale + offset``.

Signals (see docs/modbus.md for the default addresses):

========  ====================================================  ==========
signal    meaning                                               access
========  ====================================================  ==========
pv        process value                                         read
mv        actual controller output (MV) as the PLC applies it   read
hv        manual MV: the value the tuner writes, used in MAN    read/write
sp        set point                                             read
mode      0 = MAN, 1 = AUTO (:class:`drivers.link.Mode`)        read/write
sp_in     a read-only copy of sp, next to pv and mv (optional)  read
mode_in   a read-only copy of mode, next to pv and mv (opt.)    read
boot      a token the device draws anew at every start (opt.)   read
epoch     lease epoch of the fleet daemon writing (opt.)        read/write
k .. c    PID gains, standard form (:class:`autotuner.engine.control.gains`)   read/write
tune      TUNE: the operator asks for a tuning                  read
tbrk      TBRK: the operator breaks the tuning                  read
tbsy      TBSY: the tuner is busy                               write
te        TE: the tuning ended in error                         write
ite       seconds left while busy, error code when done         write
========  ====================================================  ==========

``ti`` has no infinity on the wire: a raw integral time of 0 means "no
integral action" (:func:`ti_to_wire` / :func:`ti_from_wire`), the usual PLC
convention; the tuner's :class:`~autotuner.engine.control.gains.Gains` use ``math.inf``.

Data types: ``int16, uint16, int32, uint32, float32, float64`` in register
tables; ``bool`` in the bit tables (coils, discrete inputs). ``word_order``
``big`` puts the most significant 16-bit word first (Modbus convention,
"ABCD"); ``little`` puts it last ("CDAB"). ``byte_order`` ``big`` is the
standard byte order inside each word; ``little`` swaps the two bytes of every
word ("BADC", or "DCBA" together with little word order).
"""

from __future__ import annotations

import math
import os
import struct
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Mapping

from .link import float32_step

__all__ = [
    "TABLES",
    "TYPES",
    "SIGNALS",
    "REQUIRED",
    "WRITABLE",
    "MapError",
    "Register",
    "ModbusMap",
    "DEFAULT_MAP",
    "load_map",
    "map_from_dict",
    "ti_to_wire",
    "ti_from_wire",
]

# Table names: holding registers (read/write words), input registers
# (read-only words), coils (read/write bits), discrete inputs (read-only bits).
HOLDING = "holding"
INPUT = "input"
COIL = "coil"
DISCRETE = "discrete_input"
TABLES = (HOLDING, INPUT, COIL, DISCRETE)
BIT_TABLES = frozenset({COIL, DISCRETE})
WRITABLE_TABLES = frozenset({HOLDING, COIL})

# Type name -> number of 16-bit registers (0 for a single bit).
TYPES: Mapping[str, int] = MappingProxyType(
    {"int16": 1, "uint16": 1, "int32": 2, "uint32": 2, "float32": 2, "float64": 4, "bool": 0}
)
# Type name -> the value big-endian, and its words (struct: ~1 µs a value, a third of pymodbus's conversions).
_VALUE = {t: struct.Struct(">" + f) for t, f in
          {"int16": "h", "uint16": "H", "int32": "i", "uint32": "I", "float32": "f", "float64": "d"}.items()}
_WORDS = {t: struct.Struct(f">{TYPES[t]}H") for t in _VALUE}
_INT_RANGE = {
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
}
ORDERS = ("big", "little")

GAIN_SIGNALS = ("k", "ti", "td", "nd", "b", "c")
FLAG_SIGNALS = ("tune", "tbrk", "tbsy", "te", "ite")
# The hand-back watchdog (docs/handback.md): heartbeat counter, timeout (device seconds, 0 = off), fallback MV, mode.
WATCHDOG_SIGNALS = ("heartbeat", "wd_time", "wd_mv", "wd_mode")
# Read-only copies of sp and mode that a map may put next to pv and mv: the monitor's reading of PV, MV, SP and
# mode (:meth:`drivers.modbus_link.ModbusLink.read_sample`) is then one request.
COPY_SIGNALS = ("sp_in", "mode_in")
# A token the device draws anew at every start (optional): a session that reads it change knows the device
# restarted with its registers at their defaults, and writes nothing more to it.
# The lease epoch a daemon of a fleet writes before its writes and with its heartbeat (optional): the device refuses
# the writes of a connection whose epoch is older than the newest it was written (docs/fleet.md).
SIGNALS = ("pv", "mv", "hv", "sp", "mode", *COPY_SIGNALS, "boot", *GAIN_SIGNALS, *FLAG_SIGNALS, *WATCHDOG_SIGNALS,
           "epoch")
# What a map must have for the tuner to run an experiment and report on it.
REQUIRED = frozenset({"pv", "mv", "hv", "sp", "mode", "k", "ti"})
# What the tuner writes: these must be in a writable table.
WRITABLE = frozenset({"hv", "mode", *GAIN_SIGNALS, "tbsy", "te", "ite", *WATCHDOG_SIGNALS, "epoch"})
# Boolean signals (the handshake bits) and the rest (numbers).
BOOL_SIGNALS = frozenset({"tune", "tbrk", "tbsy", "te"})


class MapError(ValueError):
    """A register map is not usable; the message names the file, the signal and the problem."""


def ti_to_wire(ti: float) -> float:
    """Integral time as written to a PLC: ``math.inf`` (no integral action) becomes 0."""
    return 0.0 if math.isinf(ti) else ti


def ti_from_wire(ti: float) -> float:
    """Integral time as read from a PLC: 0 means no integral action (``math.inf``)."""
    return math.inf if ti == 0.0 else ti


@dataclass(frozen=True)
class Register:
    """Where one signal lives and how its value is coded; ``eng = raw · scale + offset``."""

    table: str
    address: int
    type: str = "float32"
    word_order: str = "big"
    byte_order: str = "big"
    scale: float = 1.0
    offset: float = 0.0

    def __post_init__(self) -> None:
        if self.table not in TABLES:
            raise ValueError(f"unknown table {self.table!r} (one of {', '.join(TABLES)})")
        if self.type not in TYPES:
            raise ValueError(f"unknown type {self.type!r} (one of {', '.join(TYPES)})")
        if self.table in BIT_TABLES and self.type != "bool":
            raise ValueError(f"table {self.table} holds bits: type must be bool, not {self.type}")
        if self.table not in BIT_TABLES and self.type == "bool":
            raise ValueError(f"table {self.table} holds 16-bit registers: type bool needs a coil or discrete_input")
        if isinstance(self.address, bool) or not isinstance(self.address, int):
            raise ValueError(f"address must be an integer, got {self.address!r}")
        if not 0 <= self.address or self.address + self.size > 65536:
            raise ValueError(f"address {self.address} (size {self.size}) is outside 0..65535")
        for name in ("word_order", "byte_order"):
            if getattr(self, name) not in ORDERS:
                raise ValueError(f"{name} must be 'big' or 'little', got {getattr(self, name)!r}")
        for name in ("scale", "offset"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{name} must be a finite number, got {v!r}")
            object.__setattr__(self, name, float(v))
        if self.scale == 0.0:
            raise ValueError("scale must be non-zero")

    @property
    def size(self) -> int:
        """Number of table entries it occupies (registers, or 1 bit)."""
        return TYPES[self.type] or 1

    @property
    def is_bit(self) -> bool:
        return self.table in BIT_TABLES

    @property
    def end(self) -> int:
        """One past the last address it occupies."""
        return self.address + self.size

    def describe(self) -> str:
        """E.g. ``holding register 4 (float32)``."""
        kind = {HOLDING: "holding register", INPUT: "input register", COIL: "coil",
                DISCRETE: "discrete input"}[self.table]
        return f"{kind} {self.address}" + ("" if self.is_bit else f" ({self.type})")

    def resolution(self, value: float) -> float:
        """The step of the coding near the engineering ``value``: ``|scale|`` for an integer, a float32's or
        float64's spacing (times ``|scale|``) for a float."""
        if self.type in _INT_RANGE:
            return abs(self.scale)
        raw = (value - self.offset) / self.scale
        step = float32_step(raw) if self.type == "float32" else math.ulp(raw)
        return abs(self.scale) * step

    # -- coding ------------------------------------------------------------

    def encode(self, value: float, *, strict: bool = True) -> list[int]:
        """Engineering value → raw words (or ``[0]``/``[1]`` for a bit).

        Raises ValueError for a value outside the type's range, and for a
        NaN/infinite value unless ``strict`` is False and the type is a float
        (a simulator serving a NaN fault does that).
        """
        if self.is_bit:
            return [1 if value else 0]
        if not math.isfinite(value) and (strict or self.type not in ("float32", "float64")):
            raise ValueError(f"cannot encode {value} as {self.type}")
        raw = (value - self.offset) / self.scale
        if self.type in _INT_RANGE:
            lo, hi = _INT_RANGE[self.type]
            raw = round(raw)
            if not lo <= raw <= hi:
                raise ValueError(f"{value} is raw {raw}, outside the {self.type} range {lo}..{hi}")
            raw = int(raw)
        elif self.type == "float32" and math.isfinite(raw) and abs(raw) > 3.4028234663852886e38:
            raise ValueError(f"{value} is outside the float32 range")
        words = list(_WORDS[self.type].unpack(_VALUE[self.type].pack(raw)))
        if self.word_order == "little":
            words.reverse()
        if self.byte_order == "little":
            words = [_swap(w) for w in words]
        return words

    def decode(self, words: list[int] | list[bool]) -> float:
        """Raw words (or one bit) → engineering value; a NaN/inf float is returned as is."""
        if self.is_bit:
            if len(words) != 1:
                raise ValueError(f"a bit is one value, got {len(words)}")
            return 1.0 if words[0] else 0.0
        if len(words) != self.size:
            raise ValueError(f"{self.type} takes {self.size} registers, got {len(words)}")
        regs = [int(w) for w in words]
        if self.word_order == "little":
            regs.reverse()
        if self.byte_order == "little":
            regs = [_swap(w) for w in regs]
        raw = _VALUE[self.type].unpack(_WORDS[self.type].pack(*regs))[0]
        return float(raw) * self.scale + self.offset


def _swap(word: int) -> int:
    return ((word & 0xFF) << 8) | ((word >> 8) & 0xFF)


@dataclass(frozen=True)
class ModbusMap:
    """The register of every signal (optional signals may be absent); validated on creation."""

    registers: Mapping[str, Register]
    source: str = field(default="<map>", compare=False)

    def __post_init__(self) -> None:
        regs = dict(self.registers)
        where = self.source
        for name, reg in regs.items():
            if name not in SIGNALS:
                raise MapError(f"{where}: unknown signal {name!r} (known: {', '.join(SIGNALS)})")
            if not isinstance(reg, Register):
                raise MapError(f"{where}: signal {name!r}: not a Register")
            if name in WRITABLE and reg.table not in WRITABLE_TABLES:
                raise MapError(f"{where}: signal {name!r}: the tuner writes it, so it must be a holding "
                               f"register or a coil, not {reg.table}")
            if name in BOOL_SIGNALS and not reg.is_bit:
                raise MapError(f"{where}: signal {name!r}: a handshake bit must be a coil or discrete_input")
            if name not in BOOL_SIGNALS and reg.is_bit:
                raise MapError(f"{where}: signal {name!r}: a number needs a register table, not {reg.table}")
        missing = [s for s in SIGNALS if s in REQUIRED and s not in regs]
        if missing:
            raise MapError(f"{where}: missing required signal(s): {', '.join(missing)}")
        by_table: dict[str, list[tuple[str, Register]]] = {}
        for name, reg in regs.items():
            by_table.setdefault(reg.table, []).append((name, reg))
        for table, entries in by_table.items():
            entries.sort(key=lambda e: e[1].address)
            for (n1, r1), (n2, r2) in zip(entries, entries[1:]):
                if r2.address < r1.end:
                    raise MapError(f"{where}: signal {n2!r}: {table} address {r2.address} overlaps "
                                   f"signal {n1!r} ({table} {r1.address}..{r1.end - 1})")
        object.__setattr__(self, "registers", MappingProxyType(regs))

    def __contains__(self, signal: object) -> bool:
        return signal in self.registers

    def __getitem__(self, signal: str) -> Register:
        try:
            return self.registers[signal]
        except KeyError:
            raise KeyError(f"signal {signal!r} is not in the map {self.source}") from None

    def get(self, signal: str) -> Register | None:
        return self.registers.get(signal)

    def encode(self, signal: str, value: float) -> list[int]:
        """Engineering value of ``signal`` → the raw registers (or ``[bit]``) to write."""
        return self[signal].encode(value)

    def decode(self, signal: str, registers: list[int] | list[bool]) -> float:
        """Raw registers (or ``[bit]``) of ``signal`` → engineering value."""
        return self[signal].decode(registers)

    def as_dict(self) -> dict[str, Any]:
        """The YAML/JSON form (inverse of :func:`map_from_dict`)."""
        return {"signals": {n: {"table": r.table, "address": r.address, "type": r.type,
                                "word_order": r.word_order, "byte_order": r.byte_order,
                                "scale": r.scale, "offset": r.offset}
                            for n, r in self.registers.items()}}


_ENTRY_KEYS = frozenset({"table", "address", "type", "word_order", "byte_order", "scale", "offset"})
_DEFAULT_KEYS = frozenset({"word_order", "byte_order"})


def map_from_dict(data: Any, source: str = "<map>") -> ModbusMap:
    """A map from its YAML/JSON form::

        word_order: big        # optional defaults for every signal
        byte_order: big
        signals:
          pv: {table: input, address: 0, type: float32}
          ...

    ``type`` defaults to ``float32`` in register tables and ``bool`` in bit tables;
    ``scale`` 1, ``offset`` 0. Raises :class:`MapError` naming ``source``, the signal and the problem.
    """
    if not isinstance(data, dict):
        raise MapError(f"{source}: a map is a mapping with a 'signals' key, got {type(data).__name__}")
    unknown = set(data) - _DEFAULT_KEYS - {"signals"}
    if unknown:
        raise MapError(f"{source}: unknown top-level key(s): {', '.join(sorted(map(str, unknown)))} "
                       "(expected signals, word_order, byte_order)")
    signals = data.get("signals")
    if not isinstance(signals, dict) or not signals:
        raise MapError(f"{source}: 'signals' must be a non-empty mapping of signal name → register")
    defaults = {k: data[k] for k in _DEFAULT_KEYS if k in data}
    regs: dict[str, Register] = {}
    for name, entry in signals.items():
        if name not in SIGNALS:
            raise MapError(f"{source}: unknown signal {name!r} (known: {', '.join(SIGNALS)})")
        if not isinstance(entry, dict):
            raise MapError(f"{source}: signal {name!r}: expected a mapping with table and address")
        bad = set(entry) - _ENTRY_KEYS
        if bad:
            raise MapError(f"{source}: signal {name!r}: unknown key(s) {', '.join(sorted(map(str, bad)))} "
                           f"(allowed: {', '.join(sorted(_ENTRY_KEYS))})")
        for key in ("table", "address"):
            if key not in entry:
                raise MapError(f"{source}: signal {name!r}: missing {key!r}")
        kw = {**defaults, **entry}
        if "type" not in kw:
            kw["type"] = "bool" if kw["table"] in BIT_TABLES else "float32"
        if kw["type"] == "bool":
            kw.pop("word_order", None)
            kw.pop("byte_order", None)
        try:
            regs[name] = Register(**kw)
        except (TypeError, ValueError) as exc:
            raise MapError(f"{source}: signal {name!r}: {exc}") from None
    return ModbusMap(regs, source=source)


def load_map(path: str | os.PathLike[str]) -> ModbusMap:
    """Read a YAML map file (format: :func:`map_from_dict`); MapError names the file on any problem."""
    import yaml

    name = os.fspath(path)
    try:
        with open(name, encoding="utf-8") as f:
            data = yaml.safe_load(f)
    except OSError as exc:
        raise MapError(f"{name}: cannot read the map: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise MapError(f"{name}: not valid YAML: {exc}") from None
    return map_from_dict(data, source=name)


def _default() -> ModbusMap:
    f32 = "float32"
    return ModbusMap(
        {
            # Input registers: what only the PLC sets, then copies of SP and mode (the monitor: one request).
            "pv": Register(INPUT, 0, f32),
            "mv": Register(INPUT, 2, f32),
            "sp_in": Register(INPUT, 4, f32),
            "mode_in": Register(INPUT, 6, "uint16"),
            "boot": Register(INPUT, 7, "uint16"),
            # Holding registers: set point, manual MV, gains, ite, mode.
            "sp": Register(HOLDING, 0, f32),
            "hv": Register(HOLDING, 2, f32),
            "k": Register(HOLDING, 4, f32),
            "ti": Register(HOLDING, 6, f32),
            "td": Register(HOLDING, 8, f32),
            "nd": Register(HOLDING, 10, f32),
            "b": Register(HOLDING, 12, f32),
            "c": Register(HOLDING, 14, f32),
            "ite": Register(HOLDING, 16, f32),
            "mode": Register(HOLDING, 18, "uint16"),
            # The hand-back watchdog: heartbeat counter, then timeout, fallback MV and mode (one write).
            "heartbeat": Register(HOLDING, 19, "uint16"),
            "wd_time": Register(HOLDING, 20, f32),
            "wd_mv": Register(HOLDING, 22, f32),
            "wd_mode": Register(HOLDING, 24, "uint16"),
            # The fence of a fleet: the lease epoch of the daemon that writes (docs/fleet.md).
            "epoch": Register(HOLDING, 26, "uint32"),
            # Coils: the handshake bits.
            "tune": Register(COIL, 0, "bool"),
            "tbrk": Register(COIL, 1, "bool"),
            "tbsy": Register(COIL, 2, "bool"),
            "te": Register(COIL, 3, "bool"),
        },
        source="DEFAULT_MAP",
    )


#: The default register map, served by :func:`drivers.modbus_server.serve_modbus`
#: (``autotuner sim --modbus``): float32 big-endian (ABCD) engineering values,
#: no scaling; PV and actual MV in input registers 0 and 2, read-only copies of SP and mode in input
#: registers 4 (float32) and 6 (uint16); SP, manual MV,
#: gains (k, ti, td, nd, b, c), ite in holding registers 0..17 (two registers
#: each); mode in holding register 18 (uint16, 0 = MAN, 1 = AUTO); TUNE, TBRK,
#: TBSY, TE in coils 0..3. ti = 0 means no integral action. The hand-back watchdog in holding registers 19..24,
#: the lease epoch of a fleet's daemon (uint32) in holding registers 26..27.
DEFAULT_MAP: ModbusMap = _default()
