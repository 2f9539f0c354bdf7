"""The OPC UA address space of the loops: one object per loop under ``Objects/Loops``, its variables and events.

Every node has a string NodeId in the namespace :data:`NAMESPACE` (the
loop's id, then ``.`` and the child's name: ``TIC-101.PV``,
``TIC-101.PIDParameters.P``), so tag bindings survive restarts and
reordering; docs/opcua.md has the table. Variables are read-only (the
loops change only through the methods, :mod:`api.opcua.server`). Their
values come from the loop's status (:meth:`autotuner.service.daemon.Loop.as_json`):
:meth:`LoopNodes.update` writes the ones that changed, so a subscription
sees a data change only when there is one. A value the daemon does not know
(null in the REST status) is NaN (or "") with a Bad status code:
``BadWaitingForInitialData``, or ``BadNoCommunication`` while the monitor's
link is down.

The loop's health summary (docs/health.md, "Online") is the object ``LOOP.Health`` with ``State``,
``Severity``, ``Rank``, ``Flags`` (comma-separated), ``Recommendation``, ``Reason`` and ``Time`` (unix s).

OPC 40083 (Plastics and Rubber Machinery, ``ClosedLoopControlType``) names
are offered beside ours: ``AutoTuningActive`` (= TBSY) and ``PIDParameters``
with ``P`` = k (proportional gain), ``I`` = ti (integral time, s; +Inf
without integral action) and ``D`` = td (derivative time, s) of the
controller's current gains; the methods ``AutoTuningOn``/``AutoTuningOff``
are added by the server.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any

from asyncua import Node, Server, ua

from autotuner.engine.outcome import Code

# The namespace of every node of ours (fixed: SCADA bindings use it with the string ids).
NAMESPACE = "urn:relaytune:autotuner"
FOLDER = "Loops"
# UNECE codes of OPC UA's EUInformation (OPC 10000-8 §5.6.3): UnitId = the code's characters as a base-256 number.
UNECE = "http://www.opcfoundation.org/UA/units/un/cefact"
# Unit symbols (as a config's ``units`` writes them) with their UN/CEFACT Recommendation 20 code and name. A symbol
# not here is published with UnitId -1 ("no code", OPC 10000-8) and itself as its display name.
UNECE_CODES: dict[str, tuple[str, str]] = {
    "s": ("SEC", "second"), "min": ("MIN", "minute"), "h": ("HUR", "hour"), "rad/s": ("2A", "radian per second"),
    "°": ("DD", "degree (angle)"), "1": ("C62", "one (fraction)"), "%": ("P1", "percent"),
    "°C": ("CEL", "degree Celsius"), "K": ("KEL", "kelvin"), "°F": ("FAH", "degree Fahrenheit"),
    "Pa": ("PAL", "pascal"), "kPa": ("KPA", "kilopascal"), "MPa": ("MPA", "megapascal"), "bar": ("BAR", "bar"),
    "mbar": ("MBR", "millibar"), "psi": ("PS", "pound-force per square inch"),
    "m³/h": ("MQH", "cubic metre per hour"), "m3/h": ("MQH", "cubic metre per hour"),
    "m³/s": ("MQS", "cubic metre per second"), "m3/s": ("MQS", "cubic metre per second"),
    "l/min": ("L2", "litre per minute"), "L/min": ("L2", "litre per minute"), "l": ("LTR", "litre"),
    "L": ("LTR", "litre"), "kg/h": ("E93", "kilogram per hour"), "t/h": ("E18", "tonne per hour"),
    "kg": ("KGM", "kilogram"), "g": ("GRM", "gram"), "m": ("MTR", "metre"), "cm": ("CMT", "centimetre"),
    "mm": ("MMT", "millimetre"), "m/s": ("MTS", "metre per second"), "Hz": ("HTZ", "hertz"), "V": ("VLT", "volt"),
    "mV": ("2Z", "millivolt"), "A": ("AMP", "ampere"), "mA": ("4K", "milliampere"), "W": ("WTT", "watt"),
    "kW": ("KWT", "kilowatt"),
}
# The variable type (OPC 10000-8 §5.3.2) of a variable with (EngineeringUnits, EURange): the Analog type having
# those as mandatory properties; neither: BaseDataVariableType.
ANALOG_TYPES = {(True, False): ua.ObjectIds.AnalogUnitType, (False, True): ua.ObjectIds.AnalogItemType,
                (True, True): ua.ObjectIds.AnalogUnitRangeType}
# The ``ite`` of a session whose loop could not be put back (docs/handback.md).
NOT_RESTORED = float(Code.LOOP_NOT_RESTORED)
# Severity of the events (1-1000).
TE_SEVERITY, NOT_RESTORED_SEVERITY = 600, 1000


def unece_id(code: str) -> int:
    """The UnitId of a UN/CEFACT code: its characters as a base-256 number (``"CEL"`` → 4408652)."""
    unit_id = 0
    for ch in code:
        unit_id = (unit_id << 8) | ord(ch)
    return unit_id


def unit(symbol: str) -> ua.EUInformation:
    """The EUInformation of the unit ``symbol`` (``°C``, ``%/°C``): its UN/CEFACT code where
    :data:`UNECE_CODES` has one, else UnitId -1 with the symbol as display name and description."""
    code, description = UNECE_CODES.get(symbol, (None, symbol))
    return ua.EUInformation(NamespaceUri=UNECE, UnitId=-1 if code is None else unece_id(code),
                            DisplayName=ua.LocalizedText(symbol), Description=ua.LocalizedText(description))


def unit_symbol(template: str, units: dict[str, Any]) -> str | None:
    """``template`` (a :class:`Var`'s unit: ``s``, or ``{pv}``, ``{mv}/{pv}`` …) with the loop's ``units``
    (its REST status' ``units``); None when it names a unit the config leaves empty (no unit is published)."""
    names = {key: units.get(key) or "" for key in ("pv", "mv")}
    if any(f"{{{key}}}" in template and not text for key, text in names.items()):
        return None
    if "/" in template:  # a compound unit in brackets, as the operator page writes it (api/static/units.js):
        # %/(m³/h), not %/m³/h (which reads (%/m³)/h)
        names = {key: f"({text})" if re.search(r"[/·\s]", text) else text for key, text in names.items()}
    return template.format(**names)


@dataclass(frozen=True)
class Var:
    """One variable of a loop: its browse name (and NodeId suffix), how to get it from the status, its type,
    its unit (a symbol, or a template of the loop's units: :func:`unit_symbol`; None: none), what it means,
    and the key of the loop's ``units`` with its EURange (``pv_range``, ``mv_range``; None: none)."""

    name: str
    get: Callable[[dict[str, Any]], Any]
    kind: ua.VariantType
    unit: str | None
    description: str
    eu_range: str | None = None


def _gain(group: str, key: str) -> Callable[[dict[str, Any]], Any]:
    """A getter of ``status[group][key]``; a missing ``pti`` (no integral action) is +Inf, else None."""

    def get(status: dict[str, Any]) -> Any:
        gains = status.get(group)
        if gains is None:
            return None
        value = gains.get(key)
        return math.inf if value is None and key == "pti" else value

    return get


def _point(key: str) -> Callable[[dict[str, Any]], Any]:
    return lambda status: None if status.get("point") is None else status["point"].get(key)


def _key(key: str) -> Callable[[dict[str, Any]], Any]:
    return lambda status: status.get(key)


D, B, S = ua.VariantType.Double, ua.VariantType.Boolean, ua.VariantType.String
# The units of the loop's config (``units.pv``, ``units.mv``) and of its gains (the controller's k; the process's
# |F| and static gain).
PV_UNIT, MV_UNIT, K_UNIT, F_UNIT = "{pv}", "{mv}", "{mv}/{pv}", "{pv}/{mv}"
VARIABLES: tuple[Var, ...] = (
    Var("PV", _key("pv"), D, PV_UNIT, "process value, PV units (the monitor's reading; the experiment's while tuning)",
        "pv_range"),
    Var("SP", _key("sp"), D, PV_UNIT, "set point, PV units (the saved SP while tuning)", "pv_range"),
    Var("MV", _key("mv"), D, MV_UNIT, "manipulated variable, MV units", "mv_range"),
    Var("Mode", _key("mode"), S, None, "MAN or AUTO; empty when unknown"),
    *(Var(name, _gain("current_gains", key), D, u, f"controller's current {text}")
      for name, key, u, text in (("k", "pk", K_UNIT, "gain k, MV units per PV unit"),
                                 ("ti", "pti", "s", "integral time ti, s (+Inf: no integral action)"),
                                 ("td", "ptd", "s", "derivative time td, s"),
                                 ("nd", "pnd", None, "derivative filter nd"),
                                 ("b", "pb", None, "set-point weight b (proportional)"),
                                 ("c", "pc", None, "set-point weight c (derivative)"))),
    Var("TBSY", _key("tbsy"), B, None, "tuning busy"),
    Var("TE", _key("te"), B, None, "the last tuning failed (ite holds its code)"),
    Var("ite", _key("ite"), D, None, "while busy: plant seconds left (estimate); after: the outcome code"),
    Var("stage", lambda s: s.get("stage") or "", S, None, "noise, relay, done; empty before the first session"),
    Var("progress", _key("progress"), D, "1", "progress of the running experiment, 0-1"),
    Var("message", _key("message"), S, None, "tuning, idle, or the last session's outcome message"),
    Var("session", lambda s: s.get("session") or "", S, None, "id of the running or last session (REST history)"),
    Var("controller", lambda s: s.get("controller") or "", S, None, "PI or PID of the last session"),
    Var("omega", _point("omega"), D, "rad/s", "identified point: frequency, rad/s"),
    Var("gain", _point("gain"), D, F_UNIT, "identified point: |F(jω)|, PV units per MV unit"),
    Var("phase_deg", _point("phase_deg"), D, "°", "identified point: arg F(jω), degrees (negative: lag)"),
    Var("static_gain", _key("static_gain"), D, F_UNIT,
        "static gain of the last session, PV units per MV unit (NaN: integrating/none)"),
    *(Var(key, _gain("gains", key), D, u, f"last tuned {text}")
      for key, u, text in (("pk", K_UNIT, "gain k, MV units per PV unit"),
                           ("pti", "s", "integral time ti, s (+Inf: no integral)"),
                           ("ptd", "s", "derivative time td, s"), ("pnd", None, "derivative filter nd"),
                           ("pb", None, "set-point weight b"), ("pc", None, "set-point weight c"))),
    Var("pending_gains", _key("pending_gains"), B, None, "the last session succeeded and its gains are not applied"),
    Var("monitor_error", lambda s: s.get("monitor_error") or "", S, None, "why the monitor cannot read the loop"),
    Var("AutoTuningActive", _key("tbsy"), B, None, "OPC 40083: automatic tuning is active (= TBSY)"),
)
# OPC 40083's PIDParameters (P, I, D) of the controller's current gains, children of ``LOOP.PIDParameters``.
PID_PARAMETERS: tuple[Var, ...] = (
    Var("P", _gain("current_gains", "pk"), D, K_UNIT, "OPC 40083 P = k, the proportional gain, MV units per PV unit"),
    Var("I", _gain("current_gains", "pti"), D, "s", "OPC 40083 I = ti, the integral time, s (+Inf: none)"),
    Var("D", _gain("current_gains", "ptd"), D, "s", "OPC 40083 D = td, the derivative time, s"),
)



def _health(key: str, shown: Callable[[Any], Any] = lambda value: value) -> Callable[[dict[str, Any]], Any]:
    """A getter of ``status['health'][key]`` (None while the loop has no health summary)."""
    def get(status: dict[str, Any]) -> Any:
        health = status.get("health")
        value = None if health is None else health.get(key)
        return None if value is None else shown(value)

    return get


# The loop's health (docs/health.md, "Online"), children of ``LOOP.Health``: its summary, as REST's.
HEALTH: tuple[Var, ...] = (
    Var("State", _health("state"), S, None, "ok (assessed for the current gains), pending (collecting samples "
        "since the start or the last tuning) or off (disabled in the config)"),
    Var("Severity", _health("severity"), S, None, "the worst flag's severity: none, low, medium or high"),
    Var("Rank", _health("rank"), D, None, "orders loops worst first (higher: worse; as REST's rank)"),
    Var("Flags", _health("flags", ",".join), S, None, "what is wrong, comma-separated (manual, saturated, "
        "oscillating, stiction, sluggish, noisy, frozen_pv, poor_tracking); empty: nothing"),
    Var("Recommendation", _health("recommendation"), S, None, "the one thing to do first: retune, check_valve, "
        "check_sensor, put_in_auto or none"),
    Var("Reason", _health("reason"), S, None, "the worst flag's one-line reason; while pending, what it waits for"),
    Var("Time", _health("time"), D, "s", "when the assessment was made, unix seconds (NaN: none yet)"),
)

# Written after every other variable of an update.
LAST = frozenset({"TBSY", "AutoTuningActive"})


def node_id(idx: int, *parts: str) -> ua.NodeId:
    """The string NodeId ``PART.PART...`` in namespace ``idx``."""
    return ua.NodeId(".".join(parts), idx)


def _data_value(var: Var, status: dict[str, Any]) -> tuple[Any, ua.DataValue]:
    """(the plain value for change detection, the DataValue to write) of ``var`` in ``status``."""
    value = var.get(status)
    code = ua.StatusCodes.Good
    if value is None:
        code = ua.StatusCodes.BadNoCommunication if status.get("monitor_error") else \
            ua.StatusCodes.BadWaitingForInitialData
        value = "" if var.kind is S else False if var.kind is B else math.nan
    value = float(value) if var.kind is D else value
    key = ("nan" if var.kind is D and math.isnan(value) else value, code)
    stamp = datetime.now(timezone.utc)  # both: asyncua stamps the server's time only on a client's write
    return key, ua.DataValue(Value=ua.Variant(value, var.kind), StatusCode=ua.StatusCode(code),
                             SourceTimestamp=stamp, ServerTimestamp=stamp)


async def _add_variable(parent: Node, idx: int, prefix: tuple[str, ...], var: Var, period: float,
                        units: dict[str, Any]) -> Node:
    """``var`` under ``parent``, with its EngineeringUnits and EURange properties where the loop's ``units``
    (its REST status') give them."""
    node = await parent.add_variable(node_id(idx, *prefix, var.name), ua.QualifiedName(var.name, idx),
                                     "" if var.kind is S else False if var.kind is B else math.nan, var.kind)
    await node.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.Variant(
        ua.LocalizedText(var.description), ua.VariantType.LocalizedText)))
    await node.write_attribute(ua.AttributeIds.MinimumSamplingInterval, ua.DataValue(ua.Variant(
        period * 1000.0, ua.VariantType.Double)))
    symbol = None if var.unit is None else unit_symbol(var.unit, units)
    if symbol is not None:
        await node.add_property(node_id(idx, *prefix, var.name, "EngineeringUnits"),
                                ua.QualifiedName("EngineeringUnits", 0), unit(symbol),
                                datatype=ua.NodeId(ua.ObjectIds.EUInformation))
    span = None if var.eu_range is None else units.get(var.eu_range)
    if span is not None:
        await node.add_property(node_id(idx, *prefix, var.name, "EURange"), ua.QualifiedName("EURange", 0),
                                ua.Range(Low=float(span[0]), High=float(span[1])),
                                datatype=ua.NodeId(ua.ObjectIds.Range))
    analog = ANALOG_TYPES.get((symbol is not None, span is not None))
    if analog is not None:  # the type whose mandatory properties it has: what HMIs look for units and ranges on
        base = ua.NodeId(ua.ObjectIds.BaseDataVariableType)
        await node.delete_reference(base, ua.ObjectIds.HasTypeDefinition)
        await node.add_reference(ua.NodeId(analog), ua.ObjectIds.HasTypeDefinition)
    return node


