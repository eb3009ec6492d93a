"""A run's output files replace the previous run's together, and only once the run has ended.

A task calls :func:`begin` once everything that can fail before the first step has been checked, writes
every output under its :func:`part_path` (``rollout.part.h5``) and calls :func:`publish` at the end,
whatever happened in between: a folder never holds files of two runs, a run that fails before its first
step leaves the last run's files untouched, and a run that ends incomplete keeps the last complete run's
files in ``previous/``.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from lagfluid.data.store import TrajectoryFileError, open_lagfluid_file

log = logging.getLogger(__name__)


def finite_or_none(value: Any) -> Any:
    """``value`` with every NaN/inf float (in nested dicts, lists, tuples) as None: JSON has no NaN."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_none(v) for v in value]
    return value


def write_json(path: Path, value: Any) -> None:
    """Write ``value`` as strict JSON (undefined numbers as null, which every parser reads)."""
    path.write_text(json.dumps(finite_or_none(value), indent=2, allow_nan=False))


def part_path(path: Path) -> Path:
    """Where a run writes ``path`` until it ends: ``rollout.h5`` -> ``rollout.part.h5`` (same suffix)."""
    return path.with_name(f"{path.stem}.part{path.suffix}")


def begin(out_dir: Path, names: Sequence[str]) -> None:
    """Start a run in ``out_dir``: make it, and drop the part files a crashed earlier run left."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for name in names:
        part_path(out_dir / name).unlink(missing_ok=True)


def _complete_rollout(path: Path) -> bool:
    """Whether ``path`` holds a finished rollout (attributes only; the arrays are not read)."""
    try:
        with open_lagfluid_file(path) as f:
            return bool(f["00000"].attrs.get("complete", False))
    except (TrajectoryFileError, OSError, KeyError):
        return False


def publish(out_dir: Path, names: Sequence[str], complete: bool) -> None:
    """Move this run's part files of ``names`` into place; an earlier file this run did not write goes too.

    A run without its rollout's part file (it failed before writing it) publishes nothing: its other part
    files are dropped and the folder's files stay as they were.

    Args:
        out_dir: the run's folder.
        names: its output file names; ``names[0]`` is the rollout whose ``complete`` flag marks a finished
            earlier run.
        complete: whether this run finished; if not, a finished earlier run's files move to ``previous/``
            (and a finished run removes ``previous/``: it holds the last complete run only).
    """
    if not part_path(out_dir / names[0]).exists():  # no rollout of this run: nothing of it to publish
        for name in names:
            part_path(out_dir / name).unlink(missing_ok=True)
        log.warning("this run wrote no %s; the files in %s are left as they were", names[0], out_dir)
        return
    old = [out_dir / name for name in names if (out_dir / name).exists()]
    if complete:  # a complete run supersedes the one an incomplete run had set aside
        shutil.rmtree(out_dir / "previous", ignore_errors=True)
    elif old and _complete_rollout(out_dir / names[0]):
        keep = out_dir / "previous"
        shutil.rmtree(keep, ignore_errors=True)
        keep.mkdir()
        for path in old:
            os.replace(path, keep / path.name)
        log.warning("this run is incomplete; the last complete run's outputs are kept in %s", keep)
    for name in names:
        final = out_dir / name
        if part_path(final).exists():
            os.replace(part_path(final), final)
        else:
            final.unlink(missing_ok=True)
