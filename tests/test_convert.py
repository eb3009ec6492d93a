"""``python -m lagfluid.data.convert``: LagrangeBench round trips, a DeepMind file read, GNS trained on it."""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from scipy.spatial.distance import cdist

from lagfluid.data.convert import PART_MARKER, ConversionError, convert, main
from lagfluid.data.datasets import AdvectionSamples, TrajectoryWindows
from lagfluid.data.store import read_trajectory
from lagfluid.errors import LagfluidError
from lagfluid.run import CONF_DIR
from lagfluid.state import ParticleType
from lagfluid.tasks.generate import generate

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
        # the types: the walls come back as walls (the dummy layers were left out on the way there)
        assert (b["boundary_type"] == ParticleType.WALL).all() and len(b["boundary_type"]) == len(walls)
        assert b["position"].shape[1] == a["position"].shape[1]  # every fluid particle, fluid again
        for key in ("dt", "l0", "gravity", "viscosity", "bounds"):
            np.testing.assert_array_equal(b["attrs"][key], a["attrs"][key], err_msg=key)
    # the metadata: spacing, steps, the fluid's domain (not LagrangeBench's bounds round the walls), radius
    for key in ("dt", "l0", "sample_every", "steps", "sequence_length", "default_connectivity_radius"):
        assert meta[key] == ours_meta[key], key
    np.testing.assert_array_equal(meta["bounds"], ours_meta["bounds"])
    for key in ("vel_mean", "vel_std", "acc_mean", "acc_std"):
        assert meta[key] == pytest.approx(ours_meta[key], rel=1e-4, abs=1e-9), key
    assert [s["gravity"] for s in meta["scenes"]] == [s["gravity"] for s in ours_meta["scenes"]]
    # GNS learns from trajectories: it reads the converted set; FGN's stage samples are not there
    assert len(TrajectoryWindows(back, "train", history=2)) > 0
    with pytest.raises(
        LagfluidError, match=r"holds trajectories only .* AdvectionSamples learns from the MPS stage"
    ):
        AdvectionSamples(back, "train")


def _lagrangebench_finds(position, bounds, radius):
    """Which pairs within ``radius`` LagrangeBench's default neighbour list finds, written here from its code.

    LagrangeBench (``case_setup/case.py``) builds ``space.free()`` and jax-md's cell list (``jax_sph.jax_md
    .partition.neighbor_list``, backend ``jaxmd_vmap``) with ``box = bounds[:, 1] - bounds[:, 0]`` only, in
    float32: ``n = floor(box / r)`` cells per axis of size ``box / n`` over ``[0, box)``; a particle's cell
    index is ``int32(x / cell)`` (truncated toward 0, not clamped), flattened as ``i + n_x j + n_x n_y k``; a
    flat index below 0 wraps once (numpy indexing), beyond the last cell the particle is dropped; candidates
    are the particles filed in the 27 cells around one's own, cell indices wrapping round the grid; the pairs
    closer than ``r`` among them are kept. A particle outside ``[0, box)`` is filed in a wrong cell.

    Args:
        position: (N, 3) one frame.
        bounds: (3, 2) ``metadata.json``'s ``[[lo, hi], ...]``.
        radius: the connectivity radius.

    Returns:
        ``(i, j, found)``: the pairs ``i < j`` closer than ``radius`` (brute force); is each found.
    """
    box = np.float32(bounds[:, 1] - bounds[:, 0])
    n = np.floor(box / np.float32(radius))
    index = np.trunc(position.astype(np.float32) / (box / n)).astype(np.int64)
    n = n.astype(np.int64)
    flat = index[:, 0] + n[0] * index[:, 1] + n[0] * n[1] * index[:, 2]
    flat = np.where(flat < 0, flat + n.prod(), flat)
    filed = (flat >= 0) & (flat < n.prod())
    cell = np.stack(np.unravel_index(np.where(filed, flat, 0), tuple(n), order="F"), axis=1)
    distance = cdist(position.astype(np.float64), position.astype(np.float64))  # brute force, (N, N)
    i, j = np.nonzero(np.triu(distance < radius, k=1))
    apart = np.abs(cell[i] - cell[j])
    apart = np.minimum(apart, n - apart)  # the grid wraps round
    return i, j, filed[i] & filed[j] & (apart <= 1).all(axis=1)


