"""``autotuner design``: the classical tuning rules from a model, a plant or a measured point, one rule
(``--rule``) or all compared on the plant (``--compare``); ``--list`` names them (docs/rules.md)."""

from __future__ import annotations

import cmath
import json
import math
from enum import Enum
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from autotuner.cli.app import app, bad_input, fmt, gains_rows, stdout

if TYPE_CHECKING:
    from autotuner.benchmarks.rule_comparison import Row
    from autotuner.engine.design.process_data import ProcessData
    from autotuner.engine.design.rules import RuleResult


class RuleController(str, Enum):
    P = "P"
    PI = "PI"
    PID = "PID"


class StepKind(str, Enum):
    LOAD = "load"
    SETPOINT = "setpoint"


def _key_values(text: str, option: str, keys: tuple[str, ...]) -> dict[str, float]:
    """Parse ``k1=v1,k2=v2`` with exactly the given keys; bad input exits with code 2."""
    values: dict[str, float] = {}
    for part in text.split(","):
        key, sep, value = part.partition("=")
        key = key.strip()
        if not sep or key not in keys or key in values:
            bad_input(f"bad {option} {text!r}: expected {','.join(k + '=..' for k in keys)}")
        try:
            values[key] = float(value)
        except ValueError:
            bad_input(f"bad {option} {text!r}: {value.strip()!r} is not a number")
    if set(values) != set(keys):
        bad_input(f"bad {option} {text!r}: expected {','.join(k + '=..' for k in keys)}")
    return values


def _design_data(fopdt: str | None, plant: str | None, point: str | None, static_gain: float | None) -> ProcessData:
    """The process data from exactly one of --fopdt, --plant, --point; bad input exits with code 2."""
    if sum(x is not None for x in (fopdt, plant, point)) != 1:
        bad_input("give exactly one of --fopdt K=..,T=..,L=.., --plant EXPR, --point omega=..,gain=..,phase=..")
    if static_gain is not None and point is None:
        bad_input("--static-gain goes with --point only (a model or plant has its own)")
    from autotuner.engine.design.process_data import from_fopdt, from_plant, from_point
    from autotuner.engine.experiment.relay import Point
    from autotuner.engine.plant.expression import parse_process

    try:
        if fopdt is not None:
            v = _key_values(fopdt, "--fopdt", ("K", "T", "L"))
            return from_fopdt(v["K"], v["T"], v["L"])
        if plant is not None:
            return from_plant(parse_process(plant))
        v = _key_values(point, "--point", ("omega", "gain", "phase"))
        if not (v["omega"] > 0 and v["gain"] > 0 and -360.0 < v["phase"] <= 0.0):
            bad_input("--point needs omega > 0 rad/s, gain > 0 and phase = arg F in degrees, "
                      "negative for lag (e.g. phase=-135)")
        value = v["gain"] * cmath.exp(1j * math.radians(v["phase"]))
        return from_point(Point(v["omega"], value), static_gain)
    except ValueError as exc:  # DataError, ExpressionError (names the token and its position)
        bad_input(str(exc))


def _extra_rows(tuning: RuleResult) -> list[tuple[str, str]]:
    rows = []
    for key, value in tuning.extra.items():
        if key == "two_controller":
            rows += [(name.replace("_", " "), json.dumps(value)) for name, value in value.items()]
        else:
            rows.append((key, ", ".join(f"{k} = {fmt(v) if isinstance(v, float) else v}" for k, v in value.items())))
    return rows


