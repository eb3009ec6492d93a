"""``train=cconv_dagger``: CConv (2 ms steps, two-step unrolls) on its own states, with exact stages after it.

A tiny DAgger round of CConv followed by MPS's exact collision and pressure (the ``cconv_exact`` row): the
trajectory is the hybrid's, each label is two MPS steps from its state, and CConv's windows of it are the
hybrid's state, the velocity its frames imply and MPS's two steps (seconds).
"""

import copy
import json

import h5py
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import open_dict
from torch_geometric.data import Batch

from baselines.cconv.trainable import CConvTrainable
from lagfluid.data.datasets import StepWindows
from lagfluid.data.expert_windows import EXPERT, LATER, ExpertStepWindows
from lagfluid.data.layout import GROUP
from lagfluid.errors import ConfigError
from lagfluid.models.checkpoint import read_checkpoint
from lagfluid.models.mps_simulator import build_mps
from lagfluid.rollout import rollout
from lagfluid.run import CONF_DIR, _register_plugin_configs
from lagfluid.scenes import build_scene
from lagfluid.state import ParticleType
from lagfluid.tasks.config import at_simulator_time_step, build_simulator
from lagfluid.tasks.generate import generate
from lagfluid.tasks.generate.expert import expert_step
from lagfluid.tasks.generate.spec import DataSpec
from lagfluid.tasks.train import train

DATA = ["scene=random", "data=tiny", "data.next_steps=2"]
BOTH = ["model.exact_after.collision=true", "model.exact_after.pressure=true"]
SMALL = ["model.cconv.layer_channels=[8,8,8,3]"]  # a small network: seconds


def _compose(*overrides):
    _register_plugin_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def _train_cfg(data, out, *extra):
    return _compose(
        "task=train", "model=cconv", "train=cconv_dagger", *DATA, f"data.out_dir={data}", f"out_dir={out}",
        *SMALL, "train.iterations={cconv: 2}", "train.checkpoint_every=1", "train.valid_every=2",
        "train.dagger.rounds=1", "train.dagger.iterations=2", "train.dagger.every=2", "train.dagger.jobs=1",
        "train.dagger.dam_steps=0", "progress=false", "threads=1", *extra,
    )  # fmt: skip


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("cconv_dagger_data")
    generate(_compose("task=generate", *DATA, f"data.out_dir={out}", "progress=false", "threads=1"))
    return out


@pytest.fixture(scope="module")
def hybrid_round(tiny_data, tmp_path_factory):
    """Two iterations of CConv's one-step training, then one DAgger round of CConv + both exact stages."""
    out = tmp_path_factory.mktemp("cconv_dagger_run")
    cfg = _train_cfg(tiny_data, out, *BOTH)
    train(cfg)
    return cfg, out


def _hybrid_frames(cfg, weights, steps):
    """The frames 0..steps of CConv + both exact stages with ``weights`` on the dataset's training scene 0."""
    spec = DataSpec.from_config(_compose("task=generate", *DATA))
    options, params, _ = spec.scene_setup(0)
    run = copy.deepcopy(cfg)
    with open_dict(run):
        run.model.weights = str(weights)
    sim = build_simulator(run)
    start = build_scene("random", params, **options)
    frames = []  # frame 0 (the start) and one per step
    rollout(sim, at_simulator_time_step(start, sim, run), steps, on_frame=frames.append)
    return sim, start, frames


def test_the_hybrid_rolls_the_scenes_out_and_each_label_is_two_mps_steps_from_its_state(hybrid_round):
    cfg, out = hybrid_round
    data = out / "dagger" / "round1" / "data"
    meta = json.loads((data / "metadata.json").read_text())
    assert meta["expert"] == {"every": 2, "substeps": 1, "horizon": 2, "solver": "mps"}
    assert meta["policy"]["model"] == "cconv + exact collision + MPS pressure"
    assert meta["policy"]["horizon"] == 2
    _, start, frames = _hybrid_frames(cfg, out, 8)
    with h5py.File(data / "scenes" / "scene_00000.h5") as f:
        stored = f[GROUP]["position"][()]
        label_frames, first, later = (f[EXPERT][k][()] for k in ("frame", "position", LATER))
    nf = start.n_fluid
    # the hybrid's trajectory, frame for frame (frame 0 the scene's start, then 8 steps of 2 ms)
    np.testing.assert_array_equal(stored, np.stack([s.pos[:nf].numpy() for s in frames]))
    assert label_frames.tolist() == [1, 3, 5, 7] and later.shape == (4, 1, nf, 3)
    mps = build_mps(cfg)
    mps.reset(start)
    for t, one, two in zip(label_frames, first, later[:, 0], strict=True):
        answer = expert_step(mps, frames[t - 1], frames[t], 0.002, 1)
        np.testing.assert_allclose(answer.pos[:nf].numpy(), one, rtol=0, atol=1e-6)
        np.testing.assert_allclose(mps.step(answer).pos[:nf].numpy(), two, rtol=0, atol=1e-6)


