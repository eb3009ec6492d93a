"""The benchmarks' one writer, ``benchmarks.provenance.write_results``: a table's csv and md, atomically."""

from __future__ import annotations

import csv
import os

import pytest

from benchmarks import provenance
from benchmarks.provenance import markdown_table, write_results

PROV = {"date": "2026-01-01 00:00 UTC", "command": "python -m benchmarks.example"}
ROWS = [{"case": "a", "ms": 1.5}, {"case": "b", "ms": 20.25}]


def test_write_results_writes_the_rows_the_intro_and_the_provenance(tmp_path):
    text = write_results(tmp_path / "out", "example", ROWS, "# Example\n\nWhat it says.", PROV)
    assert (
        (tmp_path / "out" / "example.md").read_text()
        == text
        == (
            "# Example\n\nWhat it says.\n\n| case | ms |\n| --- | --- |\n| a | 1.5 |\n| b | 20.25 |\n\n"
            "## Provenance\n\n- date: 2026-01-01 00:00 UTC\n- command: python -m benchmarks.example\n"
        )
    )
    with (tmp_path / "out" / "example.csv").open(newline="") as f:
        assert list(csv.DictReader(f)) == [{"case": "a", "ms": "1.5"}, {"case": "b", "ms": "20.25"}]
    assert (tmp_path / "out" / "example.csv").read_bytes().startswith(b"case,ms\r\n")  # csv's own line ends
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["example.csv", "example.md"]


def test_a_body_replaces_the_default_table():
    def cell(v):
        return f"{v:.2g}" if isinstance(v, float) else v

    body = markdown_table(ROWS, cell=cell, align="---:", left=("case",))
    assert body.splitlines()[1:] == ["| --- | ---: |", "| a | 1.5 |", "| b | 20 |"]
    text = provenance.results_markdown(ROWS, "# T", PROV, body + "\n\nA note.")
    assert text.startswith(f"# T\n\n{body}\n\nA note.\n\n## Provenance\n")


def test_a_failure_mid_write_leaves_the_old_results_intact(tmp_path, monkeypatch):
    write_results(tmp_path, "example", ROWS, "# Old", PROV)
    old = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert sorted(old) == ["example.csv", "example.md"] and old["example.csv"].startswith(b"case,ms")

    def full_disk(self, text):
        raise OSError(28, "No space left on device")

    real_open = open

    def opening(path, mode="r", *args, **kwargs):  # every file opened for writing fails on its first write
        f = real_open(path, mode, *args, **kwargs)
        if "w" in mode:
            f.write = full_disk.__get__(f)
        return f

    monkeypatch.setattr("builtins.open", opening)
    with pytest.raises(OSError, match="No space"):
        write_results(tmp_path, "example", [{"case": "c", "ms": 3.0}], "# New", PROV)
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == old  # no temporary file left either
    assert not any(name.startswith(".") for name in os.listdir(tmp_path))
