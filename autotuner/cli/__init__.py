"""The command line: thin commands that parse, call one library function and render."""

from autotuner.cli.commands import app, main

__all__ = ["app", "main"]
