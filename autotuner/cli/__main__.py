"""``python -m autotuner.cli``: the ``autotuner`` command."""

from autotuner.cli import main

main()
