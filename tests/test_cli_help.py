"""Every command's ``--help`` through the real entry points (the console script and ``python -m
autotuner.cli``), on whatever typer/rich the environment has: a help text is also rendered as rich markup,
and a stray ``[...]`` in it crashed ``autotuner tune --help`` once."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import typer

from autotuner.cli import app

SCRIPT = Path(sys.executable).with_name("autotuner")
ENV = {**os.environ, "COLUMNS": "200", "TERM": "dumb"}  # wide: a phrase checked below stays on one line


def _command_paths(command: object, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    paths = [prefix]
    if getattr(command, "commands", None):  # a group (typer may vendor its own click: no isinstance)
        for name, sub in sorted(command.commands.items()):
            paths += _command_paths(sub, (*prefix, name))
    return paths


PATHS = _command_paths(typer.main.get_command(app))


def _help(argv: list[str]) -> str:
    out = subprocess.run(argv, capture_output=True, text=True, timeout=120, env=ENV)
    assert out.returncode == 0, f"{argv}: exit {out.returncode}\n{out.stderr}"
    assert "Traceback" not in out.stderr, out.stderr
    assert "Usage" in out.stdout, out.stdout
    return out.stdout


def test_every_command_is_listed() -> None:
    names = {path[0] for path in PATHS if path}
    assert {"tune", "design", "bench", "serve", "sim", "jitter", "loadbench", "version"} <= names


@pytest.mark.parametrize("path", PATHS, ids=lambda p: " ".join(p) or "autotuner")
def test_help_of_every_command(path: tuple[str, ...]) -> None:
    text = _help([sys.executable, "-m", "autotuner.cli", *path, "--help"])
    for name in path:
        assert name in text


def test_help_through_the_console_script() -> None:
    assert SCRIPT.exists(), f"no console script next to {sys.executable}: install the project (pip install -e .)"
    text = _help([str(SCRIPT), "tune", "--help"])
    # The brackets are shown as written, not taken for markup.
    assert "modbus://HOST:PORT[/UNIT]" in text
    assert "tune" in _help([str(SCRIPT), "--help"])
