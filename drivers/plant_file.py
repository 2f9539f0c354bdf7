"""A plant file: many simulated loops, each a :class:`drivers.simplc.SimulatedPlc` with its process, gains,
noise and faults (docs/health.md, "Plant file").

    loops:
      - id: TIC-102                      # required: [A-Za-z0-9][A-Za-z0-9_.-]*
        description: sticky valve        # optional
        plant: 1.5*exp(-0.7*s)/(4*s+1)^2 # required: the process, as for --plant
        ts: 0.2                          # plant seconds per tick (default: ~100 per period at 135°)
        noise: 0.05                      # PV noise σ, PV units (default 0)
        seed: 1                          # of the noise and the stochastic load (default 0)
        mode: AUTO                       # or MAN (default AUTO)
        gains: {k: 0.4, ti: 6.9, b: 1}   # PI gains (default: a cautious PI designed for the plant)
        detune: {k: 2.0, ti: 0.5}        # factors on those gains (default 1)
        faults:
          stiction: {s: 3, j: 1}         # Choudhury's S and J, % of the MV span
          deadband: 1                    # % of the MV span
          load: {std: 1.0, tau: 20}      # stochastic load at the process input: σ MV units, τ seconds
          sine: {amplitude: 2, period: 60}  # sinusoidal disturbance at the process input: MV units, seconds
          steps: {size: 5, every: 300}   # random load steps at the process input: MV units, mean interval s
          frozen_pv: 600                 # the PV sensor freezes at this plant time, s

Every loop starts steady at PV = MV = SP = 50 with MV limits 0–100, as the single simulated PLC does.
:func:`load_plant` reads a file, :func:`plant_from_dict` its parsed YAML; both raise :class:`PlantFileError`
naming the file, the loop and the key. :func:`simulated_plc` builds one loop's PLC from its keys: the plant
file's loops and a daemon config's ``sim:`` loops (docs/daemon.md) are validated by it alike.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from typing import Any

from autotuner.engine.control.gains import Gains
from autotuner.engine.plant.expression import parse_process
from autotuner.engine.plant.faults import Faults

from .link import Mode
from .simplc import SimulatedPlc

_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
_LOOP_KEYS = {"id", "description", "plant", "ts", "noise", "seed", "mode", "gains", "detune", "faults"}
_FAULT_KEYS = {"stiction": {"s", "j"}, "deadband": None, "load": {"std", "tau"}, "sine": {"amplitude", "period"},
               "steps": {"size", "every"}, "frozen_pv": None}
_FAULT_FIELDS = {"s": "stiction_s", "j": "stiction_j", "std": "load_std", "tau": "load_tau",
                 "amplitude": "sine_amplitude", "period": "sine_period", "size": "step_size", "every": "step_interval"}


class PlantFileError(ValueError):
    """A plant file that cannot be read or is not valid; the message names where."""


@dataclass
class PlantLoop:
    """One loop of a plant file: its id, description and simulated PLC."""

    id: str
    description: str
    plc: SimulatedPlc


def _number(where: str, value: Any, low: float = -math.inf, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise PlantFileError(f"{where}: must be a finite number, got {value!r}")
    if positive and value <= 0.0:
        raise PlantFileError(f"{where}: must be > 0, got {value!r}")
    if value < low:
        raise PlantFileError(f"{where}: must be ≥ {low:g}, got {value!r}")
    return float(value)


def _mapping(where: str, value: Any, allowed: set[str]) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise PlantFileError(f"{where}: must be a mapping")
    unknown = sorted(set(map(str, value)) - allowed)
    if unknown:
        raise PlantFileError(f"{where}: unknown key {unknown[0]!r} (known: {', '.join(sorted(allowed))})")
    return value


def _faults(where: str, data: Any) -> Faults:
    faults = _mapping(where, data, set(_FAULT_KEYS))
    kw: dict[str, float] = {}
    for name, value in faults.items():
        keys = _FAULT_KEYS[name]
        if keys is None:
            kw[{"deadband": "deadband", "frozen_pv": "frozen_at"}[name]] = _number(f"{where}.{name}", value, 0.0)
            continue
        part = _mapping(f"{where}.{name}", value, keys)
        missing = sorted(keys - set(part))
        if missing:
            raise PlantFileError(f"{where}.{name}: missing key {missing[0]!r}")
        for key in keys:
            kw[_FAULT_FIELDS[key]] = _number(f"{where}.{name}.{key}", part[key], 0.0,
                                             positive=key in ("tau", "period", "every"))
    return Faults(**kw)


def _gains(where: str, loop: dict[str, Any], start: Gains) -> Gains:
    given = _mapping(_at(where, "gains"), loop.get("gains", {}), {"k", "ti", "b"})
    factors = _mapping(_at(where, "detune"), loop.get("detune", {}), {"k", "ti"})
    values = {key: _number(_at(where, f"gains.{key}"), given[key], positive=key == "ti") for key in given}
    k = values.get("k", start.k) * _number(_at(where, "detune.k"), factors.get("k", 1.0), positive=True)
    ti = values.get("ti", start.ti) * _number(_at(where, "detune.ti"), factors.get("ti", 1.0), positive=True)
    try:
        return Gains(k=k, ti=ti, b=values.get("b", start.b))
    except ValueError as exc:
        raise PlantFileError(f"{_at(where, 'gains')}: {exc}") from None


def _at(where: str, key: str) -> str:
    """Where ``key`` is: ``where.key`` (``key`` alone at the top of what is validated)."""
    return f"{where}.{key}" if where else key


def simulated_plc(where: str, data: Any, ts: float | None = None) -> SimulatedPlc:
    """The simulated PLC of one loop's keys (a plant file's loop without its ``id`` and ``description``, or a
    daemon config's ``sim:``): ``plant``, ``ts``, ``noise``, ``seed``, ``mode``, ``gains``, ``detune``,
    ``faults``. ``where`` names the keys in errors (a :class:`PlantFileError`, "" at the top); ``ts``: the
    plant seconds per tick when ``data`` gives none (None: ~100 per period at 135°)."""
    loop = _mapping(where or "the simulated plant", data, _LOOP_KEYS - {"id", "description"})
    if "plant" not in loop:
        raise PlantFileError(f"{where or 'the simulated plant'}: missing key 'plant'")
    try:
        process = parse_process(str(loop["plant"]))
    except ValueError as exc:
        raise PlantFileError(f"{_at(where, 'plant')}: {exc}") from None
    mode = str(loop.get("mode", "AUTO")).upper()
    if mode not in ("AUTO", "MAN"):
        raise PlantFileError(f"{_at(where, 'mode')}: must be AUTO or MAN, got {loop['mode']!r}")
    seed = loop.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise PlantFileError(f"{_at(where, 'seed')}: must be an integer, got {seed!r}")
    tick = _number(_at(where, "ts"), loop["ts"], positive=True) if "ts" in loop else (ts or 0.0)
    try:
        plc = SimulatedPlc(process, ts=tick, noise_std=_number(_at(where, "noise"), loop.get("noise", 0.0), 0.0),
                           seed=seed, faults=_faults(_at(where, "faults"), loop.get("faults", {})))
    except ValueError as exc:
        if isinstance(exc, PlantFileError):
            raise
        raise PlantFileError(f"{where or 'the simulated plant'}: {exc}") from None
    plc.set_gains(_gains(where, loop, plc.gains))
    plc.mode = Mode.MAN if mode == "MAN" else Mode.AUTO
    return plc


def _loop(where: str, data: Any) -> PlantLoop:
    loop = _mapping(where, data, _LOOP_KEYS)
    if "id" not in loop:
        raise PlantFileError(f"{where}: missing key 'id'")
    if not isinstance(loop["id"], str) or not _ID.match(loop["id"]):
        raise PlantFileError(f"{where}.id: {loop['id']!r} is not a loop id ([A-Za-z0-9][A-Za-z0-9_.-]*)")
    plc = simulated_plc(where, {key: value for key, value in loop.items() if key not in ("id", "description")})
    return PlantLoop(loop["id"], str(loop.get("description", "")), plc)


def plant_from_dict(data: Any, source: str = "plant file") -> list[PlantLoop]:
    """The loops of a parsed plant file (``source`` names it in errors)."""
    top = _mapping(source, data, {"loops"})
    loops = top.get("loops")
    if not isinstance(loops, list) or not loops:
        raise PlantFileError(f"{source}: 'loops' must be a non-empty list")
    built = [_loop(f"{source}: loops[{i}]", item) for i, item in enumerate(loops)]
    seen: set[str] = set()
    for i, loop in enumerate(built):
        if loop.id in seen:
            raise PlantFileError(f"{source}: loops[{i}].id: {loop.id!r} given twice")
        seen.add(loop.id)
    return built


def load_plant(path: str | os.PathLike[str]) -> list[PlantLoop]:
    """The loops of the YAML plant file ``path``."""
    import yaml

    name = os.fspath(path)
    try:
        with open(name, encoding="utf-8") as f:
            data = yaml.safe_load(f)
    except OSError as exc:
        raise PlantFileError(f"{name}: cannot read the plant file: {exc.strerror or exc}") from None
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise PlantFileError(f"{name}: not valid YAML: {exc}") from None
    return plant_from_dict(data, name)


def demo_plant_path() -> str:
    """The built-in demo plant (``drivers/data/demo_plant.yaml``): healthy loops and faulty ones."""
    return os.path.join(os.path.dirname(__file__), "data", "demo_plant.yaml")
