"""The pieces of the speed sweeps that decide their tables (``benchmarks.two_trees``, ``whole_run``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmarks.two_trees import largest_difference, stage_ms
from benchmarks.two_trees import main as two_trees_main
from benchmarks.whole_run import main as whole_run_main
from benchmarks.whole_run import split_settings
from lagfluid.data.store import TrajectoryWriter


def test_a_stage_is_read_by_its_name_from_the_stages_field():
    field = "neighbors=12.5 advection=3.0 pressure_net=4.25"
    assert stage_ms(field, "neighbors") == 12.5 and stage_ms(field, "pressure_net") == 4.25
    assert math.isnan(stage_ms(field, "collision"))  # absent: nan, not another stage's number


def _rollout(path, shift: float, frames: int = 3):
    pos = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]])
    with TrajectoryWriter(path, 2, np.zeros((1, 3)), np.array([2]), {"dt": 0.002, "l0": 0.05}) as w:
        for k in range(frames):
            moved = pos + 0.01 * k
            moved[1, 2] += shift * k  # the second particle drifts by `shift` per frame
            w.append(0.002 * k, moved, np.zeros((2, 3)), np.zeros(2))
    return path


def test_the_largest_difference_is_the_largest_over_every_frame_and_particle(tmp_path):
    a = _rollout(tmp_path / "a.h5", 0.0)
    assert largest_difference(a, _rollout(tmp_path / "same.h5", 0.0)) == 0.0
    # frame 2: 2 x 0.001 m in one coordinate (float32 storage)
    assert largest_difference(a, _rollout(tmp_path / "b.h5", 0.001)) == pytest.approx(0.002, rel=1e-5)
    # a shorter rollout is compared over the frames both have
    assert largest_difference(a, _rollout(tmp_path / "c.h5", 0.001, frames=2)) == pytest.approx(
        0.001, rel=1e-5
    )


def test_a_variants_settings_split_into_overrides_and_environment():
    overrides, env = split_settings(["solver.neighbors.skin_fraction=0.15", "env.THP_MEM_ALLOC_ENABLE=1"])
    assert overrides == ["solver.neighbors.skin_fraction=0.15"]
    assert env == {"THP_MEM_ALLOC_ENABLE": "1"}
    assert split_settings(["env.A=x=y"]) == ([], {"A": "x=y"})  # the first '=' splits


def test_the_sweeps_refuse_bad_input_before_any_run(tmp_path, monkeypatch):
    import benchmarks.whole_run as whole_run

    def no_run(*args, **kwargs):
        raise AssertionError("a run was started")

    monkeypatch.setattr(whole_run, "run_once", no_run)
    with pytest.raises(SystemExit, match="expected key=value"):
        whole_run_main(["--name", "x", "--variant", "a", "skin"])
    with pytest.raises(SystemExit, match="names must differ"):
        whole_run_main(["--name", "x", "--variant", "a", "k=1", "--variant", "a", "k=2"])
    with pytest.raises(SystemExit, match=r"no benchmarks/fgn_vs_mps\.py"):
        two_trees_main(["--before", str(tmp_path), "--after", "."])
