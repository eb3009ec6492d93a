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
