"""``train.dagger.rounds``: GNS trained on its own mistakes, MPS labelling the model's states (seconds)."""

import copy
import csv
import hashlib
import json

import h5py
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import open_dict

from baselines.gns.trainable import GNSTrainable
from lagfluid.data.datasets import TrajectoryWindows
from lagfluid.data.expert_windows import EXPERT, ExpertWindows, trajectory_windows
from lagfluid.data.layout import GROUP
from lagfluid.errors import ConfigError, LagfluidError, RolloutError
from lagfluid.integrate import acceleration_from_positions
from lagfluid.models.checkpoint import read_checkpoint
from lagfluid.models.mps_simulator import build_mps
from lagfluid.rollout import Guard, rollout
from lagfluid.run import CONF_DIR, _register_plugin_configs
from lagfluid.scenes import build_scene
from lagfluid.state import ParticleState, SceneParams
from lagfluid.tasks.config import at_simulator_time_step, build_simulator
from lagfluid.tasks.generate import generate
from lagfluid.tasks.generate.expert import expert_step
from lagfluid.tasks.generate.spec import DataSpec
from lagfluid.tasks.train import train

# a GNS small enough for seconds: history 2, no pushforward (windows of 3 frames and the next)
TINY_GNS = ["model.gns.latent=8", "model.gns.hidden=8", "model.gns.mlp_layers=1", "model.gns.blocks=1",
            "model.gns.history=2", "train.pushforward.unrolls=[0]",
            "train.pushforward.probs=[1]"]  # fmt: skip
DATA = ["scene=random", "data=tiny", "data.steps=12"]


def _compose(*overrides):
    _register_plugin_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def _train_cfg(data, out, *extra):
    return _compose(
        "task=train", "model=gns", "train=gns_dagger", *DATA, f"data.out_dir={data}", f"out_dir={out}",
        *TINY_GNS, "train.iterations={gns: 2}", "train.stat_samples=2", "train.checkpoint_every=1",
        "train.dagger.iterations=3", "train.dagger.every=1", "train.dagger.jobs=1",
        "train.dagger.lr_start=2e-4", "train.dagger.dam_scene=dam_small", "train.dagger.dam_steps=4",
        "progress=false", "threads=1", *extra,
    )  # fmt: skip


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("dagger_data")
    generate(_compose("task=generate", *DATA, f"data.out_dir={out}", "progress=false", "threads=1"))
    return out


@pytest.fixture(scope="module")
def two_rounds(tiny_data, tmp_path_factory):
    """A run of 2 iterations of one-step training, then 2 DAgger rounds: its config and folder."""
    out = tmp_path_factory.mktemp("dagger_run")
    cfg = _train_cfg(tiny_data, out, "train.dagger.rounds=2")
    train(cfg)
    return cfg, out


