"""The command line: thin commands that parse, call one library function and render.

One module per command group registers its commands on :data:`autotuner.cli.app.app`:
``tune``, ``sim``/``jitter`` (field), ``serve``, ``bench``/``loadbench`` (benchmarks), ``design``, ``health``.
"""

from typing import Any

from autotuner.cli.app import app

# Importing a command module registers its commands, in this order in --help.
from autotuner.cli import tune, field, serve, benchmarks, design, health  # noqa: E402,F401,I001


def main() -> Any:
    """Console-script entry point."""
    return app()


__all__ = ["app", "main"]
