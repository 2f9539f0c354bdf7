"""REST API of the autotuner daemon."""
