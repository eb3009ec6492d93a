"""Outputs are never lost: sweeps write one folder per job, reruns replace outputs only when they end."""

import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import pytest
from hydra import compose, initialize_config_dir

from lagfluid.errors import LagfluidError
from lagfluid.run import CONF_DIR
from lagfluid.tasks.config import job_folder
from lagfluid.tasks.outputs import part_path
from lagfluid.tasks.simulate import simulate

REPO = Path(__file__).resolve().parents[1]


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def _dt_of(folder: Path) -> float:
    with h5py.File(folder / "rollout.h5", "r") as f:
        dt_file = float(f["00000"].attrs["dt"])
    assert json.loads((folder / "metrics.json").read_text())["dt"] == dt_file  # the two files of one job
    return dt_file


def test_a_two_job_sweep_writes_one_folder_per_job(tmp_path):
    out = tmp_path / "out"
    args = ["-m", "model=mps", "scene=dam_small", "steps=6", "dt=0.001,0.002", f"out_dir={out}"]
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "lagfluid.run",
            *args,
            "threads=1",
            "progress=false",
            f"hydra.sweep.dir={tmp_path}/s",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        cwd=REPO,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    jobs = sorted(p.name for p in out.iterdir())
    assert jobs == [
        "0_dt=0.001,model=mps,scene=dam_small,steps=6",
        "1_dt=0.002,model=mps,scene=dam_small,steps=6",
    ]
    assert [_dt_of(out / job) for job in jobs] == [0.001, 0.002]
    assert not list(out.glob("*/*.part.*"))


def test_job_folders_are_file_names():
    assert job_folder(3, "") == "3"
    assert job_folder(0, "scene.path=/data/a b.npz,dt=0.001") == "0_scene.path=_data_a_b.npz,dt=0.001"
    assert len(job_folder(12, "x=" + "9" * 500)) <= 3 + 120


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("dtype=float16", "unknown dtype 'float16'"),
        ("device=cuda:7", "device=cuda:7"),
        ("model.weights=/nonexistent", "not found"),
    ],
)
def test_a_rerun_that_fails_before_its_first_step_keeps_the_last_outputs(tmp_path, override, message):
    if override.startswith("device") and __import__("torch").cuda.is_available():
        pytest.skip("a CUDA machine has a device; the check is for one without")
    first = simulate(_compose("experiment=debug", "steps=4", f"out_dir={tmp_path}"))
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    assert {"rollout.h5", "metrics.json", "preview.png"} <= set(before)
    model = ["model=fgn"] if override.startswith("model.") else []
    with pytest.raises(LagfluidError, match=message):
        simulate(_compose("experiment=debug", *model, "steps=4", override, f"out_dir={tmp_path}"))
    after = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    assert after == before and first["complete"]


def test_an_incomplete_rerun_keeps_the_last_complete_run_in_previous(tmp_path):
    simulate(_compose("experiment=debug", "steps=4", f"out_dir={tmp_path}"))
    good = (tmp_path / "rollout.h5").read_bytes()
    with pytest.raises(LagfluidError, match="Courant"):  # 50 ms steps: the guard stops it
        simulate(_compose("experiment=debug", "dt=0.05", "steps=10", f"out_dir={tmp_path}"))
    assert (tmp_path / "previous" / "rollout.h5").read_bytes() == good
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["complete"] is False and saved["dt"] == 0.05  # the new run's files, all of them
    with h5py.File(tmp_path / "rollout.h5", "r") as f:
        assert float(f["00000"].attrs["dt"]) == 0.05
    assert not part_path(tmp_path / "rollout.h5").exists()
    simulate(_compose("experiment=debug", "steps=4", f"out_dir={tmp_path}"))  # complete again
    assert not (tmp_path / "previous").exists()


