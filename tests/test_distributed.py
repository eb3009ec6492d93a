"""torchrun data-parallel training on the CPU (gloo): one process's loss curve with the same global batch."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from lagfluid.models.checkpoint import read_checkpoint
from lagfluid.run import CONF_DIR
from lagfluid.tasks.generate import generate

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny_ddp")
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            config_name="config",
            overrides=["task=generate", "scene=random", "data=tiny", f"data.out_dir={out}", "progress=false"],
        )
    generate(cfg)
    return out


def _args(data: Path, out: Path, stage: str, iterations: int = 6, batch: int = 4) -> list[str]:
    return [
        "task=train",
        "model=fgn",
        f"stage={stage}",
        "data=tiny",
        f"data.out_dir={data}",
        f"out_dir={out}",
        "progress=false",
        "threads=1",
        f"train.iterations.{stage}={iterations}",
        f"train.batch_size.{stage}={batch}",  # the global batch: two ranks share it
        "train.log_every=1",
        "train.valid_every=1000",
        "train.checkpoint_every=2",
        "train.stat_samples=8",
    ]


def _train(data: Path, out: Path, stage: str, processes: int, batch: int = 4) -> Path:
    head = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", str(processes)]
    head += ["--master_port", str(29500 + os.getpid() % 1000), "-m", "lagfluid.run"]
    command = head if processes > 1 else [sys.executable, "-m", "lagfluid.run"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run(
        [*command, *_args(data, out, stage, batch=batch)],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return out


def _losses(out: Path, stage: str) -> list[float]:
    with (out / f"{stage}_loss.csv").open() as f:
        return [float(r["train_loss"]) for r in csv.DictReader(f)]


def _assert_same_weights(a: Path, b: Path, stage: str) -> None:
    first, second = (read_checkpoint(out / f"{stage}.pt") for out in (a, b))
    assert first["step"] == second["step"] == 6
    for key, value in first["state_dict"].items():
        torch.testing.assert_close(second["state_dict"][key], value, rtol=1e-5, atol=1e-6, msg=key)


# 4 training samples: batches of 3 end each epoch with 1 sample, so one rank has none (it pads, weighted 0)
@pytest.mark.parametrize(("stage", "batch"), [("advection", 3), ("pressure", 4)])
def test_two_processes_follow_one_process_with_the_same_global_batch(tiny, tmp_path, stage, batch):
    one = _train(tiny, tmp_path / "one", stage, 1, batch)
    two = _train(tiny, tmp_path / "two", stage, 2, batch)
    assert len(_losses(two, stage)) == 6  # rank 0 alone wrote the log: one row per iteration
    assert _losses(two, stage) == pytest.approx(_losses(one, stage), rel=1e-5)
    _assert_same_weights(one, two, stage)


def test_a_data_parallel_run_resumes_a_checkpoint(tiny, tmp_path, monkeypatch):
    """One process stops inside iteration 5 (after its checkpoint at 4); two processes finish the run."""
    from lagfluid.tasks.train import train

    whole = _train(tiny, tmp_path / "whole", "advection", 1)
    original, calls = torch.optim.Adam.step, {"n": 0}

    def stopped_in_iteration_5(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 5:
            raise KeyboardInterrupt
        return original(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.Adam, "step", stopped_in_iteration_5)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=_args(tiny, tmp_path / "resumed", "advection"))
    with pytest.raises(KeyboardInterrupt):
        train(cfg)
    monkeypatch.setattr(torch.optim.Adam, "step", original)
    assert read_checkpoint(tmp_path / "resumed" / "advection.pt")["step"] == 4
    resumed = _train(tiny, tmp_path / "resumed", "advection", 2)
    assert _losses(resumed, "advection") == pytest.approx(_losses(whole, "advection"), rel=1e-5)
    _assert_same_weights(whole, resumed, "advection")
