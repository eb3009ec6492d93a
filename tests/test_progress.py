"""Progress without a terminal: one log line per tenth of the work, no carriage-return updates."""

from __future__ import annotations

import logging

from tqdm import tqdm

from lagfluid.progress import LogProgress, progress_bar


def test_without_a_terminal_progress_is_a_log_line_every_tenth(caplog, monkeypatch):
    monkeypatch.setattr("sys.stderr.isatty", lambda: False)
    bar = progress_bar(200, enabled=True, desc="mps", unit="step")
    assert isinstance(bar, LogProgress)
    with caplog.at_level(logging.INFO, logger="lagfluid.progress"):
        for k in range(200):
            bar.update(1)
            if k == 150:
                bar.set_postfix(loss="0.5")
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 10 and all("\r" not in line for line in lines)
    assert lines[0].startswith("mps: 20/200 step (10 %)")
    assert lines[-1].startswith("mps: 200/200 step (100 %)")
    assert lines[-1].endswith("loss=0.5")


def test_a_resumed_loop_counts_from_where_it_stopped(caplog):
    with caplog.at_level(logging.INFO, logger="lagfluid.progress"):
        bar = LogProgress(100, initial=55, desc="train pressure")
        for _ in range(45):
            bar.update(1)
    lines = [r.getMessage() for r in caplog.records]
    counts = [line.split(" (")[0] for line in lines]
    assert counts == [f"train pressure: {n}/100 it" for n in range(60, 101, 10)]


def test_on_a_terminal_or_disabled_it_is_tqdm(monkeypatch):
    monkeypatch.setattr("sys.stderr.isatty", lambda: True)
    assert isinstance(progress_bar(10, enabled=True), tqdm)
    monkeypatch.setattr("sys.stderr.isatty", lambda: False)
    quiet = progress_bar(10, enabled=False)
    assert isinstance(quiet, tqdm) and quiet.disable
