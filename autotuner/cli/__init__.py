"""The command line: thin commands that parse, call one library function and render.

One module per command group registers its commands on :data:`autotuner.cli.app.app`:
``tune``, ``sim``/``jitter`` (field), ``serve``, ``bench``/``loadbench`` (benchmarks), ``design``, ``health``.
"""

import os
from typing import Any

# Before numpy's first import. The daemon bounds its analyses in a pool of its own, and a bench runs one
# process per core: OpenBLAS's own threads only spin beside them (on the loadbench plant they doubled the
# load fit's process CPU, docs/experiment.md). The tests pin the same (tests/conftest.py).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from autotuner.cli.app import app  # noqa: E402

# Importing a command module registers its commands, in this order in --help.
from autotuner.cli import tune, field, serve, benchmarks, design, health  # noqa: E402,F401,I001


def main() -> Any:
    """Console-script entry point."""
    return app()


__all__ = ["app", "main"]
