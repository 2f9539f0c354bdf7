"""The loop over CAN: python-can for the bus, cantools and a DBC file for the frames.

:class:`CanLink` implements :class:`drivers.link.Link`. A :class:`can.Notifier`
hands every received frame to the event loop, where it is decoded with the
DBC and kept, signal by signal, with its receive time (``time.monotonic``).
Reads return the latest values; writes encode command frames and send them.

Every CanLink of the process on one interface and channel shares one
python-can bus and receive thread (:mod:`drivers.can_bus`): the watch and
the session of a loop, and the loops of other nodes on the same bus.

The frames and signals are those of the default DBC ``drivers/data/autotuner.dbc``
(see docs/can.md). Another DBC may be used as long as it has the same message
and signal names; the ids, lengths, layouts, byte orders and scalings are its own.

Conventions on the wire:

* ``Ti = 0`` means no integral action (``Gains.ti = math.inf``); a received
  ``Ti`` that is 0 or +inf reads as ``math.inf``, so a DBC with scaled-integer
  signals can carry it too.
* ``Mode`` is 0 = MAN, 1 = AUTO; the handshake bits are 0/1.

Nothing waits unboundedly: every wait is bounded by ``timeout``, and every
python-can or cantools failure becomes a :class:`LinkError`.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Iterable
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, urlsplit

import can
import cantools

from autotuner.engine.control.gains import Gains

from . import can_bus
from .link import BadValue, Fenced, LinkError, LoopState, Mode, Sample, TuneFlags, Watchdog, checked, float32_step

#: Frames the node sends (cyclic status, gains on request) and the link reads.
PROCESS, STATUS, SETPOINT = "AT_Process", "AT_Status", "AT_Setpoint"
GAINS = ("AT_Gains1", "AT_Gains2", "AT_Gains3")
#: Frames the link sends and the node applies.
CMD_MV, CMD_MODE, CMD_SP, CMD_FLAGS = "AT_CmdMV", "AT_CmdMode", "AT_CmdSP", "AT_CmdFlags"
CMD_GAINS = ("AT_CmdGains1", "AT_CmdGains2", "AT_CmdGains3")
CMD_APPLY, REQUEST = "AT_CmdGainsApply", "AT_Request"
#: Optional frames of the hand-back watchdog (a DBC without them: the device has no watchdog).
CMD_WATCHDOG, HEARTBEAT = "AT_CmdWatchdog", "AT_Heartbeat"
#: The signal of a fleet's lease epoch (optional): in every command frame that moves the loop, the watchdog's
#: frames included. A frame carries no sender: the node fences by content, ignoring a frame whose epoch is older
#: than the newest seen. A signal shorter than 32 bits (the frames with no room for more) carries it short
#: (:func:`epoch_to_wire`).
EPOCH = "Epoch"
EPOCH_FRAMES = (CMD_MV, CMD_MODE, CMD_FLAGS, CMD_APPLY)
WATCHDOG_SIGNALS: dict[str, tuple[str, ...]] = {CMD_WATCHDOG: ("WdMV", "WdTime", "WdMode"), HEARTBEAT: ("Counter",)}
#: The node's report of its fence (optional frame): the newest epoch it has seen, the frames it ignored so far.
FENCE = "AT_Fence"
FENCE_SIGNALS = ("Epoch", "Fenced")

#: Every message name a DBC must define, with the signals each must carry.
REQUIRED: dict[str, tuple[str, ...]] = {
    PROCESS: ("PV", "MV"),
    STATUS: ("Mode", "TUNE", "TBRK", "TBSY", "TE", "Counter", "ITE"),
    SETPOINT: ("SP", "HV"),
    GAINS[0]: ("K", "Ti"),
    GAINS[1]: ("Td", "N"),
    GAINS[2]: ("B", "C"),
    CMD_MV: ("HV",),
    CMD_MODE: ("Mode",),
    CMD_SP: ("SP",),
    CMD_FLAGS: ("TBSY", "TE", "ITE"),
    CMD_GAINS[0]: ("K", "Ti"),
    CMD_GAINS[1]: ("Td", "N"),
    CMD_GAINS[2]: ("B", "C"),
    CMD_APPLY: ("Apply",),
    REQUEST: ("All",),
}

# A frame's interface timestamp is taken as its bus time only if it lies within this many seconds
# before the frame reached the link (an interface whose timestamps are not on the wall clock, e.g.
# a hardware counter from 0, is far outside it: the arrival time is used instead).
BUS_TIME_WINDOW = 30.0


def bus_time(timestamp: float, arrival: float, wall_offset: float) -> float:
    """The monotonic time a frame was on the bus, from its interface ``timestamp`` (wall seconds, as
    python-can's virtual, socketcan and pcan interfaces stamp it), ``arrival`` (monotonic, when the frame
    reached the link) and ``wall_offset`` (``time.time() - time.monotonic()`` at arrival); ``arrival`` if the
    timestamp is not on the wall clock.

    Why not the arrival time alone: under load frames wait in the interface's queue, the receive thread and
    the event loop, so a frame sent before a change can reach the link after it — a read that waits for
    frames "received after now" would take that stale frame as fresh.
    """
    mono = timestamp - wall_offset
    if arrival - BUS_TIME_WINDOW <= mono <= arrival + 1.0:
        return min(mono, arrival)
    return arrival


def epoch_to_wire(epoch: int | None, bits: int) -> int:
    """The value of an ``Epoch`` signal of ``bits`` bits for the lease ``epoch`` (None or 0: no fleet, sent as 0).

    A signal of 32 bits carries the epoch itself. A shorter one (AT_CmdFlags has 24 bits free, AT_CmdWatchdog 15)
    carries ``1 + epoch mod (2**bits − 1)``: never 0 for an epoch, so 0 still means none, and the node takes it for
    the epoch nearest the newest it has seen (:func:`epoch_from_wire`).
    """
    if not epoch:
        return 0
    return epoch if bits >= 32 else epoch % ((1 << bits) - 1) + 1


def epoch_from_wire(value: int, bits: int, newest: int) -> int:
    """The lease epoch an ``Epoch`` signal of ``bits`` bits carries (0: none): a short one
    (:func:`epoch_to_wire`) read as the epoch nearest ``newest`` (the newest the node has seen; not 0) with that
    residue — right while the sender's epoch is within (2**bits − 1) / 2 of it (16383 takeovers for 15 bits)."""
    if value == 0 or bits >= 32:
        return value
    modulus = (1 << bits) - 1
    ahead = (value - 1 - newest) % modulus
    return newest + ahead if ahead <= modulus // 2 else newest + ahead - modulus


