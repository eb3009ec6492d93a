"""``python -m lagfluid.data.convert``: LagrangeBench round trips, a DeepMind file read, GNS trained on it."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from lagfluid.data.convert import ConversionError, convert, main
from lagfluid.data.datasets import AdvectionSamples, TrajectoryWindows
from lagfluid.data.store import read_trajectory
from lagfluid.errors import LagfluidError
from lagfluid.generate import generate
from lagfluid.run import CONF_DIR
from lagfluid.state import ParticleType

LB_KEYS = (
    "dim", "dx", "dt", "write_every", "sequence_length_train", "num_trajs_train", "sequence_length_test",
    "num_trajs_test", "num_particles_max", "periodic_boundary_conditions", "bounds",
    "default_connectivity_radius", "vel_mean", "vel_std", "acc_mean", "acc_std",
)  # fmt: skip


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


@pytest.fixture(scope="module")
def ours(tmp_path_factory):
    out = tmp_path_factory.mktemp("ours")
    generate(
        _compose(
            "task=generate",
            "scene=random",
            "data=tiny",
            "data.steps=16",
            f"data.out_dir={out}",
            "progress=false",
        )
    )
    return out


@pytest.fixture(scope="module")
def lagrangebench(ours, tmp_path_factory):
    return convert(ours, tmp_path_factory.mktemp("lb") / "lb")


def test_our_dataset_in_lagrangebench_layout(ours, lagrangebench):
    meta = json.loads((lagrangebench / "metadata.json").read_text())
    assert set(LB_KEYS) <= set(meta) and meta["dim"] == 3 and meta["dx"] == 0.05
    ours_meta = json.loads((ours / "metadata.json").read_text())
    assert meta["dt"] == ours_meta["dt"] and meta["write_every"] == ours_meta["sample_every"]
    # the same statistics in their units (m per frame), from the train split, as our generation writes
    for key in ("vel_mean", "vel_std", "acc_mean", "acc_std"):
        assert meta[key] == pytest.approx(ours_meta[key], rel=1e-4, abs=1e-9), key
    for split in ("train", "valid", "test"):
        with h5py.File(lagrangebench / f"{split}.h5") as f:
            assert sorted(f) == ["00000"]
            run = read_trajectory(ours / ours_meta["splits"][split][0])
            position, ptype = f["00000/position"][()], f["00000/particle_type"][()]
            nf, walls = (
                run["position"].shape[1],
                run["boundary_position"][run["boundary_type"] == ParticleType.WALL],
            )
            assert (
                position.shape == (run["position"].shape[0], nf + len(walls), 3)
                and position.dtype == np.float32
            )
            assert (ptype[:nf] == 0).all() and (ptype[nf:] == 1).all()  # LagrangeBench's fluid and wall
            np.testing.assert_array_equal(position[:, :nf], run["position"])
            np.testing.assert_array_equal(
                position[:, nf:], np.broadcast_to(walls, (len(position), *walls.shape))
            )


def test_a_lagrangebench_dataset_back_to_ours_keeps_the_trajectories(ours, lagrangebench, tmp_path):
    back = convert(lagrangebench, tmp_path / "back")
    meta = json.loads((back / "metadata.json").read_text())
    assert meta["samples"] is False and meta["counts"] == {"train": 1, "valid": 1, "test": 1}
    ours_meta = json.loads((ours / "metadata.json").read_text())
    for split in ("train", "valid", "test"):
        a = read_trajectory(ours / ours_meta["splits"][split][0])
        b = read_trajectory(back / meta["splits"][split][0])
        np.testing.assert_array_equal(b["position"], a["position"])
        walls = a["boundary_position"][a["boundary_type"] == ParticleType.WALL]
        np.testing.assert_array_equal(b["boundary_position"], walls)
        frame_dt = ours_meta["dt"] * ours_meta["sample_every"]
        np.testing.assert_allclose(
            b["velocity"][1:], np.diff(a["position"], axis=0) / frame_dt, rtol=1e-5, atol=1e-6
        )
        assert b["attrs"]["sample_every"] == ours_meta["sample_every"] and b["attrs"]["l0"] == 0.05
    # GNS learns from trajectories: it reads the converted set; FGN's stage samples are not there
    assert len(TrajectoryWindows(back, "train", history=2)) > 0
    with pytest.raises(
        LagfluidError, match=r"holds trajectories only .* AdvectionSamples learns from the MPS stage"
    ):
        AdvectionSamples(back, "train")


def test_gns_trains_a_step_on_a_converted_lagrangebench_dataset(lagrangebench, tmp_path):
    from lagfluid.train import train

    back = convert(lagrangebench, tmp_path / "back")
    small = {"latent": 16, "hidden": 16, "mlp_layers": 2, "blocks": 2, "history": 2, "radius": 2.1}
    cfg = _compose(
        "task=train", "model=gns", "train=gns_cpu", f"data.out_dir={back}", f"out_dir={tmp_path / 'gns'}",
        *[f"model.gns.{k}={v}" for k, v in small.items()], "train.iterations={gns: 2}", "train.log_every=1",
        "train.valid_every=2", "train.pushforward.start=100", "progress=false", "threads=1",
    )  # fmt: skip
    (summary,) = train(cfg)
    assert summary["step"] == 2 and (tmp_path / "gns" / "gns.pt").is_file()


def _deepmind(root, dim=3, moving=False):
    """A DeepMind-style dataset written here: two trajectories of a falling block over a kinematic floor."""
    from tfrecord.writer import TFRecordWriter

    root.mkdir()
    rng = np.random.default_rng(0)
    floor = np.stack(np.meshgrid(np.arange(4) * 0.1, np.arange(4) * 0.1, [0.0], indexing="ij"), -1).reshape(
        -1, 3
    )
    block = (
        0.05
        + np.stack(np.meshgrid(*[np.arange(2) * 0.1] * 3, indexing="ij"), -1).reshape(-1, 3)
        + [0, 0, 0.2]
    )
    trajectories = []
    for split in ("train", "valid", "test"):
        writer = TFRecordWriter(str(root / f"{split}.tfrecord"))
        for key in range(2 if split == "train" else 1):
            frames = []
            for t in range(6):
                fluid = block + [0, 0, -0.5 * 9.8 * (0.01 * t) ** 2] + 1e-3 * rng.standard_normal(block.shape)
                solid = floor + ([0.01 * t, 0, 0] if moving else 0.0)
                frames.append(np.concatenate([fluid, solid])[:, :dim].astype(np.float32))
            ptype = np.array([5] * len(block) + [3] * len(floor), dtype=np.int64)
            writer.write(
                {"key": (key, "int"), "particle_type": (ptype.tobytes(), "byte")},
                {"position": ([f.tobytes() for f in frames], "byte")},
            )
            trajectories.append((split, np.stack(frames)))
        writer.close()
    meta = {
        "bounds": [[0.0, 0.4]] * dim,
        "sequence_length": 5,
        "default_connectivity_radius": 0.15,
        "dim": dim,
        "dt": 0.01,
    }
    meta |= {"vel_mean": [0.0] * dim, "vel_std": [1.0] * dim, "acc_mean": [0.0] * dim, "acc_std": [1.0] * dim}
    (root / "metadata.json").write_text(json.dumps(meta))
    return trajectories


def test_a_deepmind_tfrecord_dataset_is_read(tmp_path):
    written = _deepmind(tmp_path / "dm")
    out = convert(tmp_path / "dm", tmp_path / "ours")
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["counts"] == {"train": 2, "valid": 1, "test": 1} and meta["source"]["format"] == "deepmind"
    assert meta["l0"] == pytest.approx(0.1, abs=2e-3)  # the block's spacing, estimated from frame 0
    for name, (_split, frames) in zip(
        meta["splits"]["train"] + meta["splits"]["valid"], written, strict=False
    ):
        run = read_trajectory(out / name)
        np.testing.assert_array_equal(run["position"], frames[:, :8])
        np.testing.assert_array_equal(run["boundary_position"], frames[0, 8:])
        assert (run["boundary_type"] == ParticleType.WALL).all()
        assert run["attrs"]["dt"] == pytest.approx(0.01) and np.allclose(run["time"], 0.01 * np.arange(6))


def test_what_cannot_convert_is_named(tmp_path, lagrangebench):
    _deepmind(tmp_path / "flat", dim=2)
    with pytest.raises(ConversionError, match=r"flat is 2D: lagfluid's simulators and training are 3D"):
        convert(tmp_path / "flat", tmp_path / "out")
    _deepmind(tmp_path / "moving", moving=True)
    with pytest.raises(ConversionError, match=r"its boundary particles move"):
        convert(tmp_path / "moving", tmp_path / "out2")
    assert not (tmp_path / "out2").exists()  # nothing half-written is left under the name
    with pytest.raises(ConversionError, match=r"exists: give a new folder"):
        convert(lagrangebench, lagrangebench)
    periodic = tmp_path / "periodic"
    periodic.mkdir()
    (periodic / "train.h5").write_bytes((lagrangebench / "train.h5").read_bytes())
    meta = json.loads((lagrangebench / "metadata.json").read_text())
    (periodic / "metadata.json").write_text(
        json.dumps({**meta, "periodic_boundary_conditions": [True, False, True]})
    )
    with pytest.raises(ConversionError, match=r"periodic along \[True, False, True\]"):
        convert(periodic, tmp_path / "out3")
    lid = tmp_path / "lid"
    lid.mkdir()
    (lid / "metadata.json").write_text(json.dumps(meta))
    with h5py.File(lagrangebench / "train.h5") as f, h5py.File(lid / "train.h5", "w") as g:
        ptype = f["00000/particle_type"][()]
        ptype[-1] = 2  # LagrangeBench's moving wall (a lid)
        g["00000/particle_type"], g["00000/position"] = ptype, f["00000/position"][()]
    with pytest.raises(ConversionError, match=r"particle types \[2\] .* static walls \(1\) only"):
        convert(lid, tmp_path / "out4")
    (tmp_path / "empty").mkdir()
    assert main([str(tmp_path / "empty"), str(tmp_path / "x")]) == 1
