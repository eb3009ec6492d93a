"""``python -m lagfluid.retrain``: one multirun retrains and exports every shipped learned model."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from baselines.cconv.simulator import SHIPPED as CCONV_SHIPPED
from baselines.gns.simulator import SHIPPED as GNS_SHIPPED
from lagfluid.models.checkpoint import read_checkpoint
from lagfluid.models.fgn.networks import owned_stages
from lagfluid.models.fgn.simulator import WEIGHTS_ROOT
from lagfluid.registry import get_trainables
from lagfluid.retrain import retrain_arguments, retrain_experiments
from lagfluid.run import CONF_DIR
from lagfluid.tasks.multirun_timer import FILE_NAME, MultirunTimer

REPO = CONF_DIR.parents[1]  # lagfluid/conf -> the repository root
# where Table 5's recipe (train=table5) starts the ablation's pressure net from
MLP_ROUND0 = REPO / "lagfluid" / "weights" / "fgn_mlp" / "round0" / "pressure.pt"


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def _shipped_dirs(cfg) -> set[Path]:
    """Where ``model=<name>`` (no ``model.weights``) loads the networks this model trains from."""
    if cfg.model.name == "gns":
        return {GNS_SHIPPED}
    if cfg.model.name == "cconv":
        return {CCONV_SHIPPED}
    return {WEIGHTS_ROOT / str(cfg.model.shipped[stage]) for stage in owned_stages(cfg.model)}


def test_every_shipped_learned_model_has_a_retrain_job():
    assert retrain_experiments() == [
        "retrain_cconv",
        "retrain_fgn",
        "retrain_fgn_gcn",
        "retrain_fgn_mlp",
        "retrain_fgn_sage",
        "retrain_fgn_trained_here",
        "retrain_gns",
    ]


@pytest.mark.parametrize("experiment", retrain_experiments())
def test_a_retrain_job_trains_every_owned_network_and_exports_where_the_model_loads_from(experiment):
    cfg = _compose(f"experiment={experiment}")
    assert cfg.task == "train" and cfg.stage == "all"
    assert {(REPO / str(cfg.export_to)).resolve()} == _shipped_dirs(cfg)
    trainables = get_trainables(str(cfg.model.name), cfg)
    if cfg.model.name.startswith("fgn"):
        assert list(trainables) == list(owned_stages(cfg.model))


def test_retrain_arguments_sweep_every_job_one_at_a_time_unless_a_subset_is_named():
    args = retrain_arguments(["data=paper"])
    assert args[0] == "-m" and f"experiment={','.join(retrain_experiments())}" in args
    assert "hydra.launcher.n_jobs=1" in args and args[-1] == "data=paper"
    two = "experiment=retrain_fgn_gcn,retrain_fgn_sage"
    assert [a for a in retrain_arguments([two]) if a.startswith("experiment=")] == [two]


def test_multirun_timer_writes_the_total_wall_time_into_the_sweep_dir(tmp_path):
    config = OmegaConf.create(
        {
            "hydra": {
                "sweep": {"dir": str(tmp_path / "sweep")},
                "sweeper": {"params": None},
                "overrides": {"task": ["experiment=a,b", "threads=2"]},
            }
        }
    )
    timer = MultirunTimer()
    timer.on_multirun_end(config)  # never started: nothing to report
    assert not (tmp_path / "sweep" / FILE_NAME).exists()
    timer.on_multirun_start(config)
    timer.on_multirun_end(config)
    record = json.loads((tmp_path / "sweep" / FILE_NAME).read_text())
    assert record["wall_s"] >= 0 and record["overrides"] == ["experiment=a,b", "threads=2"]
    assert record["started"] <= record["finished"]


def test_the_retrain_command_trains_exports_and_times_a_sweep(tmp_path):
    data = tmp_path / "data"
    gen = _compose("task=generate", "scene=random", "data=tiny", f"data.out_dir={data}", "progress=false")
    from lagfluid.tasks.generate import generate

    generate(gen)
    sweep, exported = tmp_path / "sweep", tmp_path / "weights"
    cmd = [
        sys.executable,
        "-m",
        "lagfluid.retrain",
        "experiment=retrain_fgn_mlp",
        "data=tiny",
        f"data.out_dir={data}",
        f"out_dir={tmp_path / 'runs'}",
        f"export_to={exported}",
        f"hydra.sweep.dir={sweep}",
        "train.iterations.advection=2",
        "train.batch_size.advection=1",
        "train.stat_samples=2",
        "train.onpolicy.iterations=2",
        "train.onpolicy.jobs=1",
        "threads=1",
    ]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert sorted(p.name for p in exported.glob("*.pt")) == ["advection.pt", "pressure.pt"]
    assert read_checkpoint(exported / "advection.pt")["step"] == 2
    # Table 5's recipe: the pressure net starts as round0's file (0 iterations), then two on-policy rounds on
    # the model's own rollouts fine-tune it; round 2's net ships, with the record of its own training
    (run,) = [p for p in (tmp_path / "runs").iterdir() if p.is_dir()]
    start, round0 = read_checkpoint(run / "pressure.pt"), read_checkpoint(MLP_ROUND0)
    assert start["step"] == 0
    for key, value in round0["state_dict"].items():
        assert torch.equal(start["state_dict"][key], value), key
    shipped = read_checkpoint(exported / "pressure.pt")
    assert shipped["step"] == 2 and shipped["meta"]["profile"] == "table5"
    assert Path(shipped["meta"]["data_dir"]) == run / "onpolicy" / "round2" / "data"
    assert any(not torch.equal(shipped["state_dict"][k], v) for k, v in round0["state_dict"].items())
    assert json.loads((sweep / FILE_NAME).read_text())["wall_s"] > 0


def test_retrain_fgn_keeps_the_authors_pressure_net_and_trains_the_other_two(tmp_path, monkeypatch):
    # the shipped recipe: advection and collision trained, the pressure net their published one, 0 iterations
    from lagfluid.models.fgn.simulator import AUTHORS_WEIGHTS
    from lagfluid.tasks.generate import generate
    from lagfluid.tasks.train import train

    data = tmp_path / "data"
    generate(_compose("task=generate", "scene=random", "data=tiny", f"data.out_dir={data}", "progress=false"))
    monkeypatch.chdir(REPO)  # the experiment's init_from is relative to the repository root, as export_to
    exported = tmp_path / "weights"
    cfg = _compose(
        "experiment=retrain_fgn", "data=tiny", f"data.out_dir={data}", f"out_dir={tmp_path / 'run'}",
        f"export_to={exported}", "train.iterations.advection=2", "train.iterations.collision=2",
        "train.stat_samples=2", "threads=1",
    )  # fmt: skip
    train(cfg)
    theirs, shipped = (
        read_checkpoint(AUTHORS_WEIGHTS / "pressure.pt"),
        read_checkpoint(exported / "pressure.pt"),
    )
    assert shipped["step"] == 0 and shipped["options"] == theirs["options"]
    assert shipped["meta"] == theirs["meta"]  # their file as it is, not this run's record of 0 iterations
    for key, value in theirs["state_dict"].items():
        assert torch.equal(shipped["state_dict"][key], value), key
    for name in ("advection", "collision"):
        ckpt = read_checkpoint(exported / f"{name}.pt")
        assert ckpt["step"] == 2 and "init_from" not in json.loads(ckpt["meta"]["identity"])
