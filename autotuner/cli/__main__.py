"""``python -m autotuner.cli``: the ``autotuner`` command."""

from autotuner.cli.commands import main

main()
