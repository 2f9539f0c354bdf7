"""Benchmarks: the design over the batch, the rules compared, the daemon under load."""