def _tuning_table(tuning: RuleResult) -> Table:
    table = Table(title=f"{tuning.rule}: {tuning.controller}", show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    for name, text in gains_rows(tuning.gains) + _extra_rows(tuning):
        table.add_row(name, text)
    return table


def _compare_table(rows: list[Row], controller: str) -> Table:
    from autotuner.benchmarks.rule_comparison import METHOD_NOTE

    table = Table(title=f"{controller} rules compared on the plant", title_justify="left", caption=METHOD_NOTE,
                  caption_justify="left")
    table.add_column("rule", no_wrap=True)
    for col in ("k", "ti", "td", "b", "Ms", "GM", "PM °", "IAE load"):
        table.add_column(col, justify="right")
    for r in rows:
        g = r.tuning.gains
        metrics = ((fmt(r.ms), fmt(r.gain_margin), fmt(r.phase_margin_deg), fmt(r.iae)) if r.stable
                   else ("unstable", "—", "—", "—"))
        table.add_row(r.tuning.rule, fmt(g.k), fmt(g.ti), fmt(g.td), fmt(g.b), *metrics)
    return table


def _skipped_text(skipped: dict[str, str]) -> str:
    return "\n".join(f"not applicable: {name}: {reason}" for name, reason in skipped.items())


def _rule_list() -> Table:
    from autotuner.engine.design.rules import RULES

    table = Table(title="tuning rules (autotuner design --rule NAME)", title_justify="left")
    for col in ("rule", "controllers", "when to use it", "source"):
        table.add_column(col)
    for rule in RULES.values():
        table.add_row(rule.name, "/".join(rule.controllers), rule.when, rule.source)
    return table


@app.command("design")
def design_command(
    rule: Annotated[str | None, typer.Option(help="Rule name (see --list).")] = None,
    list_rules: Annotated[bool, typer.Option("--list", help="List the rules with when to use each.")] = False,
    compare_rules: Annotated[bool, typer.Option("--compare", help="All applicable rules in one table with Ms, "
                                                "margins and load-step IAE on the plant.")] = False,
    fopdt: Annotated[str | None, typer.Option(help="FOPDT model K·e^(−Ls)/(Ts+1): K=..,T=..,L=.. (s).")] = None,
    plant: Annotated[str | None, typer.Option(help="Process transfer function in s with optional dead time.")] = None,
    point: Annotated[str | None, typer.Option(help="Measured point F(jω): omega=..(rad/s),gain=..,phase=..(deg, "
                                              "negative for lag).")] = None,
    static_gain: Annotated[float | None, typer.Option(help="Static gain with --point (inf: integrating).")] = None,
    controller: Annotated[RuleController | None, typer.Option(case_sensitive=False, help="Controller type. "
                                                              "Default: PI (PID for direct-synthesis-unstable).")] = None,
    ts: Annotated[float | None, typer.Option(help="Sample time, s (takahashi).")] = None,
    ms: Annotated[float | None, typer.Option(min=1.05, max=10.0, help="Ms target: robust and itae-optimal "
                                             "(default 1.4), direct-synthesis-unstable (default 3).")] = None,
    rb: Annotated[float, typer.Option(help="astrom-hagglund: radius r_b of the target point (0–1).")] = 0.5,
    phib: Annotated[float, typer.Option(help="astrom-hagglund: angle φ_b of the target point, degrees.")] = 45.0,
    step: Annotated[StepKind, typer.Option(help="itae-optimal: the step whose ITAE is minimised.")] = StepKind.LOAD,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object to stdout.")] = False,
) -> None:
    """Classical tuning rules from a model, a plant or a measured point (methods.md §4).

    Exit codes: 0 success, 2 bad input or a rule that does not apply.
    """
    from autotuner.benchmarks.rule_comparison import compare, compare_json
    from autotuner.engine.design.rules import Options, RuleError, tune as tune_rule

    if list_rules:
        stdout.print(_rule_list())
        return
    if (rule is None) == (not compare_rules):
        bad_input("give --rule NAME or --compare (or --list)")
    data = _design_data(fopdt, plant, point, static_gain)
    options = Options(ts=ts, ms=ms, rb=rb, phib_deg=phib, step=step.value)
    kind = controller.value if controller else None
    try:
        if compare_rules:
            rows, skipped = compare(data, kind or "PI", options)
        else:
            tuning = tune_rule(rule, data, kind, options)
    except RuleError as exc:
        bad_input(str(exc))
    if compare_rules:
        if as_json:
            print(json.dumps(compare_json(rows, skipped, kind or "PI"), allow_nan=False))
        else:
            stdout.print(_compare_table(rows, kind or "PI"))
            stdout.print(_skipped_text(skipped), highlight=False, markup=False)
    elif as_json:
        print(json.dumps(tuning.as_json(), allow_nan=False))
    else:
        stdout.print(_tuning_table(tuning))
