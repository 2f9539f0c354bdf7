"""The ``autotuner`` Typer application and what its commands share: the consoles, exit codes, bad input.

The commands live in one module per group (tune, field, serve, design, benchmarks) and register
themselves on :data:`app`. They import the engine and the service inside their bodies, so that
``autotuner --help`` and every ``--help`` start without loading scipy, pydantic or the drivers.
"""

from __future__ import annotations

import math
from enum import Enum
from typing import TYPE_CHECKING, Annotated, NoReturn

import typer
from rich.console import Console
from rich.markup import escape

from autotuner import __version__

if TYPE_CHECKING:  # only for annotations: the commands import the engine when they run
    from autotuner.engine.control.gains import Gains
    from autotuner.engine.plant.process import Process

DEMO_PLANT = "1.5*exp(-0.7*s)/(4*s+1)^2"

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2

stdout = Console()
stderr = Console(stderr=True)

app = typer.Typer(
    help="Relay-feedback PI/PID autotuner: identify one point of the process frequency "
    "response with a relay + adaptive phase filter, then compute robust gains.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    # Help texts are rich markup on every typer version (older ones defaulted to plain text): a literal
    # bracket in a help text is written escaped (rich.markup.escape), and tests/test_cli_help.py renders them all.
    rich_markup_mode="rich",
)


class Controller(str, Enum):
    PI = "PI"
    PID = "PID"


class Transport(str, Enum):
    MODBUS = "modbus"
    CAN = "can"


def _version_callback(value: bool) -> None:
    if value:
        print(__version__)
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool, typer.Option("--version", callback=_version_callback, is_eager=True, help="Print the version and exit.")
    ] = False,
) -> None:
    """Relay-feedback PI/PID autotuner."""


@app.command()
def version() -> None:
    """Print the version."""
    print(__version__)


def bad_input(message: str) -> NoReturn:
    """Print ``message`` as an error on stderr and exit with code 2 (bad input)."""
    stderr.print(f"[bold red]error:[/] {escape(message)}", highlight=False, markup=True, soft_wrap=True)
    raise typer.Exit(EXIT_BAD_INPUT)


def parse_plant(text: str, option: str = "--plant") -> Process:
    """The process of a plant expression; bad input (exit 2) names the token and its position."""
    from autotuner.engine.plant.expression import parse_process

    try:
        return parse_process(text)
    except ValueError as exc:  # ExpressionError names the token and its position
        bad_input(f"bad {option} expression\n{exc}")


def parse_loads(texts: list[str] | None, origin: str) -> list[tuple[float, float]]:
    """``--load T:SIZE`` options as (plant seconds from ``origin``, MV units) load steps; bad input exits 2."""
    steps = []
    for text in texts or []:
        when, sep, size = text.partition(":")
        try:
            step: tuple[float, float] | None = (float(when), float(size))
        except ValueError:
            step = None
        if not sep or step is None or not all(math.isfinite(x) for x in step) or step[0] < 0.0:
            bad_input(f"bad --load {text!r}: expected T:SIZE, T ≥ 0 plant seconds from {origin} and SIZE the "
                      "step in MV units at the process input, e.g. --load 30:0.2")
        steps.append(step)
    return steps


def fmt(x: float, unit: str = "") -> str:
    """A number for a table: 4 significant digits, ∞ for infinity."""
    return "∞" if math.isinf(x) else f"{x:.4g}{unit}"


def gains_rows(gains: Gains) -> list[tuple[str, str]]:
    """Table rows of the gains in standard, series (or why it does not exist) and parallel form."""
    from autotuner.engine.control.gains import FormError, to_parallel, to_series

    rows = [
        ("standard (ISA)", f"k = {fmt(gains.k)}, ti = {fmt(gains.ti, ' s')}, td = {fmt(gains.td, ' s')}, "
         f"nd = {fmt(gains.nd)}, b = {fmt(gains.b)}, c = {fmt(gains.c)}"),
    ]
    try:
        s = to_series(gains)
        rows.append(("series", f"k' = {fmt(s.k)}, ti' = {fmt(s.ti, ' s')}, td' = {fmt(s.td, ' s')}"))
    except FormError as exc:
        rows.append(("series", f"does not exist: {exc}"))
    p = to_parallel(gains)
    rows.append(("parallel", f"kp = {fmt(p.kp)}, ki = {fmt(p.ki, ' /s')}, kd = {fmt(p.kd, ' s')}"))
    return rows
