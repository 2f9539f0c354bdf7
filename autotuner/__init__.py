"""autotuner: relay-feedback PID autotuning engine (pure, sample-driven, no I/O)."""

__version__ = "0.1.0"
