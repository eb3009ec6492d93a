"""A run's outputs: CSV files, the report's parts (merged with an earlier run's on ``--only``), the README."""

from __future__ import annotations

import csv
import json
import logging
import os
import platform
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lagfluid.errors import ConfigError

log = logging.getLogger("benchmarks.tables")

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "benchmarks" / "results"
README = REPO / "README.md"
MARK_START, MARK_END = "<!-- tables:start -->", "<!-- tables:end -->"


@dataclass
class Report:
    """What a run of the script writes: CSV files, report sections, README pieces."""

    prefix: Path
    meta: dict[str, str]
    sections: dict[str, str] = field(default_factory=dict)
    readme: dict[str, str] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)
    rows: dict[str, list[dict[str, Any]]] = field(default_factory=dict)

    def path(self, suffix: str) -> Path:
        """``<prefix>_<suffix>`` (e.g. ``tables_quick_tradeoff.png``), remembered as written."""
        path = Path(f"{self.prefix}_{suffix}")
        self.files.append(path)
        return path

    def csv(self, name: str, rows: list[dict[str, Any]]) -> None:
        """Write ``<prefix>_<name>.csv`` with the run-wide provenance columns."""
        write_csv(self.path(f"{name}.csv"), rows, self.meta)
        self.rows[name] = rows


def write_csv(path: Path, rows: list[dict[str, Any]], meta: dict[str, str]) -> None:
    """Rows as CSV, each with the run-wide provenance columns (machine, date, the script's commit)."""
    if not rows:
        return
    rows = [{**r, **meta} for r in rows]
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})


def cpu_model() -> str:
    """The CPU's model name (Linux /proc/cpuinfo; the platform's processor string elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def write_readme(
    section: str, readme: Path = README, marks: tuple[str, str] = (MARK_START, MARK_END)
) -> bool:
    """Replace the text between the README's ``marks`` (the tables') with ``section``; False without them."""
    start, end = marks
    text = readme.read_text()
    if start not in text or end not in text:
        log.warning("%s has no %s ... %s markers: README not updated", readme, start, end)
        return False
    head, rest = text.split(start, 1)
    _, tail = rest.split(end, 1)
    readme.write_text(f"{head}{start}\n{section.strip()}\n{end}{tail}")
    return True


def parts_file(prefix: Path) -> Path:
    """``<prefix>_parts.json``: what a run rendered, for the ``--only`` reruns that merge with it."""
    return Path(f"{prefix}_parts.json")


def missing_parts_message(path: Path, options: str = "") -> str:
    """Why an ``--only`` run cannot go on: the earlier run's ``<prefix>_parts.json`` at ``path`` is missing.

    ``options``: what the whole run needs besides (``--simulators gns_unroll``: the subset's own file).
    """
    same = f" with {options}" if options else ""
    return (
        f"--only reruns parts of an earlier run, but {path} is missing: run the whole profile first{same} "
        "(without --only), or the other parts would vanish from the report and the README"
    )


def merge_parts(
    report: Report, partial: bool, commands: dict[str, str], invocation: str = ""
) -> dict[str, dict[str, str]]:
    """This run's report sections and README pieces, over those an earlier run saved (``--only`` reruns).

    Every run saves what it rendered to ``<prefix>_parts.json`` with the date and commit of the run that
    made each piece, so that ``--only table2`` (say, on a quieter machine) replaces Table 2 and keeps the
    other parts, each still saying when it was run. A full run starts afresh. ``history`` keeps each run's
    command and runtime, so the report still says what made the parts an ``--only`` run kept.

    Args:
        report: this run's rendered parts.
        partial: an ``--only`` run (merge with the saved parts) rather than a full one.
        commands: this run's rows, ``{row key: command}``.
        invocation: this run's command and runtime, for the history.

    Returns:
        ``{"sections": {part: markdown}, "readme": {piece: markdown}, "runs": {key: "date at commit"},
        "commands": {row key: command}, "history": {"date at commit": invocation}}``.
    """
    path = parts_file(report.prefix)
    merged: dict[str, dict[str, str]] = {
        "sections": {},
        "readme": {},
        "runs": {},
        "commands": {},
        "history": {},
    }
    if partial and not path.is_file():
        raise ConfigError(missing_parts_message(path))
    if partial:
        try:
            saved = json.loads(path.read_text())
            merged = {k: dict(saved.get(k, {})) for k in merged}
        except (OSError, ValueError) as err:
            log.warning("%s unreadable (%s): only this run's parts are written", path, err)
    run = f"{report.meta['date']} at commit {report.meta['script_commit']}"
    for kind in ("sections", "readme"):
        for key, text in getattr(report, kind).items():
            merged[kind][key] = text
            merged["runs"][f"{kind}:{key}"] = run
    merged["commands"].update(commands)
    merged["history"][run] = invocation
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(json.dumps(merged, indent=1))
    os.replace(tmp, path)
    report.files.append(path)
    return merged


def earlier_parts(merged: dict[str, dict[str, str]], kind: str, run: str) -> str:
    """A line naming the pieces of ``kind`` that come from earlier runs than ``run`` ('' when none)."""
    older = {k.split(":", 1)[1]: v for k, v in merged["runs"].items() if k.startswith(kind) and v != run}
    if not older:
        return ""
    return (
        "Parts from earlier runs (`--only` reran the others): "
        + "; ".join(f"{k}: {v}" for k, v in sorted(older.items()))
        + ".\n\n"
    )
