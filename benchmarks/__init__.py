"""Benchmarks: speed and accuracy tables, run as ``python -m benchmarks.<name>``; results in ``results/``."""