def test_a_converted_dataset_is_read_by_lagrangebench_conventions(lagrangebench):
    meta = json.loads((lagrangebench / "metadata.json").read_text())
    bounds, radius = np.asarray(meta["bounds"], dtype=np.float64), meta["default_connectivity_radius"]
    assert bounds.shape == (3, 2) and (bounds[:, 0] < bounds[:, 1]).all()  # [[lo, hi]] per axis
    for split in ("train", "valid", "test"):
        with h5py.File(lagrangebench / f"{split}.h5") as f:
            position, ptype = f["00000/position"][()], f["00000/particle_type"][()]
        assert (ptype == 1).any()  # walls, outside the fluid's domain [0, 0.6] x [0, 0.6] x [0, 1]
        every = position.reshape(-1, 3).astype(np.float64)
        assert (every >= bounds[:, 0]).all() and (every <= bounds[:, 1]).all(), split  # bounds hold them all
        for frame in position[[0, -1]]:  # the walls stand still, the fluid moves
            i, _, found = _lagrangebench_finds(frame, bounds, radius)
            assert len(i) > 10 * len(frame) and found.all(), f"{split}: {(~found).sum()} pairs missed"


def test_the_cell_search_written_here_misses_pairs_of_particles_outside_the_bounds():
    # a tank's corner on the lattice: walls one spacing past the fluid's domain [0, 0.6]^2 x [0, 1], as our
    # scenes have them; bounds round every particle find every pair, the domain's miss some (not vacuous)
    axes = [np.arange(-1, 14) * 0.05, np.arange(-1, 14) * 0.05, np.arange(-1, 11) * 0.05]
    lattice = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    i, _, found = _lagrangebench_finds(lattice, np.array([[-0.05, 0.65], [-0.05, 0.65], [-0.05, 1.0]]), 0.155)
    assert len(i) > 0 and found.all()
    _, _, found = _lagrangebench_finds(lattice, np.array([[0.0, 0.6], [0.0, 0.6], [0.0, 1.0]]), 0.155)
    assert (~found).sum() > 100


def test_lagrangebench_limits_are_warned_at_convert_time(ours, tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="lagfluid.data.convert"):
        convert(ours, tmp_path / "lb")
    # data.steps=16 every 2: 9 frames; LagrangeBench's defaults take 6 + 1 + 3 to train, 6 + 20 to validate
    (line,) = [r.getMessage() for r in caplog.records]
    assert "trajectories of 9 frames (train), 9 frames (valid), 9 frames (test)" in line
    assert "train 10 frames" in line and "valid/test 26" in line and "\n" not in line
    # a scene far from the origin: jax-md's cells over [0, hi - lo) would misplace every particle
    far = tmp_path / "far"
    far.mkdir()
    meta = json.loads((tmp_path / "lb" / "metadata.json").read_text())
    meta["bounds"] = [[lo + 10.0, hi + 10.0] for lo, hi in meta["bounds"]]
    del meta["domain_bounds"]
    (far / "metadata.json").write_text(json.dumps(meta))
    with h5py.File(tmp_path / "lb" / "train.h5") as f, h5py.File(far / "train.h5", "w") as g:
        g["00000/position"], g["00000/particle_type"] = (
            f["00000/position"][()] + 10.0,
            f["00000/particle_type"][()],
        )
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="lagfluid.data.convert"):
        convert(far, tmp_path / "far_lb", to="lagrangebench")
    assert any(
        "particles lie outside [0, hi - lo) along x, y, z" in r.getMessage()
        and "neighbors.backend=matscipy" in r.getMessage()
        for r in caplog.records
    )


