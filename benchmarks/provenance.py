"""Provenance of a benchmark run: when, on what, from which commit, with which command and load.

Every committed result carries this block, so a number can be traced to the run that produced it.
"""

from __future__ import annotations

import datetime as dt
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

import scipy
import torch


def git_commit() -> str:
    """Short commit of the source tree, noting uncommitted changes; 'unknown' outside a repository.

    Changes under ``benchmarks/results/`` do not count: they are what a benchmark writes (a run's own
    figures, written before its report, would otherwise mark its report as made from uncommitted code).
    """
    root = Path(__file__).resolve().parents[1]
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--", ".", ":(exclude)benchmarks/results"],
            cwd=root,
            capture_output=True,
            text=True,
        )
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return sha + (" + uncommitted changes in the working tree" if dirty.stdout.strip() else "")


def provenance(module: str, load_before: float, device: str = "cpu", **extra: str) -> dict[str, str]:
    """The provenance keys of a run of ``python -m <module>``, plus the benchmark's own ``extra`` keys.

    Args:
        module: the benchmark's module name, e.g. ``benchmarks.neighbors``.
        load_before: 1-minute load average when the run started (``os.getloadavg()[0]``).
        device: the torch device the run used.
        **extra: further ``key=value`` lines (runtime, particles, solver, ...).
    """
    machine = f"{platform.platform()}, {platform.machine()}, {os.cpu_count()} CPUs"
    if torch.device(device).type == "cuda":
        machine += f", {torch.cuda.get_device_name(torch.device(device))}"
    return {
        "date": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": machine,
        "versions": (
            f"python {platform.python_version()}, torch {torch.__version__}, scipy {scipy.__version__}"
        ),
        "torch threads": str(torch.get_num_threads()),
        "git commit": git_commit(),
        "command": (f"python -m {module} " + shlex.join(sys.argv[1:])).rstrip(),
        "load average (1 min) before / after": f"{load_before:.2f} / {os.getloadavg()[0]:.2f}",
        **extra,
    }


def markdown(prov: dict[str, str]) -> str:
    """The provenance as a markdown list."""
    return "\n".join(f"- {k}: {v}" for k, v in prov.items())
