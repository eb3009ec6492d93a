"""``task=simulate resume=true``: a killed or stopped run continues to the uninterrupted run's very file."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from hydra import compose, initialize_config_dir

import lagfluid.tasks.simulate as simulate_module
from lagfluid.errors import RolloutError
from lagfluid.run import CONF_DIR
from lagfluid.tasks.simulate import simulate
from lagfluid.tasks.simulate_resume import CHECKPOINT

REPO = Path(__file__).resolve().parents[1]
FRAME_ARRAYS = ("time", "position", "velocity", "pressure")


def _compose(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        overrides = ["experiment=debug", "checkpoint_every_s=0", *overrides]
        return compose(config_name="config", overrides=overrides)


def _assert_same_run(a: Path, b: Path) -> None:
    with h5py.File(a / "rollout.h5") as fa, h5py.File(b / "rollout.h5") as fb:
        ga, gb = fa["00000"], fb["00000"]
        assert bool(gb.attrs["complete"]) and gb.attrs["stop_reason"] == ""
        for name in FRAME_ARRAYS:
            np.testing.assert_array_equal(ga[name][()], gb[name][()], err_msg=name)
    ma, mb = (json.loads((d / "metrics.json").read_text()) for d in (a, b))
    assert mb["complete"] and mb["steps"] == ma["steps"]
    assert mb["density_error"] == ma["density_error"]
    assert mb["velocity_divergence_per_s"] == ma["velocity_divergence_per_s"]
    assert not (b / CHECKPOINT).exists()  # a completed run leaves no checkpoint behind


def _stopped_at(monkeypatch, step: int, error: type[BaseException]) -> None:
    """Make the run's simulator raise ``error`` when asked to step from ``step`` (a Ctrl-C, a crash)."""
    build = simulate_module.build_simulator

    def stopping(cfg):
        simulator = build(cfg)
        real = simulator.step

        def step_or_stop(state, record=False):
            if state.step == step:
                raise error("stopped for the test")
            return real(state, record=record)

        simulator.step = step_or_stop
        return simulator

    monkeypatch.setattr(simulate_module, "build_simulator", stopping)


@pytest.mark.parametrize(
    "overrides",
    [
        ["model=mps", "write_every=3", "dtype=float64"],  # frames on every 3rd step and the last, as one run
        ["model=fgn"],
        ["model=gns"],  # the integrated velocity history (rollout_memory) carries over bit for bit
        ["model=cconv"],
    ],
    ids=lambda o: " ".join(o),
)
def test_a_stopped_run_resumes_to_the_uninterrupted_run(tmp_path, monkeypatch, overrides):
    steps = ["steps=8"]
    simulate(_compose(*overrides, *steps, f"out_dir={tmp_path / 'whole'}"))
    with monkeypatch.context() as patch:
        _stopped_at(patch, 5, KeyboardInterrupt)
        with pytest.raises(KeyboardInterrupt):
            simulate(_compose(*overrides, *steps, f"out_dir={tmp_path / 'stopped'}"))
    stopped = json.loads((tmp_path / "stopped" / "metrics.json").read_text())
    assert not stopped["complete"] and stopped["steps"] == 5
    simulate(_compose(*overrides, *steps, "resume=true", f"out_dir={tmp_path / 'stopped'}"))
    _assert_same_run(tmp_path / "whole", tmp_path / "stopped")


def test_resume_refuses_other_settings_and_a_folder_without_a_checkpoint(tmp_path, monkeypatch):
    out = f"out_dir={tmp_path}"
    with pytest.raises(RolloutError, match=r"no resume\.pt"):
        simulate(_compose("steps=6", "resume=true", out))
    with monkeypatch.context() as patch:
        _stopped_at(patch, 4, KeyboardInterrupt)
        with pytest.raises(KeyboardInterrupt):
            simulate(_compose("steps=6", out))
    with pytest.raises(RolloutError, match=r"other settings \(dt: None -> 0.001"):
        simulate(_compose("steps=6", "dt=0.001", "resume=true", out))
    # frames on other steps would not continue the file: write_every is a setting of the run, not free
    with pytest.raises(RolloutError, match=r"other settings \(write_every: 1 -> 2\); repeat its command"):
        simulate(_compose("steps=6", "write_every=2", "resume=true", out))
    with pytest.raises(RolloutError, match="at step 4, past steps=3"):
        simulate(_compose("steps=3", "resume=true", out))
    # the refusals touched nothing: the stopped run still resumes, and may run longer than asked first
    simulate(_compose("steps=8", "resume=true", out))
    assert json.loads((tmp_path / "metrics.json").read_text())["steps"] == 8
    with pytest.raises(RolloutError, match="nothing to resume"):
        simulate(_compose("steps=8", "resume=true", out))


