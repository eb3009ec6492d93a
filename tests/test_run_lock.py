"""Runs lock what they write: a second run is refused by name, touching nothing; a killed run's lock frees."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from lagfluid.run import CONF_DIR
from lagfluid.tasks.locks import OutputsInUse, hold_outputs, lock_path
from lagfluid.tasks.outputs import part_path, publish
from lagfluid.tasks.simulate import simulate

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def _compose(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=["experiment=debug", "threads=1", *overrides])


def _files(folder: Path) -> dict[str, tuple[bytes, int]]:
    """Every file under ``folder`` (``.hydra/`` too) with its bytes and modification time."""
    return {
        str(p.relative_to(folder)): (p.read_bytes(), p.stat().st_mtime_ns)
        for p in folder.rglob("*")
        if p.is_file()
    }


class _Holder:
    """Another process that holds ``hold_outputs(folder, task, units)`` until :meth:`release` (or a kill)."""

    def __init__(self, folder: Path, task: str = "simulate", units: tuple[str, ...] = ("",)) -> None:
        code = (
            "import sys; from pathlib import Path; from lagfluid.tasks.locks import hold_outputs\n"
            f"with hold_outputs(Path({str(folder)!r}), {task!r}, {units!r}):\n"
            "    print('held', flush=True); sys.stdin.read()\n"
        )
        self.proc = subprocess.Popen(
            [sys.executable, "-c", code, "task=" + task],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=REPO,
            env=ENV,
        )
        assert self.proc.stdout.readline().strip() == "held"

    def release(self) -> None:
        self.proc.stdin.close()
        assert self.proc.wait(timeout=60) == 0

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=60)
        self.proc.stdin.close()


def test_a_second_simulate_into_a_held_out_dir_is_refused_by_name_and_touches_nothing(tmp_path):
    out = tmp_path / "run"
    simulate(_compose("steps=2", f"out_dir={out}"))  # a complete earlier run
    (out / ".hydra").mkdir()
    (out / ".hydra" / "config.yaml").write_text("the holder's config, as Hydra wrote it\n")
    holder = _Holder(out)
    before = _files(out)
    assert {"rollout.h5", "metrics.json", "preview.png", ".lagfluid.lock"} <= set(before)
    command = [sys.executable, "-m", "lagfluid.run", "experiment=debug", "steps=2", "threads=1"]
    command.append(f"out_dir={out}")
    try:
        # the command line: Hydra's callback stops it before Hydra writes .hydra/ or the log there
        done = subprocess.run(command, cwd=REPO, env=ENV, capture_output=True, text=True, timeout=300)
        assert done.returncode == 1
        line = f"lagfluid: out_dir {out} is in use by another run: pid {holder.proc.pid} on "
        assert done.stderr.startswith(line) and done.stderr.count("\n") == 1, done.stderr
        assert "(task=simulate: task=simulate), since " in done.stderr
        assert "wait for it to end or choose another out_dir" in done.stderr
        # the task's own lock: a programmatic run (no Hydra callback) is refused before it touches a file
        with pytest.raises(OutputsInUse, match=f"pid {holder.proc.pid} on .*task=simulate"):
            simulate(_compose("steps=2", f"out_dir={out}"))
        assert _files(out) == before
    finally:
        holder.release()
    assert not lock_path(out).exists()  # released and removed
    assert simulate(_compose("steps=3", f"out_dir={out}"))["complete"]  # free again


def test_a_lock_left_by_a_killed_run_is_taken_over_and_logged(tmp_path, caplog):
    out = tmp_path / "run"
    holder = _Holder(out)
    holder.kill()  # kill -9: its lock file stays, its lock does not
    assert str(holder.proc.pid) in lock_path(out).read_text()
    with caplog.at_level(logging.WARNING, logger="lagfluid.tasks.locks"):
        assert simulate(_compose("steps=2", f"out_dir={out}"))["complete"]
    [record] = [r for r in caplog.records if r.name == "lagfluid.tasks.locks"]
    assert f"took over the lock of pid {holder.proc.pid} on " in record.getMessage()
    assert "which ended without releasing it" in record.getMessage()
    assert not lock_path(out).exists()


def test_units_of_one_folder_lock_apart_and_a_refusal_keeps_none(tmp_path):
    holder = _Holder(tmp_path, "train", ("collision",))
    try:
        with hold_outputs(tmp_path, "train", ["advection"]):  # another trainable of the folder: side by side
            assert lock_path(tmp_path, "advection").is_file()
        with pytest.raises(OutputsInUse, match=rf"out_dir {tmp_path} \(collision\) is in use .*task=train"):
            with hold_outputs(tmp_path, "train", ["advection", "collision", "pressure"]):
                pytest.fail("not refused")
        assert not lock_path(tmp_path, "advection").exists()  # what the refused run took, it gave back
        assert not lock_path(tmp_path, "pressure").exists()
    finally:
        holder.release()


def test_every_task_that_writes_takes_its_lock(tmp_path):
    """export, evaluate, train and generate are refused while another run holds what they would write."""
    from lagfluid.tasks.evaluate import evaluate
    from lagfluid.tasks.export import export_task
    from lagfluid.tasks.generate import generate
    from lagfluid.tasks.train import train

    run, train_dir, data_dir = tmp_path / "run", tmp_path / "train", tmp_path / "data"
    simulate(_compose("steps=2", f"out_dir={run}"))
    cases = [
        (run, "simulate", ("",), lambda: export_task(_compose("task=export", f"run={run}", "format=gif"))),
        (run, "simulate", ("",), lambda: evaluate(_compose("task=evaluate", "steps=2", f"out_dir={run}"))),
        (
            train_dir,
            "train",
            ("collision",),
            lambda: train(
                _compose("task=train", "model=fgn", "stage=collision", f"out_dir={tmp_path / 'train'}")
            ),
        ),
        (
            data_dir / "scenes",
            "generate",
            ("scene_00001",),
            lambda: generate(
                _compose(
                    "task=generate", "data=tiny", "data.scene_index=1", f"data.out_dir={tmp_path / 'data'}"
                )
            ),
        ),
    ]
    for folder, task, units, run_task in cases:
        holder = _Holder(folder, task, units)
        try:
            before = _files(folder)
            with pytest.raises(OutputsInUse, match=f"pid {holder.proc.pid} on "):
                run_task()
            assert _files(folder) == before, task
        finally:
            holder.release()


def test_an_evaluation_waiting_for_a_held_reference_says_for_what_and_whom(tmp_path, caplog):
    from lagfluid.tasks.evaluate.options import EvaluateOptions
    from lagfluid.tasks.evaluate.reference import key_hash, reference_key, reference_rollout

    cfg = _compose("model=mps", "steps=2", f"evaluate.reference_dir={tmp_path}")
    folder = tmp_path / f"{cfg.scene.name}-{key_hash(reference_key(cfg))}"
    holder = _Holder(folder, "evaluate", ("reference",))  # another evaluation computing this reference
    waiting = f"waiting for the MPS reference in {folder}: pid {holder.proc.pid} on "
    logged = threading.Event()

    def release_once_logged() -> None:  # the wait is logged before it blocks; then the holder lets go
        for _ in range(2000):  # at most ~20 s: without the line the test fails, it does not hang
            if any(r.getMessage().startswith(waiting) for r in caplog.records):
                logged.set()
                break
            threading.Event().wait(0.01)
        holder.release()

    releaser = threading.Thread(target=release_once_logged, daemon=True)
    with caplog.at_level(logging.INFO, logger="lagfluid"):
        releaser.start()
        path, reused, _ = reference_rollout(cfg, EvaluateOptions.from_config(cfg.evaluate))
    releaser.join(timeout=60)
    assert logged.is_set() and path == folder / "rollout.h5" and not reused
    [line] = [r.getMessage() for r in caplog.records if r.getMessage().startswith(waiting)]
    assert "(task=evaluate: task=evaluate), since " in line and line.endswith("holds its lock")
    assert not lock_path(folder, "reference").exists()


def test_a_run_that_wrote_no_rollout_leaves_the_earlier_files_alone(tmp_path, caplog):
    names = ("rollout.h5", "metrics.json", "preview.png")
    for name in names:  # an earlier run's files (incomplete or unreadable: no previous/ for them)
        (tmp_path / name).write_bytes(b"earlier " + name.encode())
    part_path(tmp_path / "metrics.json").write_text("{}")  # this run got as far as its metrics, no rollout
    publish(tmp_path, names, complete=False)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == {
        name: b"earlier " + name.encode() for name in names
    }
    assert "this run wrote no rollout.h5" in caplog.text
