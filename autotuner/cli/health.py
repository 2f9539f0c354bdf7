"""``autotuner health FILE.csv``: the loop-health assessment of a historian export (docs/health.md)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.markup import escape
from rich.table import Table

from autotuner.cli.app import app, bad_input, fmt, parse_plant, stdout

if TYPE_CHECKING:  # only for annotations: the command imports the engine when it runs
    from autotuner.engine.health.assessment import Assessment


def _range(text: str, option: str) -> tuple[float, float]:
    low, sep, high = text.partition(":")
    try:
        pair = (float(low), float(high))
    except ValueError:
        pair = None
    if not sep or pair is None or not all(math.isfinite(x) for x in pair) or not pair[0] < pair[1]:
        bad_input(f"bad {option} {text!r}: expected LO:HI with LO < HI, e.g. {option} 0:100")
    return pair


@app.command("health")
def health_command(
    file: Annotated[Path, typer.Argument(help="CSV with a header row and the columns t (seconds, or ISO-8601 "
                                         "timestamps), sp, pv, mv and optionally mode (AUTO/MAN); other columns "
                                         "are ignored.", show_default=False)],
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object as the last line of stdout.")]
    = False,
    mv_limits: Annotated[str, typer.Option("--mv-limits", help="The MV limits LO:HI, MV units.")] = "0:100",
    pv_range: Annotated[str | None, typer.Option("--pv-range", help="The PV range LO:HI, PV units (default: "
                                                 "from the model's gain, else from the data).")] = None,
    model: Annotated[str | None, typer.Option("--model", help="The process model of the last tuning, e.g. "
                                              "'1.5*exp(-0.7*s)/(4*s+1)^2': its dead time for the Harris index, "
                                              "its ultimate period for the oscillation detector.")] = None,
    ts: Annotated[float | None, typer.Option("--ts", help="Sample time to assess at, seconds (default: the "
                                             "file's median spacing; an uneven file is resampled).")] = None,
    window: Annotated[float | None, typer.Option("--window", help="Assess the last this many seconds "
                                                 "(default: the whole file).")] = None,
) -> None:
    """Assess a loop's health from a historian export: oscillation, stiction, sluggishness, noise, … and what
    to do about it."""
    from autotuner.engine.health.assessment import assess
    from autotuner.engine.health.scales import LoopLimits
    from autotuner.service.health_csv import CsvError, read_record

    if ts is not None and not (math.isfinite(ts) and ts > 0.0):
        bad_input(f"bad --ts {ts:g}: a sample time is a positive number of seconds")
    if window is not None and not window > 0.0:
        bad_input(f"bad --window {window:g}: a window is a positive number of seconds")
    limits = LoopLimits(mv=_range(mv_limits, "--mv-limits"),
                        pv=None if pv_range is None else _range(pv_range, "--pv-range"))
    process = None if model is None else parse_plant(model, "--model")
    try:
        result = assess(read_record(file), limits, process, math.inf if window is None else window, ts)
    except CsvError as exc:
        bad_input(str(exc))
    except ValueError as exc:  # too few samples in the window, a sample time longer than the file
        bad_input(f"{file}: {exc}")
    if as_json:
        print(json.dumps(result.to_json(), allow_nan=False))
        return
    _render(result)


def _render(result: Assessment) -> None:
    """The flags and the indices as two tables."""
    from autotuner.engine.health.indices import Indices

    flags = Table(title=f"loop health: {result.samples} samples of {fmt(result.ts, ' s')}, "
                        f"{fmt(result.end - result.start, ' s')}; recommendation: {result.recommendation}",
                  title_justify="left")
    for name in ("flag", "severity", "reason"):
        flags.add_column(name)
    for f in result.flags:
        flags.add_row(f.name, f.severity.value, escape(f.reason))
    if not result.flags:
        flags.add_row("none", "", "no problem found")
    stdout.print(flags)
    indices = Table(title="indices", title_justify="left")
    for name in ("index", "value", "meaning"):
        indices.add_column(name)
    described = {f.name: f.metadata["description"] for f in Indices.__dataclass_fields__.values()}
    for name, value in result.indices.to_json().items():
        shown = "–" if value is None else str(value) if isinstance(value, int) else fmt(value)
        indices.add_row(name, shown, escape(described[name]))
    stdout.print(indices)
    if result.dead_time_source is not None:
        stdout.print(f"Harris index: dead time from {result.dead_time_source}", highlight=False)
