"""``benchmarks/gpu_day.sh``'s CPU dry run, which runs ``benchmarks/gpu_train.sh``'s: the GPU scripts'
commands end to end at tiny sizes (< 1 min).

What a GPU lease brings back must be there and usable, in no more files than a lease returns: both networks
load as simulators, both loss logs have rows, provenance names the commands; each training was stopped by
``train.max_seconds`` (its profile's iterations are the full recipe's) and can be continued.
"""

import csv
import math
import os
import re
import signal
import subprocess
import tarfile
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from lagfluid.models.checkpoint import read_checkpoint
from lagfluid.run import CONF_DIR
from lagfluid.tasks.config import build_simulator

REPO = Path(__file__).resolve().parents[1]
SCRIPT = "benchmarks/gpu_train.sh"
DAY = "benchmarks/gpu_day.sh"

BACK = {"gns.pt", "cconv.pt", "gns_loss.csv", "cconv_loss.csv", "gpu_train.log", "provenance.md"}
DAY_BACK = BACK | {"gpu_day.log", "gpu_check.tar.gz"}


def _dry_run_env(work, out):
    return {**os.environ, "GPU_TRAIN_DRY_RUN": "1", "GPU_TRAIN_WORK": str(work), "OUT": str(out)}


def _day_env(work, out):
    return {**os.environ, "GPU_DAY_DRY_RUN": "1", "GPU_DAY_WORK": str(work), "OUT": str(out)}


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


@pytest.fixture(scope="module")
def dry_run(tmp_path_factory):
    """``(exit status, console output, $OUT, working folder)`` of one dry run."""
    root = tmp_path_factory.mktemp("gpu_train")
    # its own process group: a run that hangs is ended with every training it started
    proc = subprocess.Popen(
        ["bash", DAY],
        cwd=REPO,
        env=_day_env(root / "day", root / "out"),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        output, _ = proc.communicate(timeout=300)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        output, _ = proc.communicate()
        pytest.fail(f"the dry run did not end in 300 s:\n{output[-3000:]}")
    return proc.returncode, output, root / "out", root / "day" / "train"


def test_the_dry_run_brings_back_eight_flat_files_a_lease_returns(dry_run):
    rc, output, out, _ = dry_run
    assert rc == 0, output[-3000:]
    # a lease returns at most 8 files, each named in letters, digits, '.', '_' and '-'
    assert {p.name for p in out.iterdir()} == DAY_BACK and all(p.is_file() for p in out.iterdir())
    assert all(re.fullmatch(r"[A-Za-z0-9._-]+", p.name) for p in out.iterdir())
    log = (out / "gpu_day.log").read_text()
    assert "environment\t0\t" in log and "check\tskipped\t0" in log and "train\t0\t" in log
    assert "exit status: 0" in log and "===== train" in log
    with tarfile.open(out / "gpu_check.tar.gz") as tar:
        assert tar.getnames()[0] == "check"  # the check's folder (skipped in a dry run: empty)


def test_a_day_into_an_out_that_holds_files_is_refused_untouched(tmp_path):
    (tmp_path / "earlier.md").write_text("mine")
    env = _day_env(tmp_path / "day", tmp_path)
    done = subprocess.run(["bash", DAY], cwd=REPO, env=env, capture_output=True, text=True)
    assert done.returncode == 1
    assert done.stderr == f"benchmarks/gpu_day.sh: {tmp_path} is not empty: move its files, or set OUT\n"
    assert (tmp_path / "earlier.md").read_text() == "mine"
    assert {p.name for p in tmp_path.iterdir()} == {"earlier.md"}  # nothing written beside it


@pytest.mark.parametrize(("kind", "iterations"), [("gns", 2_000_000), ("cconv", 50_000)])
def test_each_network_comes_back_loadable_with_its_loss_log_and_stopped_by_the_cap(dry_run, kind, iterations):
    _, _, out, work = dry_run
    shipped = read_checkpoint(out / f"{kind}.pt", kind)
    assert "optimizer" not in shipped and "rng" not in shipped  # shipping size
    assert 0 < shipped["step"] < iterations  # the full recipe's length, stopped by train.max_seconds
    assert read_checkpoint(work / kind / f"{kind}.pt")["step"] == shipped["step"]  # continuable
    sim = build_simulator(_compose(f"model={kind}", f"model.weights={out}"))
    loaded = sim.net.state_dict()
    assert all(torch.equal(loaded[k].cpu(), v) for k, v in shipped["state_dict"].items())
    with (out / f"{kind}_loss.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == shipped["step"]  # the dry run logs every iteration
    assert all(math.isfinite(float(r["train_loss"])) for r in rows)
    log = (out / "gpu_train.log").read_text()
    assert f"{kind}: stopped by train.max_seconds at iteration {shipped['step']} of {iterations}" in log
    assert f"| {kind} | {shipped['step']} | {iterations} | " in (out / "provenance.md").read_text()


def test_provenance_names_the_commit_the_commands_and_their_exit_status(dry_run):
    _, _, out, _ = dry_run
    text = (out / "provenance.md").read_text()
    assert "- git commit: " in text and "- dry run: True" in text and f"torch {torch.__version__}" in text
    for step, command in (
        ("generate", "python -m lagfluid.run -m task=generate scene=random data=tiny"),
        ("train_gns", "python -m lagfluid.run task=train model=gns train=gns_paper data=tiny"),
        ("train_cconv", "python -m lagfluid.run task=train model=cconv train=cconv_paper data=tiny"),
    ):
        assert f"| {step} | 0 | " in text and command in text, step
    log = (out / "gpu_train.log").read_text()
    assert "===== train_gns" in log and "===== train_cconv" in log and "wrote " in log  # every command's


def test_an_out_that_holds_one_of_its_files_is_refused_untouched(tmp_path):
    (tmp_path / "gns.pt").write_text("mine")
    env = _dry_run_env(tmp_path / "work", tmp_path)
    done = subprocess.run(["bash", SCRIPT], cwd=REPO, env=env, capture_output=True, text=True)
    assert done.returncode == 1
    assert done.stderr == f"benchmarks/gpu_train.sh: {tmp_path}/gns.pt exists: move it, or set OUT\n"
    assert (tmp_path / "gns.pt").read_text() == "mine"
    assert {p.name for p in tmp_path.iterdir()} == {"gns.pt", "work"}  # nothing written beside it