def test_a_failing_preview_costs_only_the_figure(tmp_path, monkeypatch, caplog):
    import lagfluid.viz

    simulate(_compose("experiment=debug", "steps=2", f"out_dir={tmp_path}"))

    def broken(*args, **kwargs):
        raise RuntimeError("no display")

    monkeypatch.setattr(lagfluid.viz, "preview", broken)
    metrics = simulate(_compose("experiment=debug", "steps=4", f"out_dir={tmp_path}"))
    assert metrics["complete"] and json.loads((tmp_path / "metrics.json").read_text())["steps"] == 4
    with h5py.File(tmp_path / "rollout.h5", "r") as f:
        assert f["00000/position"].shape[0] == 5  # this run's rollout, published
    assert not (tmp_path / "preview.png").exists()  # the old run's picture went with the old run
    assert "preview.png not written: RuntimeError: no display" in caplog.text


def test_part_files_of_a_crashed_run_are_never_published(tmp_path):
    tmp_path.mkdir(exist_ok=True)
    stale = part_path(tmp_path / "preview.png")
    stale.write_bytes(b"left by a crash")
    simulate(_compose("experiment=debug", "steps=2", f"out_dir={tmp_path}"))
    assert (tmp_path / "preview.png").read_bytes() != b"left by a crash" and not stale.exists()


def test_a_simulator_failing_in_reset_keeps_the_last_outputs(tmp_path, monkeypatch):
    from lagfluid import registry
    from lagfluid.models.mps_simulator import build_mps

    simulate(_compose("experiment=debug", "steps=2", f"out_dir={tmp_path}"))
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}

    def refusing(cfg):
        sim = build_mps(cfg)

        def reset(state, history=()):
            raise LagfluidError("this scene is not for me")

        sim.reset = reset
        return sim

    monkeypatch.setitem(registry._REGISTERED, "refusing", refusing)
    with pytest.raises(LagfluidError, match="not for me"):
        simulate(_compose("experiment=debug", "model.name=refusing", "steps=2", f"out_dir={tmp_path}"))
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before
    assert not (tmp_path / "previous").exists()


@pytest.mark.parametrize(
    ("task", "overrides", "folder"),
    [
        ("simulate", ["dt=0.001", "threads=1"], "1_dt=0.001"),
        ("train", ["stage=collision", "threads=1"], ""),  # the trainables of one model share a folder
        ("train", ["stage=collision", "train.lr_start=0.01"], "train.lr_start=0.01"),
    ],
)
def test_the_job_folder_rule(tmp_path, task, overrides, folder):
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode
    from omegaconf import open_dict

    from lagfluid.tasks.config import multirun_out_dir

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            config_name="config",
            overrides=[f"task={task}", f"out_dir={tmp_path}", *overrides],
            return_hydra_config=True,
        )
    with open_dict(cfg):
        cfg.hydra.mode = RunMode.MULTIRUN
        cfg.hydra.job.num = 1
        cfg.hydra.job.override_dirname = ",".join(o for o in overrides if not o.startswith("threads"))
        cfg.hydra.overrides.task = overrides
    HydraConfig.instance().set_config(cfg)
    try:
        assert multirun_out_dir(cfg) == (tmp_path / folder if folder else tmp_path)
    finally:
        HydraConfig.instance().cfg = None


def test_metrics_of_a_run_stopped_before_its_first_step_are_strict_json(tmp_path):
    # the guard refuses step 1: no step time exists; NaN would make metrics.json unreadable to strict parsers
    out = tmp_path / "stopped"
    cfg = _compose(
        "model=mps", "scene=dam_small", "steps=3", "solver.guard.max_courant=1e-12", f"out_dir={out}"
    )
    with pytest.raises(LagfluidError, match="Courant number"):  # the CLI's one line, exit 1
        simulate(cfg)

    def refuse(name):
        raise AssertionError(f"metrics.json holds {name}")

    metrics = json.loads((out / "metrics.json").read_text(), parse_constant=refuse)
    assert metrics["complete"] is False and metrics["steps"] == 0
    assert metrics["time_per_step_median_s"] is None