def test_kill_9_then_resume_gives_the_uninterrupted_run(tmp_path):
    """A real SIGKILL: the part file may hold frames past the last checkpoint; they are dropped and redone."""
    steps, env = "steps=15", {**os.environ, "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "lagfluid.run", "experiment=debug", steps, "checkpoint_every_s=0"]
    command.append("threads=1")
    killed = tmp_path / "killed"
    proc = subprocess.Popen([*command, f"out_dir={killed}"], cwd=REPO, env=env, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not (killed / CHECKPOINT).exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.2)  # a few more steps: frames past the checkpoint
    proc.send_signal(signal.SIGKILL)
    assert proc.wait() == -signal.SIGKILL, "the run ended before it could be killed"
    assert (killed / "rollout.part.h5.part").exists() and not (killed / "rollout.h5").exists()
    subprocess.run([*command, "resume=true", f"out_dir={killed}"], cwd=REPO, env=env, check=True)
    subprocess.run([*command, f"out_dir={tmp_path / 'whole'}"], cwd=REPO, env=env, check=True)
    _assert_same_run(tmp_path / "whole", killed)


def _compose_late_checkpoint(*overrides: str):
    """A run whose first periodic checkpoint would come after an hour: only a stop saves one."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        overrides = ["experiment=debug", "checkpoint_every_s=3600", *overrides]
        return compose(config_name="config", overrides=overrides)


@pytest.mark.parametrize(
    "overrides",
    [["model=mps", "write_every=3"], ["model=gns"]],  # GNS: its velocity history is saved at the stop too
    ids=lambda o: " ".join(o),
)
def test_ctrl_c_before_the_first_periodic_checkpoint_saves_one_and_resumes(tmp_path, monkeypatch, overrides):
    steps, stopped = ["steps=8"], tmp_path / "stopped"
    simulate(_compose_late_checkpoint(*overrides, *steps, f"out_dir={tmp_path / 'whole'}"))
    with monkeypatch.context() as patch:
        _stopped_at(patch, 5, KeyboardInterrupt)
        with pytest.raises(KeyboardInterrupt):
            simulate(_compose_late_checkpoint(*overrides, *steps, f"out_dir={stopped}"))
    assert (stopped / CHECKPOINT).is_file()  # saved at the stop: no periodic save came before it
    simulate(_compose_late_checkpoint(*overrides, *steps, "resume=true", f"out_dir={stopped}"))
    _assert_same_run(tmp_path / "whole", stopped)


def _stored_frames(part: Path) -> int:
    """Frames in a running writer's part file (0 while it cannot be read)."""
    try:
        with h5py.File(part, "r", locking=False) as f:
            return int(f["00000/time"].shape[0])
    except (OSError, KeyError):
        return 0


def test_sigint_after_the_first_frames_then_resume_gives_the_uninterrupted_run(interruptible, tmp_path):
    """A real Ctrl-C (SIGINT) to a run at the default checkpoint_every_s: it saves a checkpoint, stopping."""
    command = [sys.executable, "-m", "lagfluid.run", "experiment=debug", "steps=15", "threads=1"]
    stopped = tmp_path / "stopped"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        [*command, f"out_dir={stopped}"], cwd=REPO, env=env, stderr=subprocess.DEVNULL, **interruptible
    )
    part = stopped / "rollout.part.h5.part"
    deadline = time.monotonic() + 300
    while _stored_frames(part) < 3 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=300) != 0, "the run ended before it could be interrupted"
    assert (stopped / CHECKPOINT).is_file()
    metrics = json.loads((stopped / "metrics.json").read_text())
    assert not metrics["complete"] and 2 <= metrics["steps"] < 15
    simulate(_compose_late_checkpoint("steps=15", "threads=1", "resume=true", f"out_dir={stopped}"))
    simulate(_compose_late_checkpoint("steps=15", "threads=1", f"out_dir={tmp_path / 'whole'}"))
    _assert_same_run(tmp_path / "whole", stopped)
