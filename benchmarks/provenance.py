"""Provenance of a benchmark run: when, on what, from which commit, with which command and load.

Every committed result carries this block, so a number can be traced to the run that produced it.
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import os
import platform
import shlex
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

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


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` whole or not at all: a temporary file beside it, then ``os.replace``.

    A run that fails mid-write (a full disk, an interrupt) leaves the previous file as it was and no
    temporary file behind. The text is written as given (``newline=""``: the csv module's line ends too).
    """
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w", newline="") as f:
            f.write(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def markdown_table(
    rows: list[dict], cell: Callable[[Any], str] = str, align: str = "---", left: tuple[str, ...] = ()
) -> str:
    """The rows as a markdown table, one column per key of the first row.

    Args:
        rows: one dict per row, every row with the first row's keys.
        cell: how a value is written (e.g. floats to 4 significant digits).
        align: the rule under every header (``---`` left, ``---:`` right) but those in ``left`` (``---``).
        left: columns kept left-aligned whatever ``align`` says (labels beside numbers).
    """
    keys = list(rows[0])
    rule = ["---" if k in left else align for k in keys]
    lines = ["| " + " | ".join(keys) + " |", "| " + " | ".join(rule) + " |"]
    lines += ["| " + " | ".join(cell(r[k]) for k in keys) + " |" for r in rows]
    return "\n".join(lines)


def results_markdown(rows: list[dict], intro: str, prov: dict[str, str], body: str | None = None) -> str:
    """``intro``, the table of ``rows`` (or ``body`` in its place), then the provenance: a results file."""
    body = markdown_table(rows) if body is None else body
    return f"{intro}\n\n{body}\n\n## Provenance\n\n{markdown(prov)}\n"


def write_results(
    out: Path, name: str, rows: list[dict], intro: str, prov: dict[str, str], body: str | None = None
) -> str:
    """Write ``out/<name>.csv`` (the rows) and ``out/<name>.md`` (``intro``, the rows, the provenance).

    The one writer of the benchmarks' results; each file is written atomically (:func:`write_atomic`).

    Args:
        out: the results folder (made if missing).
        name: file stem, e.g. ``wall_approach``.
        rows: one dict per row, every row with the first row's keys (the columns, in order).
        intro: the markdown before the table: a ``#`` title and what the table says.
        prov: :func:`provenance`'s block.
        body: the markdown between ``intro`` and the provenance when the rows alone do not say it (their
            table formatted or transposed, notes after it, several tables); default: the rows' table.

    Returns:
        The markdown written.
    """
    out.mkdir(parents=True, exist_ok=True)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    write_atomic(out / f"{name}.csv", buffer.getvalue())
    text = results_markdown(rows, intro, prov, body)
    write_atomic(out / f"{name}.md", text)
    return text