def default_dbc() -> Path:
    """Path of the DBC shipped for the simulated PLC."""
    return Path(str(resources.files("drivers") / "data" / "autotuner.dbc"))


def load_dbc(dbc: str | Path | None = None) -> cantools.database.can.Database:
    """The DBC at ``dbc`` (default: the shipped one), checked for the frames the link needs.

    Raises ValueError naming what is missing or why the file cannot be read.
    """
    path = Path(dbc) if dbc is not None else default_dbc()
    try:
        db = cantools.database.load_file(str(path), database_format="dbc")
    except (OSError, cantools.database.Error, ValueError) as exc:
        raise ValueError(f"cannot load DBC {path}: {exc}") from exc
    missing = []
    for name, signals in REQUIRED.items():
        try:
            msg = db.get_message_by_name(name)
        except KeyError:
            missing.append(name)
            continue
        have = {s.name for s in msg.signals}
        missing += [f"{name}.{s}" for s in signals if s not in have]
    if missing:
        raise ValueError(f"DBC {path} lacks {', '.join(missing)} (see docs/can.md)")
    return db


def has_watchdog(db: cantools.database.can.Database) -> bool:
    """Whether the DBC has the watchdog's frames with their signals (AT_CmdWatchdog, AT_Heartbeat)."""
    for name, signals in WATCHDOG_SIGNALS.items():
        try:
            have = {s.name for s in db.get_message_by_name(name).signals}
        except KeyError:
            return False
        if not set(signals) <= have:
            return False
    return True


