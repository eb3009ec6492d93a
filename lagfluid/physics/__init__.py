"""MPS operators, split-step stages and the exact (ground-truth) stage implementations."""