def test_cconvs_window_of_the_hybrid_is_its_state_the_frames_velocity_and_mps_two_steps(
    hybrid_round, tiny_data
):
    cfg, out = hybrid_round
    data = out / "dagger" / "round1" / "data"
    trainable = CConvTrainable(cfg)
    items, valid = trainable.datasets(data)
    assert isinstance(items, ExpertStepWindows) and len(items) == 4 and len(valid) == 0
    with h5py.File(data / "scenes" / "scene_00000.h5") as f:
        frames, first, later = (
            f[k][()] for k in (f"{GROUP}/position", f"{EXPERT}/position", f"{EXPERT}/{LATER}")
        )
    item = items[1]  # the label at frame 3
    nf = frames.shape[1]
    np.testing.assert_array_equal(item.pos[:nf].numpy(), frames[3])
    # v_t = (x_3 - x_2) / 2 ms, computed here by hand in float64 (float32 rounding apart)
    by_hand = (frames[3] - frames[2].astype(np.float64)) / 0.002
    np.testing.assert_allclose(item.vel[:nf].numpy(), by_hand, rtol=0, atol=1e-3)
    assert torch.count_nonzero(item.vel[nf:]) == 0 and int(item.step) == 3
    np.testing.assert_array_equal(item.y.numpy(), np.stack([first[1], later[1, 0]], axis=1))
    # the same fields as the solver's windows: one batch holds both, and the trainable predicts two steps
    solver = trainable.windows(tiny_data, "train")
    assert type(solver) is StepWindows
    assert set(solver[0].keys()) == set(item.keys())
    net = trainable.build_network()
    net.load_state_dict(read_checkpoint(out / "cconv.pt")["state_dict"])
    prediction, target = trainable.predict(net.eval(), Batch.from_data_list([solver[0], item]))
    n_both = int((solver[0].ptype == ParticleType.FLUID).sum()) + nf
    assert prediction.shape == target.shape == (n_both, 2, 4)


def test_the_round_fine_tunes_cconv_from_the_start_on_the_original_data_and_the_hybrids(
    hybrid_round, tiny_data
):
    _, out = hybrid_round
    here = out / "dagger" / "round1"
    identity = json.loads(read_checkpoint(here / "cconv.pt")["meta"]["identity"])
    assert identity["init_from"] == str(out.resolve())
    assert identity["data"]["dir"] == str(tiny_data.resolve())
    assert [d["dir"] for d in identity["extra_data"]] == [str((here / "data").resolve())]
    tuned, first = (read_checkpoint(p)["state_dict"] for p in (here / "cconv.pt", out / "cconv.pt"))
    assert any(not torch.equal(tuned[k], first[k]) for k in tuned)


def test_labels_of_fewer_steps_than_cconvs_unroll_are_refused_before_any_rollout(tiny_data, tmp_path):
    cfg = _train_cfg(tiny_data, tmp_path / "run", "train.dagger.horizon=1")
    with pytest.raises(ConfigError, match=r"train.dagger.horizon=1: CConv trains on 2-step unrolls"):
        train(cfg)
    assert not (tmp_path / "run" / "dagger").exists()


def test_a_bad_horizon_is_refused_before_anything_runs(tiny_data, tmp_path):
    cfg = _train_cfg(tiny_data, tmp_path / "run", "train.dagger.horizon=0")
    with pytest.raises(ConfigError, match=r"train.dagger.horizon must be a whole number >= 1, got 0$"):
        train(cfg)
    assert not (tmp_path / "run" / "cconv.pt").exists()
