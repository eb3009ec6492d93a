"""Progress without a terminal: one log line per tenth of the work, no carriage-return updates."""

from __future__ import annotations

import logging

import pytest
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


class _Clock:
    """A clock the test moves by hand (seconds)."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_the_log_lines_eta_starts_after_the_first_step(caplog, monkeypatch):
    clock = _Clock()
    monkeypatch.setattr("lagfluid.progress.time.perf_counter", clock)
    bar = LogProgress(100, desc="mps", unit="step")
    with caplog.at_level(logging.INFO, logger="lagfluid.progress"):
        clock.now += 16.0  # the first step compiles the kernels
        bar.update(1)
        bar.restart_clock()
        for _ in range(19):
            clock.now += 0.5  # every later step: 0.5 s
            bar.update(1)
    line = caplog.records[-1].getMessage()
    # 20 of 100 done at 2 steps/s: 40 s left (with the first step counted: 80 steps / (20 / 25.5 s) = 102 s);
    # elapsed is still the whole 25.5 s
    assert line == "mps: 20/100 step (20 %), 2 step/s, 26 s elapsed, ~40 s left"


def test_the_bars_eta_starts_after_the_first_step(monkeypatch):
    import io

    from lagfluid.progress import ProgressBar

    clock = _Clock()
    monkeypatch.setattr("sys.stderr.isatty", lambda: True)
    bar = progress_bar(100, enabled=True, desc="mps", unit="step")
    assert isinstance(bar, ProgressBar)
    bar.close()
    bar = ProgressBar(total=100, file=io.StringIO(), mininterval=0)
    bar._time = clock  # tqdm's own clock
    bar.reset(100)
    clock.now += 16.0
    bar.update(1)
    bar.restart_clock()
    for _ in range(19):
        clock.now += 0.5
        bar.update(1)
    meter = bar.format_dict
    rate = meter["rate"] or (meter["n"] - meter["initial"]) / meter["elapsed"]
    assert meter["n"] == 20 and rate == pytest.approx(2.0)
    assert (meter["total"] - meter["n"]) / rate == pytest.approx(40.0)


def test_a_rollout_restarts_the_eta_clock_after_its_first_step(monkeypatch):
    from lagfluid import rollout as rollout_module
    from lagfluid.scenes import build_scene

    events: list[str] = []

    class Recorder:
        def update(self, n=1):
            events.append("update")

        def restart_clock(self):
            events.append("restart")

        def set_postfix(self, **values):
            pass

        def close(self):
            pass

    class Still:
        """A simulator whose fluid never moves."""

        name, dt, history_length, max_courant, parameters, last_fields = "still", None, 0, None, 0, None
        last_info, last_timings = {}, {}

        def reset(self, state, history=()):
            pass

        def step(self, state, *, record=False):
            nf = state.n_fluid
            return state.advanced_fluid(state.pos[:nf], state.vel[:nf], state.params.dt)

    monkeypatch.setattr(rollout_module, "progress_bar", lambda *args, **kwargs: Recorder())
    state = build_scene("dam", fluid_size=[2, 2, 2], tank_size=[5, 5])
    rollout_module.rollout(Still(), state, 3)
    assert events == ["update", "restart", "update", "update"]


def test_a_cold_kernel_cache_is_announced_once_before_compiling(tmp_path, monkeypatch, caplog):
    from lagfluid.neighbors import pair_kernels

    for name in ("cold_kernels_probe", "cold_kernels_probe_2"):
        (tmp_path / f"{name}.py").write_text(
            "from numba import njit\n\n\n@njit(cache=True)\ndef twice(x):\n    return 2 * x\n"
        )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(pair_kernels, "_announced", [])
    with caplog.at_level(logging.INFO, logger="lagfluid.neighbors.pair_kernels"):
        kernels = pair_kernels.load("cold_kernels_probe")  # nothing compiled yet: said before the first call
    assert [r.getMessage() for r in caplog.records] == [
        f"compiling the CPU kernels once, ~{pair_kernels.COMPILE_SECONDS} s; cached afterwards "
        f"({tmp_path / '__pycache__'})"
    ]
    assert pair_kernels.uncached_kernels(kernels) == str(tmp_path / "__pycache__")
    assert kernels.twice(21) == 42  # compiled and cached on disk
    assert pair_kernels.uncached_kernels(kernels) is None  # the next run loads it: nothing to announce
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="lagfluid.neighbors.pair_kernels"):
        second = pair_kernels.load("cold_kernels_probe_2")  # cold too: announced once per process at most
    assert pair_kernels.uncached_kernels(second) is not None and not caplog.records
