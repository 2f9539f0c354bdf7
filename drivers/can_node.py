"""A CAN node in front of a :class:`drivers.simplc.SimulatedPlc` (the simulated plant server for CAN).

The node sends, every ``period`` wall seconds, AT_Process (PV, MV), AT_Status
(mode, handshake bits, rolling counter, ite) and AT_Setpoint (SP, manual MV);
every ``gains_every`` periods, and at once on AT_Request, also the three gains
frames. It applies the command frames it receives (manual MV, mode, SP,
handshake outputs, gains) to the PLC. Frames and signals are those of the DBC
(default ``drivers/data/autotuner.dbc``; see docs/can.md).

The node does not tick the PLC: run :func:`drivers.simplc.run` next to it
(``period`` is in wall seconds, so for a plant run ``speed`` times faster than
real time pass ``period = plc.ts / speed``).

A fleet's fence (docs/can.md): a command frame whose ``Epoch`` is older than
the newest the node has seen is ignored and reported at once (AT_Fence).

Fault injection: ``node.silent = True`` stops every transmission (the node
"goes silent"), while received commands are still applied, as with a node
whose transmitter has failed; ``node.deaf = True`` ignores received commands.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from pathlib import Path
from typing import Any

import can

from autotuner.engine.checks import finite
from autotuner.engine.control.gains import Gains

from .can_bus import RX_POLL, open_bus
from .can_link import (CMD_APPLY, CMD_FLAGS, CMD_GAINS, CMD_MODE, CMD_MV, CMD_SP, CMD_WATCHDOG, EPOCH, FENCE,
                       GAINS, HEARTBEAT, PROCESS, REQUEST, SETPOINT, STATUS, encode, epoch_from_wire, gains_from_wire,
                       gains_to_wire, has_fence, has_watchdog, load_dbc)
from .link import LinkError, Mode, Watchdog
from .simplc import SimulatedPlc

log = logging.getLogger(__name__)


class CanPlcNode:
    """Serves ``plc`` on ``bus`` per ``db``; build it with :func:`serve_can`."""

    def __init__(self, plc: SimulatedPlc, bus: can.BusABC, db: Any, period: float, gains_every: int = 10) -> None:
        if not period > 0.0:
            raise ValueError(f"period must be > 0, got {period}")
        self.plc = plc
        self.bus = bus
        self.db = db
        self.period = float(period)
        self.gains_every = max(1, int(gains_every))
        #: Fault injection: no frames are sent while True.
        self.silent = False
        #: Fault injection: received commands are ignored while True.
        self.deaf = False
        #: Frames sent, commands applied, rejected (undecodable or invalid values), ignored (while deaf), fenced
        #: (their Epoch older than the newest seen).
        self.stats = {"sent": 0, "applied": 0, "rejected": 0, "ignored": 0, "send_errors": 0, "fenced": 0}
        self._fenced_epochs: set[int] = set()  # the older epochs whose frames were ignored (each logged once)
        self._counter = 0
        self._staged: dict[str, dict[str, Any]] = {}
        names = (CMD_MV, CMD_MODE, CMD_SP, CMD_FLAGS, *CMD_GAINS, CMD_APPLY, REQUEST)
        if has_watchdog(self.db):
            names += (CMD_WATCHDOG, HEARTBEAT)
        self._cmds = {self.db.get_message_by_name(n).frame_id: self.db.get_message_by_name(n) for n in names}
        # The length (bits) of each command frame's Epoch signal; whether the DBC has the fence's report frame.
        self._epoch_bits = {m.name: g.length for m in self._cmds.values() for g in m.signals if g.name == EPOCH}
        self._reports = has_fence(self.db)
        self._task: asyncio.Task[None] | None = None
        self._notifier: can.Notifier | None = None

    def start(self) -> None:
        """Start receiving and the cyclic transmission (call from the event loop)."""
        loop = asyncio.get_running_loop()
        self._notifier = can.Notifier(self.bus, [self._on_message], timeout=RX_POLL, loop=loop)
        self._task = loop.create_task(self._cyclic(), name="can-node-cyclic")

    async def close(self) -> None:
        """Stop transmitting and receiving, release the bus; never raises."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            try:
                await task
            except (asyncio.CancelledError, Exception):  # noqa: BLE001
                pass
        notifier, self._notifier = self._notifier, None
        try:
            if notifier is not None:
                notifier.stop(timeout=RX_POLL + 1.0)
        except Exception:  # noqa: BLE001
            pass
        try:
            self.bus.shutdown()
        except Exception:  # noqa: BLE001
            pass

    async def __aenter__(self) -> "CanPlcNode":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ---------------------------------------------------------------- transmit

    def _send(self, name: str, values: dict[str, Any]) -> None:
        if self.silent:
            return
        try:
            self.bus.send(encode(self.db, name, values), timeout=self.period)
            self.stats["sent"] += 1
        except (can.CanError, OSError, ValueError) as exc:
            self.stats["send_errors"] += 1
            log.warning("CAN node: cannot send %s: %s", name, exc)

    def publish(self, gains: bool = False) -> None:
        """Send the cyclic frames now (and the gains frames if ``gains``)."""
        plc = self.plc
        f = plc.flags
        self._send(PROCESS, {"PV": plc.read_pv(), "MV": plc.mv})
        self._send(STATUS, {"Mode": int(plc.mode), "TUNE": int(f.tune), "TBRK": int(f.tbrk), "TBSY": int(f.tbsy),
                            "TE": int(f.te), "Counter": self._counter, "ITE": f.ite})
        self._counter = (self._counter + 1) % 16
        self._send(SETPOINT, {"SP": plc.sp, "HV": plc.hv})
        if gains:
            for name, values in zip(GAINS, gains_to_wire(plc.gains)):
                self._send(name, values)
            self.report_fence()

    def report_fence(self) -> None:
        """Send AT_Fence (where the DBC has it): the newest lease epoch seen, the frames ignored so far."""
        if self._reports:
            self._send(FENCE, {"Epoch": self.plc.epoch, "Fenced": self.plc.fenced % (1 << 32)})

    async def _cyclic(self) -> None:
        start = time.monotonic()
        k = 0
        while True:
            self.publish(gains=k % self.gains_every == 0)
            k += 1
            delay = start + k * self.period - time.monotonic()
            if delay < -self.period:  # fell behind (loop blocked): restart the schedule, skip the backlog
                start, k = time.monotonic(), 0
                delay = 0.0
            await asyncio.sleep(max(0.0, delay))

    # ----------------------------------------------------------------- receive

    def _on_message(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame:
            return
        spec = self._cmds.get(msg.arbitration_id)
        if spec is None or bool(msg.is_extended_id) != bool(spec.is_extended_frame):
            return
        if self.deaf:
            self.stats["ignored"] += 1
            return
        try:
            values = spec.decode(bytes(msg.data), decode_choices=False, scaling=True)
            if self._superseded(spec.name, values):
                return
            self._apply(spec.name, values)
        except Exception as exc:  # noqa: BLE001 - a bad command frame never stops the node
            self.stats["rejected"] += 1
            log.warning("CAN node: rejected %s: %s", spec.name, exc)
            return
        self.stats["applied"] += 1

    def _superseded(self, name: str, v: dict[str, Any]) -> bool:
        """The fence of a fleet (docs/fleet.md): a frame whose Epoch (0: none, not fenced) is older than the newest
        the node has seen is ignored (an apply drops the staged gains too), counted in ``plc.fenced``, logged once
        per epoch and reported at once (AT_Fence); a newer one becomes the newest. A short Epoch
        (:func:`~drivers.can_link.epoch_to_wire`) is read as the epoch nearest the newest; before any full one has
        been seen (the newest 0) it fences nothing and sets nothing."""
        plc = self.plc
        bits = self._epoch_bits.get(name, 32)
        if bits < 32 and plc.epoch == 0:
            return False
        epoch = epoch_from_wire(int(v.get(EPOCH, 0)), bits, plc.epoch)
        if epoch >= plc.epoch or epoch == 0:
            plc.epoch = max(plc.epoch, epoch)
            return False
        plc.fenced += 1
        self.stats["fenced"] += 1
        self.report_fence()
        if name == CMD_APPLY:
            self._staged = {}
        if epoch not in self._fenced_epochs:
            self._fenced_epochs.add(epoch)
            log.warning("CAN node: ignored %s of lease epoch %d, older than the newest seen, %d (another tuner took "
                        "the loop over); %d frame(s) ignored so far", name, epoch, plc.epoch, plc.fenced)
        return True

    def _apply(self, name: str, v: dict[str, Any]) -> None:
        plc = self.plc
        if name == CMD_MV:
            plc.hv = finite("manual MV", v["HV"])
        elif name == CMD_MODE:
            plc.mode = Mode(int(v["Mode"]))
        elif name == CMD_SP:
            plc.sp = finite("SP", v["SP"])
        elif name == CMD_FLAGS:
            plc.flags = dataclasses.replace(plc.flags, tbsy=bool(v["TBSY"]), te=bool(v["TE"]),
                                            ite=finite("ite", v["ITE"]))
        elif name in CMD_GAINS:
            self._staged[name] = v
        elif name == CMD_APPLY:
            if not v["Apply"]:
                return
            staged, self._staged = self._staged, {}
            missing = [n for n in CMD_GAINS if n not in staged]
            if missing:
                raise ValueError(f"gains apply without {', '.join(missing)}")
            merged: dict[str, Any] = {}
            for n in CMD_GAINS:
                merged.update(staged[n])
            gains: Gains = gains_from_wire(merged)
            plc.set_gains(gains)
            self.publish(gains=True)  # echo the gains now applied
        elif name == REQUEST:
            if v["All"]:
                self.publish(gains=True)
        elif name == CMD_WATCHDOG:
            plc.watchdog = Watchdog(timeout=finite("watchdog time", v["WdTime"]),
                                    mv=finite("watchdog MV", v["WdMV"]), mode=Mode(int(v["WdMode"])))
        elif name == HEARTBEAT:
            plc.heartbeat = int(v["Counter"])


async def serve_can(plc: SimulatedPlc, interface: str = "virtual", channel: str = "autotuner",
                    dbc: str | Path | None = None, period: float | None = None, gains_every: int = 10,
                    **bus_kwargs: Any) -> CanPlcNode:
    """Start a node serving ``plc`` on a python-can bus; it sends its cyclic frames every ``period`` wall
    seconds (default ``plc.ts``). Close it with ``await node.close()``.

    Raises LinkError if the bus cannot be opened, ValueError for a bad DBC or period.
    """
    db = load_dbc(dbc)
    period = plc.ts if period is None else period
    if not period > 0.0:
        raise ValueError(f"period must be > 0, got {period}")
    bus = open_bus(interface, channel, **bus_kwargs)
    try:
        node = CanPlcNode(plc, bus, db, period, gains_every)
        node.start()
    except BaseException:
        bus.shutdown()
        raise
    return node


__all__ = ["CanPlcNode", "serve_can", "LinkError"]
