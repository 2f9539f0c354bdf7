"""The pure engine: process models and simulation, the PID unit, the relay experiment, design and rules (numpy/scipy only, no I/O)."""