def test_convert_removes_no_part_folder_but_its_own(ours, tmp_path, capsys):
    dst, part = tmp_path / "lb", tmp_path / "lb.part"
    part.mkdir()
    (part / "notes.txt").write_text("a user's")
    assert main([str(ours), str(dst)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{part} exists and was not made by lagfluid.data.convert" in err
    assert (part / "notes.txt").read_text() == "a user's" and not dst.exists()
    # one an unfinished conversion left (its marker, its process gone) is replaced
    (part / "notes.txt").unlink()
    ended = subprocess.Popen([sys.executable, "-c", "pass"])
    ended.wait()
    (part / PART_MARKER).write_text(json.dumps({"pid": ended.pid, "host": os.uname().nodename}))
    (part / "train.h5").write_bytes(b"half a file")
    assert convert(ours, dst) == dst and not part.exists()
    assert not (dst / PART_MARKER).exists() and sorted(p.name for p in dst.iterdir()) == [
        "metadata.json", "test.h5", "train.h5", "valid.h5"
    ]  # fmt: skip
    # one a running conversion is writing is left alone
    other = tmp_path / "other.part"
    other.mkdir()
    (other / PART_MARKER).write_text(json.dumps({"pid": os.getpid(), "host": os.uname().nodename}))
    with pytest.raises(ConversionError, match=r"other\.part is being written by another conversion"):
        convert(ours, tmp_path / "other")
    assert (other / PART_MARKER).is_file()


def test_gns_trains_a_step_on_a_converted_lagrangebench_dataset(lagrangebench, tmp_path):
    from lagfluid.tasks.train import train

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
    assert not (tmp_path / "out2.part").exists()  # nor the part folder this run made
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


def test_broken_metadata_and_files_are_one_line(ours, lagrangebench, tmp_path, capsys):
    for key in ("l0", "splits", "steps"):  # a hand-edited lagfluid dataset
        src = tmp_path / f"no_{key}"
        shutil.copytree(ours, src)
        meta = json.loads((ours / "metadata.json").read_text())
        del meta[key]
        (src / "metadata.json").write_text(json.dumps(meta))
        assert main([str(src), str(tmp_path / f"out_{key}")]) == 1
        err = capsys.readouterr().err
        assert err == f"lagfluid.data.convert: {src / 'metadata.json'} lacks the key '{key}'\n"
    meta = json.loads((lagrangebench / "metadata.json").read_text())
    truncated = tmp_path / "truncated"
    truncated.mkdir()
    (truncated / "metadata.json").write_text(json.dumps(meta))
    whole = (lagrangebench / "train.h5").read_bytes()
    (truncated / "train.h5").write_bytes(whole[: len(whole) // 2])  # truncate -s 50%
    assert main([str(truncated), str(tmp_path / "out_t")]) == 1
    err = capsys.readouterr().err
    assert (
        err.count("\n") == 1
        and f"cannot read {truncated / 'train.h5'} as HDF5 (corrupt or truncated?)" in err
    )
    assert not (tmp_path / "out_t").exists() and not (tmp_path / "out_t.part").exists()
    no_dt = tmp_path / "no_dt"
    no_dt.mkdir()
    (no_dt / "metadata.json").write_text(json.dumps({k: v for k, v in meta.items() if k != "dt"}))
    (no_dt / "train.h5").write_bytes(whole)
    with pytest.raises(LagfluidError, match=r"no_dt/metadata\.json lacks the key 'dt'"):
        convert(no_dt, tmp_path / "out_dt")
    with h5py.File(no_dt / "train.h5", "a") as f:
        del f["00000/position"]
    (no_dt / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(ConversionError, match=r"train\.h5:00000 lacks \['position'\]"):
        convert(no_dt, tmp_path / "out_dt")
