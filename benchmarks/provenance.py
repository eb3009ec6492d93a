"""Provenance of a benchmark run: when, on what, from which commit, with which command and load.

Every committed result carries this block, so a number can be traced to the run that produced it.
"""

from __future__ import annotations

import csv
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


def write_results(out: Path, name: str, rows: list[dict], intro: str, prov: dict[str, str]) -> str:
    """Write ``out/<name>.csv`` (the rows) and ``out/<name>.md`` (``intro``, the rows, the provenance).

    Args:
        out: the results folder (made if missing).
        name: file stem, e.g. ``wall_approach``.
        rows: one dict per row, every row with the first row's keys (the columns, in order).
        intro: the markdown before the table: a ``#`` title and what the table says.
        prov: :func:`provenance`'s block.

    Returns:
        The markdown written.
    """
    out.mkdir(parents=True, exist_ok=True)
    with open(out / f"{name}.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    header = "| " + " | ".join(rows[0]) + " |\n| " + " | ".join("---" for _ in rows[0]) + " |\n"
    table = header + "\n".join("| " + " | ".join(str(r[k]) for k in rows[0]) + " |" for r in rows)
    text = f"{intro}\n\n{table}\n\n## Provenance\n\n{markdown(prov)}\n"
    (out / f"{name}.md").write_text(text)
    return text
