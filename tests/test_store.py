import h5py
import numpy as np
import pytest

from lagfluid.data.store import TrajectoryFileError, TrajectoryWriter, read_trajectory


def _write(path, frames=3, complete=True):
    rng = np.random.default_rng(0)
    w = TrajectoryWriter(path, 5, rng.random((4, 3)), np.array([2, 2, 3, 3]), {"dt": 0.002, "model": "mps"})
    data = []
    for k in range(frames):
        pos, vel, p = rng.random((5, 3)), rng.random((5, 3)), rng.random(5)
        w.append(0.002 * k, pos, vel, p)
        data.append((pos, vel, p))
    w.close(complete=complete, stop_reason="" if complete else "stopped")
    return data


def test_round_trip(tmp_path):
    path = tmp_path / "rollout.h5"
    data = _write(path)
    out = read_trajectory(path)
    assert out["position"].shape == (3, 5, 3) and out["position"].dtype == np.float32
    np.testing.assert_allclose(out["position"][2], data[2][0], rtol=1e-6)
    np.testing.assert_allclose(out["time"], [0.0, 0.002, 0.004])
    assert out["boundary_type"].tolist() == [2, 2, 3, 3]
    assert out["attrs"]["model"] == "mps" and bool(out["attrs"]["complete"])
    assert not (tmp_path / "rollout.h5.part").exists()
    with h5py.File(path) as f:
        assert f["00000/position"].compression == "gzip" and f["00000/position"].shuffle
        assert f["00000/position"].chunks == (1, 5, 3)


def test_interrupted_writer_leaves_a_readable_part_file(tmp_path):
    path = tmp_path / "rollout.h5"
    w = TrajectoryWriter(path, 2, np.zeros((1, 3)), np.array([2]), {})
    w.append(0.0, np.zeros((2, 3)), np.zeros((2, 3)), np.zeros(2))
    # simulate a crash: the file is never closed by the writer; flushed frames must be readable
    with h5py.File(w.tmp_path, "r", locking=False) as f:
        assert f["00000/position"].shape == (1, 2, 3)
    w.close(complete=False, stop_reason="interrupted")
    out = read_trajectory(path)
    assert not bool(out["attrs"]["complete"]) and out["attrs"]["stop_reason"] == "interrupted"


def test_missing_corrupt_and_foreign_files_are_clear_errors(tmp_path):
    with pytest.raises(TrajectoryFileError, match="not found"):
        read_trajectory(tmp_path / "nope.h5")
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not an hdf5 file")
    with pytest.raises(TrajectoryFileError, match="corrupt"):
        read_trajectory(bad)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f.attrs["format"] = "something_else"
    with pytest.raises(TrajectoryFileError, match="not a lagfluid trajectory"):
        read_trajectory(foreign)
    path = tmp_path / "ok.h5"
    _write(path)
    with pytest.raises(TrajectoryFileError, match="no trajectory group '00001'"):
        read_trajectory(path, group="00001")
    with h5py.File(path, "a") as f:
        f.attrs["format_version"] = 99
    with pytest.raises(TrajectoryFileError, match="format_version 99"):
        read_trajectory(path)


def test_a_float64_trajectory_is_stored_and_read_as_float64(tmp_path):
    path = tmp_path / "rollout.h5"
    pos = 1e6 + np.arange(6.0).reshape(2, 3) * 0.01  # 1 cm apart 1e6 m out: float32 rounds to 6 cm steps
    w = TrajectoryWriter(path, 2, pos[:1], np.array([2]), {"dt": 0.002}, dtype=np.float64)
    w.append(0.0, pos, -pos, pos[:, 0])
    w.close()
    out = read_trajectory(path)
    for name, value in (("position", pos), ("velocity", -pos), ("pressure", pos[:, 0])):
        assert out[name].dtype == np.float64 and np.array_equal(out[name][0], value), name
    assert np.array_equal(out["boundary_position"], pos[:1])
    with pytest.raises(ValueError, match="float32 or float64, not float16"):
        TrajectoryWriter(tmp_path / "half.h5", 2, pos[:1], np.array([2]), {}, dtype=np.float16)


def test_a_float64_run_far_from_the_origin_stores_its_exact_positions(tmp_path):
    """A grid 1e6 m out (the float32 refusal advises dtype=float64): stored as computed, read back exactly."""
    import torch
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from lagfluid.run import CONF_DIR
    from lagfluid.scenes import build_scene
    from lagfluid.tasks.evaluate import evaluate
    from lagfluid.tasks.simulate import simulate

    near = build_scene("dam", fluid_size=[8, 8, 10], tank_size=[21, 9], dtype=torch.float64)
    pos = near.pos.numpy() + np.array([1e6, 0.0, 0.0])
    grid = tmp_path / "far.npz"
    np.savez(grid, pos=pos, vel=near.vel.numpy(), ptype=near.ptype.numpy())
    start = build_scene("file", path=str(grid), dtype=torch.float64)
    nf = start.n_fluid
    overrides = ["model=mps", "scene=file", f"scene.path={grid}", "dtype=float64", "steps=2", "threads=1"]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=[*overrides, "progress=false", f"out_dir={tmp_path}"])
    simulate(cfg)
    out = read_trajectory(tmp_path / "rollout.h5")
    assert out["position"].dtype == out["velocity"].dtype == out["pressure"].dtype == np.float64
    np.testing.assert_array_equal(out["position"][0], start.pos[:nf].numpy())  # frame 0 is the start, exactly
    np.testing.assert_array_equal(out["boundary_position"], start.pos[nf:].numpy())
    assert np.unique(out["position"][0][:, 0]).size == 8  # 8 columns of fluid, as built (float32 stored 6)
    assert np.unique(out["position"][-1], axis=0).shape[0] == nf  # distinct after the steps too
    # read back as a scene: the last frame, exactly as stored
    last = build_scene("trajectory", path=str(tmp_path / "rollout.h5"), frame=-1, dtype=torch.float64)
    np.testing.assert_array_equal(last.pos[:nf].numpy(), out["position"][-1])
    np.testing.assert_array_equal(last.vel[:nf].numpy(), out["velocity"][-1])
    # task=evaluate stores its model's rollout the same way and compares float64 files: MPS against MPS is 0
    evaluated = evaluate(
        OmegaConf.merge(
            cfg,
            {"task": "evaluate", "out_dir": str(tmp_path / "evaluate")},
            {"evaluate": {"reference_dir": str(tmp_path / "reference"), "figures": False}},
        )
    )
    model = read_trajectory(tmp_path / "evaluate" / "rollout.h5")
    assert model["position"].dtype == np.float64
    np.testing.assert_array_equal(model["position"], out["position"])
    assert evaluated["summary"]["chamfer_mm"]["max"] == 0.0