async def event_type(server: Server, idx: int, name: str, description: str) -> Node:
    """A subtype of BaseEventType with string NodeIds and the properties Loop, Session (String) and Ite (Double)."""
    base = server.get_node(ua.ObjectIds.BaseEventType)
    etype = await base.add_object_type(node_id(idx, name), ua.QualifiedName(name, idx))
    await etype.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.Variant(
        ua.LocalizedText(description), ua.VariantType.LocalizedText)))
    for prop, kind in (("Loop", S), ("Session", S), ("Ite", D)):
        await etype.add_property(node_id(idx, name, prop), ua.QualifiedName(prop, idx), ua.get_default_value(kind),
                                 varianttype=kind)
    return etype


class LoopNodes:
    """The nodes of one loop and the last values written to them; raises its events on the status' transitions."""

    def __init__(self, server: Server, obj: Node, nodes: dict[Var, Node],
                 events: dict[str, list[Any]]) -> None:
        # TBSY last: a client that sees it fall (each write may let other requests in) finds the results there.
        order = sorted(nodes.items(), key=lambda item: item[0].name in LAST)
        self.server, self.obj, self._nodes, self._events = server, obj, dict(order), events
        self._written: dict[Var, Any] = {}
        self._last: dict[str, Any] | None = None

    @classmethod
    async def create(cls, server: Server, folder: Node, idx: int, status: dict[str, Any], period: float,
                     event_types: dict[str, Node]) -> LoopNodes:
        """The loop object of ``status['id']`` under ``folder``, with its variables; methods come later."""
        loop_id = status["id"]
        obj = await folder.add_object(node_id(idx, loop_id), ua.QualifiedName(loop_id, idx))
        await obj.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.Variant(
            ua.LocalizedText(status.get("description") or loop_id), ua.VariantType.LocalizedText)))
        units = status.get("units") or {}
        nodes = {var: await _add_variable(obj, idx, (loop_id,), var, period, units) for var in VARIABLES}
        pid = await obj.add_object(node_id(idx, loop_id, "PIDParameters"), ua.QualifiedName("PIDParameters", idx))
        for var in PID_PARAMETERS:
            nodes[var] = await _add_variable(pid, idx, (loop_id, "PIDParameters"), var, period, units)
        health = await obj.add_object(node_id(idx, loop_id, "Health"), ua.QualifiedName("Health", idx))
        await health.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.Variant(
            ua.LocalizedText("the loop's health: its newest assessment's summary (docs/health.md)"),
            ua.VariantType.LocalizedText)))
        for var in HEALTH:
            nodes[var] = await _add_variable(health, idx, (loop_id, "Health"), var, period, units)
        events: dict[str, list[Any]] = {}
        for name, etype in event_types.items():  # to the loop's subscribers and to the Server object's
            events[name] = [await server.get_event_generator(etype, obj),
                            await server.get_event_generator(etype, ua.ObjectIds.Server)]
        self = cls(server, obj, nodes, events)
        await self.update(status)
        return self

    async def update(self, status: dict[str, Any]) -> None:
        """Write the values of ``status`` that changed; raise the TE and not-restored events of a session's end."""
        for var, node in self._nodes.items():
            key, value = _data_value(var, status)
            if self._written.get(var) != key:
                self._written[var] = key
                await self.server.write_attribute_value(node.nodeid, value)
        last, self._last = self._last, status
        if last is None or status["tbsy"]:
            return
        ended = last["tbsy"] or last.get("session") != status.get("session")
        if ended and status.get("session"):
            await self._session_ended(status)

    async def _session_ended(self, status: dict[str, Any]) -> None:
        ite, message = status.get("ite"), status.get("message") or ""
        if ite == NOT_RESTORED or "NOT RESTORED" in message.upper():
            await self._raise("LoopNotRestored", status, NOT_RESTORED_SEVERITY)
        if status.get("te"):
            await self._raise("TuningError", status, TE_SEVERITY)

    async def _raise(self, name: str, status: dict[str, Any], severity: int) -> None:
        for generator in self._events[name]:
            event = generator.event
            event.Loop, event.Session, event.Ite = status["id"], status.get("session") or "", float(status["ite"])
            event.Severity = severity
            event.SourceNode, event.SourceName = self.obj.nodeid, status["id"]
            await generator.trigger(message=f"{status['id']}: {status.get('message') or ''}")