def has_fence(db: cantools.database.can.Database) -> bool:
    """Whether the DBC has the node's fence report (AT_Fence with its signals)."""
    try:
        return set(FENCE_SIGNALS) <= {s.name for s in db.get_message_by_name(FENCE).signals}
    except KeyError:
        return False


def watchdog_limit(db: cantools.database.can.Database) -> float | None:
    """The longest watchdog timeout the DBC's ``WdTime`` carries, device seconds (None: no watchdog frames)."""
    if not has_watchdog(db):
        return None
    signal = db.get_message_by_name(CMD_WATCHDOG).get_signal_by_name("WdTime")
    if signal.maximum is not None:
        return float(signal.maximum)
    raw = 2 ** (signal.length - 1) - 1 if signal.is_signed else 2 ** signal.length - 1
    return raw * signal.scale + signal.offset


def signal_step(db: cantools.database.can.Database, message: str, signal: str, value: float) -> float:
    """The coding step of a DBC signal near the engineering ``value`` (float: its spacing; integer: its scale)."""
    sig = db.get_message_by_name(message).get_signal_by_name(signal)
    scale = abs(float(sig.scale))
    if not sig.is_float:
        return scale
    raw = (value - float(sig.offset)) / float(sig.scale)
    return scale * (float32_step(raw) if sig.length == 32 else math.ulp(raw))


def ti_to_wire(ti: float) -> float:
    """Integral time as sent: 0 for no integral action."""
    return ti if math.isfinite(ti) else 0.0


def ti_from_wire(ti: float) -> float:
    """Integral time as received: 0 (or +inf) means no integral action."""
    if math.isnan(ti) or ti < 0.0:
        raise ValueError(f"Ti is not a valid integral time ({ti})")
    return math.inf if ti == 0.0 or ti == math.inf else ti


def gains_to_wire(g: Gains) -> tuple[dict[str, float], dict[str, float], dict[str, float]]:
    """The three gains frames' signals for ``g``."""
    return ({"K": g.k, "Ti": ti_to_wire(g.ti)}, {"Td": g.td, "N": g.nd}, {"B": g.b, "C": g.c})


def gains_from_wire(values: dict[str, Any]) -> Gains:
    """Gains from the signals K, Ti, Td, N, B, C (ValueError if they are not valid gains)."""
    return Gains(k=float(values["K"]), ti=ti_from_wire(float(values["Ti"])), td=float(values["Td"]),
                 nd=float(values["N"]), b=float(values["B"]), c=float(values["C"]))


def encode(db: cantools.database.can.Database, name: str, values: dict[str, Any]) -> can.Message:
    """A python-can message for DBC message ``name`` (ValueError if a value does not fit)."""
    msg = db.get_message_by_name(name)
    try:
        data = msg.encode(values, scaling=True, padding=False, strict=True)
    except (cantools.database.Error, ValueError, KeyError, OverflowError) as exc:
        raise ValueError(f"cannot encode {name} {values}: {exc}") from exc
    return can.Message(arbitration_id=msg.frame_id, is_extended_id=msg.is_extended_frame,
                       data=data, is_fd=msg.is_fd)