# ------------------------------------------------------------------------------------------ the label
def test_mps_label_of_a_free_fall_is_the_integrator_inverse_of_mps_substeps():
    """Three particles far apart (no neighbours, free surface: a = g): MPS's 4 steps of 2 ms from the model's
    x_t and v_t = (x_t - x_{t-1}) / 8 ms are x_t + 4 dt v + g dt^2 (1 + 2 + 3 + 4), and GNS's target
    (x' - 2 x_t + x_{t-1}) / (8 ms)^2 is g (S + 1) / 2S = 5/8 g, as in MPS's own trajectories."""
    mps = build_mps(_compose("dtype=float64"))
    g, dt, substeps, frame_dt = torch.tensor([0.0, 0.0, -9.8065], dtype=torch.float64), 0.002, 4, 0.008
    params = SceneParams(gravity=tuple(g.tolist()), viscosity=1e-6, density=1000.0, dt=frame_dt, l0=0.05)
    x_t = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 2.0]], dtype=torch.float64)
    v_t = torch.tensor([[0.1, -0.2, 0.3], [0.0, 0.0, -1.0], [0.5, 0.5, 0.0]], dtype=torch.float64)
    x_prev = x_t - v_t * frame_dt
    ptype = torch.ones(3, dtype=torch.long)
    # the states' own velocities are not what MPS starts from: the frames' difference is
    before = ParticleState(x_prev, torch.full_like(v_t, 7.0), ptype, params, check=False)
    after = ParticleState(x_t, torch.full_like(v_t, 9.0), ptype, params, step=6, check=False)
    mps.reset(ParticleState(x_t, v_t, ptype, params.with_overrides(dt=dt)))
    answer = expert_step(mps, before, after, dt, substeps)
    torch.testing.assert_close(answer.pos, x_t + substeps * dt * v_t + g * dt**2 * 10, rtol=0, atol=1e-12)
    torch.testing.assert_close(answer.vel, v_t + substeps * dt * g, rtol=0, atol=1e-12)
    target = acceleration_from_positions(x_prev, x_t, answer.pos, frame_dt)
    torch.testing.assert_close(target, (g * 5 / 8).expand(3, 3), rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------------------ the rounds
def test_each_round_rolls_out_the_previous_rounds_weights_and_mps_labels_their_states(two_rounds):
    cfg, out = two_rounds
    r1, r2 = out / "dagger" / "round1", out / "dagger" / "round2"
    for data, policy in ((r1 / "data", out), (r2 / "data", r1)):
        meta = json.loads((data / "metadata.json").read_text())
        assert (meta["trajectory"], meta["labels"], meta["expert"]["substeps"]) == ("model", "mps", 2)
        assert meta["policy"]["weights"] == _sha(policy / "gns.pt")
        assert meta["splits"] == {"train": ["scenes/scene_00000.h5"], "valid": [], "test": []}
    # round 1's scene is the dataset's training scene moved by the one-step weights, frame for frame
    spec = DataSpec.from_config(_compose("task=generate", *DATA, "steps=12"))
    options, params, _ = spec.scene_setup(0)
    run = copy.deepcopy(cfg)
    with open_dict(run):
        run.model.weights = str(out)
    sim = build_simulator(run)
    start = build_scene("random", params, **options)
    frames = []
    rollout(sim, at_simulator_time_step(start, sim, run), 6, on_frame=lambda s: frames.append(s))
    with h5py.File(r1 / "data" / "scenes" / "scene_00000.h5") as f:
        stored = f[GROUP]["position"][()]
        label_frames, labels = f[EXPERT]["frame"][()], f[EXPERT]["position"][()]
    np.testing.assert_array_equal(stored, np.stack([s.pos[: s.n_fluid].numpy() for s in frames]))
    # every frame the model made (3..6, after its 2 MPS warm-start frames) is labelled by 2 MPS steps
    assert label_frames.tolist() == [3, 4, 5, 6]
    mps = build_mps(cfg)
    mps.reset(start)
    for t, label in zip(label_frames, labels, strict=True):
        answer = expert_step(mps, frames[t - 1], frames[t], 0.002, 2)
        np.testing.assert_allclose(answer.pos[:64].numpy(), label, rtol=0, atol=1e-6)


def test_round_k_fine_tunes_from_round_k_minus_1_on_the_original_data_and_rounds_1_to_k(
    two_rounds, tiny_data
):
    _, out = two_rounds
    r1, r2 = out / "dagger" / "round1", out / "dagger" / "round2"
    for k, here, previous in ((1, r1, out), (2, r2, r1)):
        identity = json.loads(read_checkpoint(here / "gns.pt")["meta"]["identity"])
        assert identity["init_from"] == str(previous.resolve())
        assert identity["data"]["dir"] == str(tiny_data.resolve())  # the original data trains (and validates)
        rounds = [str((out / "dagger" / f"round{j}" / "data").resolve()) for j in range(1, k + 1)]
        assert [d["dir"] for d in identity["extra_data"]] == rounds
        assert (identity["iterations"], identity["lr"][0]) == (3, 2e-4)
    tuned, first = (read_checkpoint(p)["state_dict"] for p in (r2 / "gns.pt", out / "gns.pt"))
    assert any(not torch.equal(tuned[k], first[k]) for k in tuned)


def test_a_dagger_window_is_the_models_frames_and_its_target_the_inverse_of_mps_answer(two_rounds):
    cfg, out = two_rounds
    data = out / "dagger" / "round1" / "data"
    items = ExpertWindows(data, "train", history=2)
    with h5py.File(data / "scenes" / "scene_00000.h5") as f:
        frames, labels = f[GROUP]["position"][()], f[EXPERT]["position"][()]
    assert len(items) == 4  # labels at frames 3..6, each with 2 frames before it
    item = items[1]  # frame 4
    np.testing.assert_array_equal(item.pos[:64].numpy(), frames[4])
    np.testing.assert_array_equal(item.history.numpy(), frames[2:4].transpose(1, 0, 2))
    np.testing.assert_array_equal(item.y.numpy(), labels[1])
    assert float(item.frame_dt) == np.float32(0.004) and int(item.step) == 8
    trainable = GNSTrainable(cfg)
    net = trainable.build_network()
    net.load_state_dict(read_checkpoint(out / "gns.pt")["state_dict"])
    _, target = trainable.predict(net.eval(), item)
    expected = acceleration_from_positions(
        *(torch.from_numpy(a) for a in (frames[3], frames[4], labels[1])), 0.004
    )
    torch.testing.assert_close(net.acceleration.inverse(target), expected, rtol=1e-5, atol=1e-3)
    # a history of 4 frames leaves out the label at frame 3 (only 3 frames before it)
    longer = ExpertWindows(data, "train", history=4)
    assert len(longer) == 3 and torch.equal(longer[0].y, torch.from_numpy(labels[1]))
    # from frame 2 on it keeps that label: the frame before frame 0 is frame 0's copy (GNS learns from H on)
    early = ExpertWindows(data, "train", history=4, first=2)
    assert len(early) == 4 and [int(early[j].frames_before) for j in range(4)] == [3, 4, 4, 4]
    np.testing.assert_array_equal(early[0].history.numpy(), frames[[0, 0, 1, 2]].transpose(1, 0, 2))
    # the solver-trajectory windows refuse the model's trajectory, and the trainable reads it right
    with pytest.raises(LagfluidError, match="on-policy dataset"):
        TrajectoryWindows(data, "train", history=2)
    assert isinstance(trainable.datasets(data)[0], ExpertWindows)
    with pytest.raises(LagfluidError, match="DAgger dataset, whose frames are the model's own steps"):
        trajectory_windows(data, "train", history=2, stride=2)  # its frames are already the model's


def test_each_rounds_dam_rollout_is_measured_and_a_rerun_redoes_nothing(two_rounds):
    cfg, out = two_rounds
    with (out / "dagger" / "dam.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [r["round"] for r in rows] == ["0", "1", "2"]
    assert [r["weights"] for r in rows] == [
        str(out),
        str(out / "dagger" / "round1"),
        str(out / "dagger" / "round2"),
    ]
    assert all(r["complete"] == "True" and r["steps"] == "4" for r in rows)
    for k in range(3):
        metrics = json.loads((out / "dagger" / f"round{k}" / "dam" / "metrics.json").read_text())
        assert metrics["scene"] == "dam_small" and metrics["steps"] == 4
    r2 = out / "dagger" / "round2"
    watched = [r2 / "data" / "scenes" / "scene_00000.h5", r2 / "gns.pt", r2 / "dam" / "rollout.h5"]
    stamps = [p.stat().st_mtime_ns for p in watched]
    train(cfg)
    assert [p.stat().st_mtime_ns for p in watched] == stamps


def test_the_rounds_benchmark_compares_each_rounds_dam_rollout_with_the_reference(two_rounds, tmp_path):
    """``benchmarks.dagger_rounds``: a row per round from its stored dam rollout; against round 0's own
    rollout as the reference, round 0 is 0 mm away and the fine-tuned rounds are not."""
    from benchmarks.dagger_rounds import main, round_rows
    from lagfluid.physics.settings import SolverSettings

    _, out = two_rounds
    reference = out / "dagger" / "round0" / "dam" / "rollout.h5"
    rows = round_rows(out, reference, SolverSettings.from_config(_compose().solver))
    assert [r["round"] for r in rows] == [0, 1, 2] and {r["rollout"] for r in rows} == {"complete"}
    assert rows[0]["chamfer_mean_mm"] == 0.0 and rows[0]["density_error_mean"] == rows[0]["density_error_mps"]
    assert rows[2]["chamfer_max_mm"] > 0.0
    assert all(r["frames_compared"] == rows[0]["frames_compared"] for r in rows)
    main([str(out), "--reference", str(reference), "--name", "r", "--about", "x", "--results", str(tmp_path)])
    assert (tmp_path / "r.csv").read_text().splitlines()[0].startswith("round,rollout,frames_compared")
    with pytest.raises(SystemExit, match=r"holds no dagger/dam\.csv"):
        round_rows(tmp_path, reference, SolverSettings.from_config(_compose().solver))


def test_start_from_skips_the_one_step_training_and_every_k_labels_every_kth_own_frame(
    two_rounds, tiny_data, tmp_path
):
    _, first = two_rounds
    out = tmp_path / "run"
    train(_train_cfg(tiny_data, out, "train.dagger.rounds=1", f"train.dagger.start_from={first}",
                     "train.dagger.dam_steps=0", "train.dagger.every=2"))  # fmt: skip
    assert not (out / "gns.pt").exists() and not (out / "dagger" / "dam.csv").exists()
    identity = json.loads(read_checkpoint(out / "dagger" / "round1" / "gns.pt")["meta"]["identity"])
    assert identity["init_from"] == str(first.resolve())
    data = out / "dagger" / "round1" / "data"
    meta = json.loads((data / "metadata.json").read_text())
    assert meta["policy"]["weights"] == _sha(first / "gns.pt") and meta["expert"]["every"] == 2
    with h5py.File(data / "scenes" / "scene_00000.h5") as f:
        assert f[EXPERT]["frame"][()].tolist() == [3, 5]  # the model's 1st and 3rd own frames


class _StopAt(Guard):
    """The model's guard, stopping the rollout at step 5 as a particle through a wall would."""

    def check(self, state):
        if state.step == 5:
            raise RolloutError("step 5: fluid particle 0 left the domain (planted)")
        super().check(state)


def test_a_rollout_stopped_by_the_models_guard_keeps_the_frames_and_labels_before(
    two_rounds, tiny_data, tmp_path, monkeypatch
):
    _, first = two_rounds
    import lagfluid.tasks.generate.expert as expert

    monkeypatch.setattr(expert, "run_guard", lambda cfg, sim: _StopAt(1.0))
    out = tmp_path / "run"
    train(_train_cfg(tiny_data, out, "train.dagger.rounds=1", f"train.dagger.start_from={first}",
                     "train.dagger.dam_steps=0"))  # fmt: skip
    scene = out / "dagger" / "round1" / "data" / "scenes" / "scene_00000.h5"
    with h5py.File(scene) as f:
        assert f[GROUP]["position"].shape[0] == 5 and f[EXPERT]["frame"][()].tolist() == [3, 4]
        assert f[GROUP].attrs["stopped_after_frame"] == 4 and "planted" in f[GROUP].attrs["stop_reason"]
    assert len(ExpertWindows(scene.parents[1], "train", history=2)) == 2


def test_where_mps_itself_fails_from_the_models_state_the_scene_stops_there(two_rounds, tiny_data, tmp_path):
    _, first = two_rounds
    out = tmp_path / "run"
    train(_train_cfg(tiny_data, out, "train.dagger.rounds=1", f"train.dagger.start_from={first}",
                     "train.dagger.dam_steps=0", "solver.guard.max_courant=1e-9"))  # fmt: skip
    with h5py.File(out / "dagger" / "round1" / "data" / "scenes" / "scene_00000.h5") as f:
        assert f[GROUP]["position"].shape[0] == 3 and f[EXPERT]["frame"].shape == (0,)
        assert "MPS advanced from the model's frame 3 fails its guard" in f[GROUP].attrs["stop_reason"]


# ------------------------------------------------------------------------------------------ bad options
@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("train.dagger.rounds=-1", r"train.dagger.rounds must be a whole number >= 0, got -1$"),
        ("train.dagger.every=0", r"train.dagger.every must be a whole number >= 1, got 0$"),
        ("train.dagger.iterations=0", r"train.dagger.iterations must be a whole number >= 1, got 0$"),
        ("train.dagger.jobs=0", r"train.dagger.jobs must be a whole number >= 1, got 0$"),
        ("train.dagger.dam_steps=-3", r"train.dagger.dam_steps must be a whole number >= 0, got -3$"),
        ("train.dagger.lr_start=0", r"train.dagger.lr_start must be a number > 0, got 0$"),
        ("train.dagger.start_from=/no/such/dir", r"train.dagger.start_from=/no/such/dir is not a folder"),
        (
            "train.dagger.dam_scene=dams",
            r"train.dagger.dam_scene=dams: no such scene; available: .*dam_small",
        ),
        ("train.dagger.horizon=0", r"train.dagger.horizon must be a whole number >= 1, got 0$"),
        ("train.frame_stride=2", r"train.frame_stride must be 1 with rounds, got 2$"),
        ("scene=dam", r"train.dagger.rounds regenerates .*\(scene=dam; the dataset's is scene=random\)"),
    ],
)
def test_bad_dagger_settings_are_refused_before_anything_runs(tiny_data, tmp_path, override, message):
    cfg = _train_cfg(tiny_data, tmp_path / "run", "train.dagger.rounds=1", override)
    with pytest.raises(ConfigError, match=message):
        train(cfg)
    assert not (tmp_path / "run" / "gns.pt").exists()


def test_a_split_step_model_is_sent_to_the_on_policy_rounds(tiny_data, tmp_path, untrained_weights):
    cfg = _compose(
        "task=train", "model=fgn", *DATA, f"data.out_dir={tiny_data}", f"out_dir={tmp_path}",
        "progress=false", f"+train.dagger={{rounds: 1, start_from: {untrained_weights}}}",
    )  # fmt: skip
    with pytest.raises(ConfigError, match=r"model fgn is split-step; its rounds are train\.onpolicy\.rounds"):
        train(cfg)
    assert not (tmp_path / "dagger").exists()
