"""One-off studies: finished investigations whose results the README, docs and model cards quote.

Each runs as ``python -m benchmarks.studies.<name>`` and writes to ``benchmarks/results/`` like the
benchmarks (results stay there, beside the files that cite them); ``benchmarks/`` itself holds what a user
reruns (the tables, speed, validation and extremes harnesses).
"""