class CanLink:
    """A loop behind a CAN node, per the DBC ``dbc`` (default: the shipped one).

    ``interface`` and ``channel`` are python-can's (``"socketcan"``/``"can0"``,
    ``"pcan"``/``"PCAN_USBBUS1"``, ``"virtual"``/any name, ...); ``bus_kwargs``
    (e.g. ``bitrate``) go to :class:`can.Bus`.

    ``timeout`` (s) bounds every wait: for a first or fresh frame, for a send.
    ``stale_after`` (s): a PV older than this is not returned — the link waits
    for a newer frame (up to ``timeout``) and raises LinkError if none comes.
    ``None`` means three times the observed period of the PV frame (at most
    ``timeout``; ``timeout`` until two frames have been seen).
    """

    def __init__(self, interface: str = "virtual", channel: str = "autotuner", dbc: str | Path | None = None,
                 timeout: float = 1.0, stale_after: float | None = None, **bus_kwargs: Any) -> None:
        if not timeout > 0.0:
            raise ValueError(f"timeout must be > 0, got {timeout}")
        if stale_after is not None and not stale_after > 0.0:
            raise ValueError(f"stale_after must be > 0, got {stale_after}")
        self.interface = interface
        self.channel = channel
        self.db = load_dbc(dbc)
        self._watchdog = has_watchdog(self.db)
        self.timeout = float(timeout)
        self.stale_after = stale_after
        self.bus_kwargs = bus_kwargs
        self._shared: can_bus.SharedBus | None = None  # the bus, shared with the process's other links on it
        self._bus: can.BusABC | None = None  # its python-can bus while the link is open
        # The frames with an Epoch signal (each sent with the link's epoch, 0 if none), and its length, bits.
        self._epoch_bits = {m.name: g.length for m in self.db.messages for g in m.signals if g.name == EPOCH}
        #: The lease epoch the frames carry (a fleet's daemon sets it; None: none, sent as 0).
        self.epoch: int | None = None
        reports = (FENCE,) if has_fence(self.db) else ()
        self._ids = {m.frame_id: m for m in self.db.messages
                     if m.name in (PROCESS, STATUS, SETPOINT, *GAINS, *reports)}
        self.frame_ids = frozenset(self._ids)
        # name -> (decoded signals, monotonic bus time: see bus_time)
        self._latest: dict[str, tuple[dict[str, Any], float]] = {}
        # Replaced (and the old one set) on every frame: waiters wake and look again.
        self._changed = asyncio.Event()
        #: Why the last undecodable frame could not be decoded.
        self.last_bad_frame = ""
        self._error: Exception | None = None
        self._pv_interval: float | None = None
        self._counter: int | None = None
        #: Health counters: frames received / undecodable, error frames, lost AT_Status frames (counter gaps),
        #: command frames sent.
        self.stats = {"frames": 0, "bad_frames": 0, "error_frames": 0, "lost_status": 0, "sent": 0}

    def __repr__(self) -> str:
        return f"CanLink(can://{self.interface}/{self.channel})"

    @classmethod
    def from_url(cls, url: str, dbc: str | Path | None = None, **kwargs: Any) -> "CanLink":
        """``can://INTERFACE/CHANNEL[?bitrate=N&timeout=S&stale_after=S&port=N&hop_limit=N]``.

        CHANNEL is everything after the first slash (``can://slcan//dev/ttyACM0``
        gives channel ``/dev/ttyACM0``). ``port`` and ``hop_limit`` are python-can's
        ``udp_multicast`` options (``hop_limit=0``: the frames never leave the host).
        Raises ValueError for anything else.
        """
        parts = urlsplit(url)
        if parts.scheme != "can":
            raise ValueError(f"not a CAN link URL (want can://INTERFACE/CHANNEL): {url!r}")
        interface = parts.netloc
        channel = parts.path[1:] if parts.path.startswith("/") else ""
        if not interface or not channel or parts.fragment:
            raise ValueError(f"a CAN link URL is can://INTERFACE/CHANNEL, e.g. can://socketcan/can0 or "
                             f"can://virtual/autotuner; got {url!r}")
        options: dict[str, Any] = {}
        for key, value in parse_qsl(parts.query, keep_blank_values=True, strict_parsing=False):
            try:
                if key in ("bitrate", "port", "hop_limit"):
                    options[key] = int(value)
                elif key in ("timeout", "stale_after"):
                    options[key] = float(value)
                else:
                    raise ValueError(f"unknown option {key!r} (bitrate, timeout, stale_after, port, hop_limit)")
            except ValueError as exc:
                raise ValueError(f"bad CAN link URL {url!r}: {exc}") from exc
        options.update(kwargs)
        return cls(interface, channel, dbc=dbc, **options)

    # ----------------------------------------------------------------- receive

    def received(self, msg: can.Message) -> None:
        """A frame from the bus (in the event loop): decoded and kept, with its bus time."""
        arrival = time.monotonic()
        now = bus_time(float(msg.timestamp), arrival, time.time() - arrival)
        if msg.is_error_frame:
            self.stats["error_frames"] += 1
            return
        if msg.is_remote_frame:
            return
        spec = self._ids.get(msg.arbitration_id)
        if spec is None or bool(msg.is_extended_id) != bool(spec.is_extended_frame):
            return
        try:
            values = spec.decode(bytes(msg.data), decode_choices=False, scaling=True)
        except (cantools.database.Error, ValueError, KeyError, IndexError) as exc:
            self.stats["bad_frames"] += 1
            self.last_bad_frame = f"{spec.name}: {exc}"
            return
        self.stats["frames"] += 1
        if spec.name == PROCESS:
            prev = self._latest.get(PROCESS)
            if prev is not None:
                dt = now - prev[1]
                self._pv_interval = dt if self._pv_interval is None else 0.8 * self._pv_interval + 0.2 * dt
        elif spec.name == STATUS:
            counter = int(values["Counter"])
            if self._counter is not None:
                modulus = 1 << spec.get_signal_by_name("Counter").length
                self.stats["lost_status"] += (counter - self._counter - 1) % modulus
            self._counter = counter
        self._latest[spec.name] = (values, now)
        self._wake()

    def _wake(self) -> None:
        changed, self._changed = self._changed, asyncio.Event()
        changed.set()

    def bus_error(self, exc: Exception) -> None:
        """The bus's receive thread failed: every call from now on is a LinkError."""
        self._error = exc
        self._wake()

    def _check(self) -> None:
        if self._bus is None:
            raise LinkError(f"{self!r} is not open")
        notifier = None if self._shared is None else self._shared.notifier
        if self._error is None and notifier is not None and notifier.exception is not None:
            self._error = notifier.exception  # the receive thread failed; its report may be on the way
        if self._error is not None:
            raise LinkError(f"CAN bus error on {self.interface}/{self.channel}: {self._error}")

    async def _fresh(self, names: Iterable[str], after: float) -> dict[str, Any]:
        """The signals of ``names`` once each has been received after ``after`` (monotonic), within ``timeout``."""
        names = tuple(names)
        deadline = time.monotonic() + self.timeout

        def ready() -> bool:
            return self._bus is None or self._error is not None or all(n in self._latest and self._latest[n][1] > after for n in names)

        self._check()
        while not ready():
            changed = self._changed
            try:
                await asyncio.wait_for(changed.wait(), max(0.0, deadline - time.monotonic()))
            except TimeoutError:
                self._check()  # a bus error explains the silence better than staleness
                late = [n for n in names if n not in self._latest or self._latest[n][1] <= after]
                seen = [f"{n} {time.monotonic() - self._latest[n][1]:.3g} s ago" for n in late if n in self._latest]
                raise LinkError(f"no fresh {', '.join(late)} from the CAN node within {self.timeout:g} s"
                                + (f" (last: {'; '.join(seen)})" if seen else " (never received)")) from None
        self._check()
        out: dict[str, Any] = {}
        for n in names:
            out.update(self._latest[n][0])
        return out

    # ------------------------------------------------------------------- send

    @property
    def carries_epoch(self) -> bool:
        """Whether every frame the link sends that moves the loop carries an Epoch: AT_CmdMV, AT_CmdMode,
        AT_CmdFlags, AT_CmdGainsApply, and AT_CmdWatchdog and AT_Heartbeat where the DBC has them."""
        needed = EPOCH_FRAMES + ((CMD_WATCHDOG, HEARTBEAT) if self._watchdog else ())
        return all(name in self._epoch_bits for name in needed)

    @property
    def reported_epoch(self) -> tuple[int, int] | None:
        """The node's last report of its fence (AT_Fence): (the newest lease epoch it has seen, the frames it ignored
        so far); None: none received (or the DBC has no AT_Fence)."""
        report = self._latest.get(FENCE)
        return None if report is None else (int(report[0][EPOCH]), int(report[0]["Fenced"]))

    def _fence(self) -> None:
        """Fenced if the node reported a newer lease epoch than the link's: it ignores the link's frames."""
        report = self.reported_epoch
        if self.epoch is None or report is None or report[0] <= self.epoch:
            return
        raise Fenced(f"CAN node on {self.interface}/{self.channel} has seen lease epoch {report[0]}, newer than this "
                     f"daemon's epoch {self.epoch} (another daemon took the loop over), and ignores its frames "
                     f"({report[1]} ignored so far): nothing more is sent to it")

    async def _send(self, *frames: tuple[str, dict[str, Any]]) -> None:
        self._check()
        if any(name in self._epoch_bits for name, _ in frames):
            self._fence()
        try:
            messages = [encode(self.db, name, {**values, EPOCH: epoch_to_wire(self.epoch, self._epoch_bits[name])}
                               if name in self._epoch_bits else values)
                        for name, values in frames]
        except ValueError as exc:
            raise LinkError(str(exc)) from exc
        bus = self._bus
        assert bus is not None

        # Fast path: send without blocking, from the event loop (a thread hop per write
        # costs latency, i.e. phase, in a fast experiment). If the interface cannot
        # take a frame at once (transmit buffer full, or any error), the rest is sent
        # from a worker thread with the full timeout, and its error is the one reported.
        pending = list(messages)
        while pending:
            try:
                bus.send(pending[0], timeout=0.0)
            except (can.CanError, OSError, ValueError):
                break
            pending.pop(0)
            self.stats["sent"] += 1
        if not pending:
            return

        def send_rest() -> None:
            for m in pending:
                bus.send(m, timeout=self.timeout)
                self.stats["sent"] += 1

        try:
            await asyncio.wait_for(asyncio.to_thread(send_rest), self.timeout + 0.5)
        except TimeoutError:
            raise LinkError(f"CAN send did not complete within {self.timeout:g} s") from None
        except (can.CanError, OSError, ValueError) as exc:
            raise LinkError(f"CAN send failed on {self.interface}/{self.channel}: {exc}") from exc

    # ------------------------------------------------------------------- Link

    async def open(self) -> None:
        """Take the interface's shared bus (opened if no link of the process has it) and start receiving (it does
        not wait for a frame: reads do)."""
        if self._shared is not None:
            return
        self._changed = asyncio.Event()
        self._error = None
        self._latest.clear()
        self._shared = can_bus.hold(self.interface, self.channel, self.bus_kwargs, self)
        self._bus = self._shared.bus

    async def close(self) -> None:
        """Stop receiving and give the bus back (the last link's close releases the interface); never raises."""
        shared, self._shared, self._bus = self._shared, None, None
        self._wake()  # waiters see the link closed
        if shared is not None:
            can_bus.let_go(shared, self)

    async def __aenter__(self) -> "CanLink":
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def _stale_limit(self) -> float:
        if self.stale_after is not None:
            return self.stale_after
        if self._pv_interval is None:
            return self.timeout
        return min(self.timeout, 3.0 * self._pv_interval)

    def age(self, message: str = PROCESS) -> float:
        """Seconds since the DBC message ``message`` was last received (inf if never)."""
        last = self._latest.get(message)
        return math.inf if last is None else time.monotonic() - last[1]

    def health(self) -> dict[str, Any]:
        """Bus state, frame counters and the age of the PV, seconds."""
        return {"transport": "can", "device": f"{self.interface}/{self.channel}", "connected": self._bus is not None,
                "pv_age": self.pv_age, **self.stats}

    @property
    def pv_age(self) -> float:
        """Seconds since the last PV frame (inf if none yet)."""
        return self.age(PROCESS)

    async def read_pv(self) -> float:
        """The latest PV; waits up to ``timeout`` for one if it is older than the stale limit."""
        self._check()
        last = self._latest.get(PROCESS)
        now = time.monotonic()
        if last is None or now - last[1] > self._stale_limit():
            after = -math.inf if last is None else last[1]
            try:
                await self._fresh((PROCESS,), after)
            except LinkError as exc:
                raise BadValue(f"stale PV: {exc}") from None
            last = self._latest[PROCESS]
        return checked("PV", float(last[0]["PV"]))

    async def write_mv(self, mv: float) -> None:
        """Send the manual MV (AT_CmdMV)."""
        await self._send((CMD_MV, {"HV": checked("MV", float(mv))}))

    async def write_mode(self, mode: Mode) -> None:
        """Send the mode (AT_CmdMode)."""
        await self._send((CMD_MODE, {"Mode": int(Mode(mode))}))

    async def write_gains(self, gains: Gains) -> None:
        """Send the three staged gains frames, then AT_CmdGainsApply (the node applies them together)."""
        g1, g2, g3 = gains_to_wire(gains)
        await self._send((CMD_GAINS[0], g1), (CMD_GAINS[1], g2), (CMD_GAINS[2], g3), (CMD_APPLY, {"Apply": 1}))

    async def request(self) -> None:
        """Ask the node for all its frames now (AT_Request)."""
        await self._send((REQUEST, {"All": 1}))

    async def read_state(self) -> LoopState:
        """Mode, MV, SP and gains from frames received after this call (requested with AT_Request)."""
        t0 = time.monotonic()
        await self.request()
        v = await self._fresh((PROCESS, STATUS, SETPOINT, *GAINS), t0)
        try:
            mode = Mode(int(v["Mode"]))
            gains = gains_from_wire(v)
        except ValueError as exc:
            raise LinkError(f"the CAN node sent invalid state: {exc}") from exc
        return LoopState(mode=mode, mv=checked("MV", float(v["MV"])), sp=checked("SP", float(v["SP"])),
                         gains=gains)

    async def read_sample(self) -> Sample:
        """PV and MV (AT_Process), mode (AT_Status) and SP (AT_Setpoint) from the latest cyclic frames; for those
        older than the stale limit it waits up to ``timeout`` for fresh ones (none: BadValue, as a stale PV)."""
        self._check()
        now = time.monotonic()
        limit = self._stale_limit()
        stale = [n for n in (PROCESS, STATUS, SETPOINT) if n not in self._latest or now - self._latest[n][1] > limit]
        if stale:
            try:
                await self._fresh(stale, now - limit)
            except LinkError as exc:
                raise BadValue(f"stale {'PV' if PROCESS in stale else 'sample'}: {exc}") from None
        v = {**self._latest[PROCESS][0], **self._latest[STATUS][0], **self._latest[SETPOINT][0]}
        try:
            mode = Mode(int(v["Mode"]))
        except ValueError as exc:
            raise LinkError(f"the CAN node sent invalid state: {exc}") from exc
        return Sample(pv=checked("PV", float(v["PV"])), mv=checked("MV", float(v["MV"])),
                      sp=checked("SP", float(v["SP"])), mode=mode)

    async def read_flags(self) -> TuneFlags:
        """The handshake bits from the latest AT_Status frame (a fresh one if it is stale)."""
        self._check()
        last = self._latest.get(STATUS)
        if last is None or time.monotonic() - last[1] > self._stale_limit():
            v = await self._fresh((STATUS,), -math.inf if last is None else last[1])
        else:
            v = last[0]
        return TuneFlags(tune=bool(v["TUNE"]), tbrk=bool(v["TBRK"]), tbsy=bool(v["TBSY"]), te=bool(v["TE"]),
                         ite=checked("ite", float(v["ITE"])))

    async def write_flags(self, flags: TuneFlags) -> None:
        """Send TBSY, TE and ite (AT_CmdFlags); TUNE and TBRK are the node's own."""
        await self._send((CMD_FLAGS, {"TBSY": int(flags.tbsy), "TE": int(flags.te),
                                      "ITE": checked("ite", float(flags.ite))}))

    def mv_resolution(self, mv: float) -> float:
        """The coding step of AT_CmdMV.HV (sent) plus that of AT_Process.MV (received) near ``mv``."""
        return signal_step(self.db, CMD_MV, "HV", mv) + signal_step(self.db, PROCESS, "MV", mv)

    async def write_watchdog(self, watchdog: Watchdog) -> None:
        """AT_CmdWatchdog (nothing if the DBC has no watchdog frames)."""
        if self._watchdog:
            await self._send((CMD_WATCHDOG, {"WdMV": checked("watchdog MV", float(watchdog.mv)),
                                             "WdTime": float(watchdog.timeout), "WdMode": int(Mode(watchdog.mode))}))

    async def write_heartbeat(self, counter: int) -> None:
        """AT_Heartbeat (nothing if the DBC has no watchdog frames)."""
        if self._watchdog:
            await self._send((HEARTBEAT, {"Counter": counter % 65536}))
