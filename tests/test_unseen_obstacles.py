"""``benchmarks.unseen_obstacles``: its scenes, its rows (skipped, resumed) and columns, with no rollout."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from benchmarks import unseen_obstacles as uo
from benchmarks.exact_after import BOTH
from benchmarks.tables.simulators import Simulator
from lagfluid.state import ParticleType

L0 = uo.L0


@pytest.fixture(scope="module")
def states(tmp_path_factory):
    return uo.build_states(list(uo.SCENES), tmp_path_factory.mktemp("meshes"))


def test_every_scene_is_small_with_obstacles_in_reach_and_no_lid(states):
    assert set(states) == {"random_s1000", "dam_cone", "fall_torus"}
    for name, state in states.items():
        pos = state.pos.double().numpy()
        fluid = pos[state.ptype.numpy() == ParticleType.FLUID]
        solid = pos[uo.obstacle_mask(state)]
        assert 2000 <= len(fluid) <= 6000, name
        assert len(solid) > 200, name  # obstacles, not a stray particle
        # in reach: an obstacle stands within 10 l0 of the initial fluid
        assert cKDTree(fluid).query(solid)[0].min() < 10 * L0, name
        # obstacles, not a lid over the tank: they cover less than half of its floor
        cells = {tuple(c) for c in np.round(solid[:, :2] / L0).astype(int).tolist()}
        lower, upper = state.bounds.double().numpy()
        floor = np.prod(np.round((upper[:2] - lower[:2]) / L0) - 1)
        assert len(cells) < 0.5 * floor, name
        # the fluid keeps its spacing from every boundary particle (a valid start)
        boundary = pos[state.ptype.numpy() != ParticleType.FLUID]
        assert cKDTree(boundary).query(fluid)[0].min() > 0.99 * L0, name


def test_mesh_folders_are_named_by_their_geometry(tmp_path):
    meshes = uo.dam_cone_meshes()
    first = uo.write_meshes(tmp_path, "dam_cone", meshes)
    assert uo.write_meshes(tmp_path, "dam_cone", uo.dam_cone_meshes()) == first  # same geometry, same files
    meshes["obstacles"][1].apply_translation([0.1, 0.0, 0.0])  # a moved pillar is another scene
    moved = uo.write_meshes(tmp_path, "dam_cone", meshes)
    assert moved["container"] != first["container"] and moved["obstacles"][1] != first["obstacles"][1]
    assert len(list(tmp_path.iterdir())) == 2


def test_rows_take_the_tables_labels_and_a_missing_one_is_skipped():
    sims = {"cconv": Simulator("cconv", "CConv (CPU training)", "cconv")}
    plain = uo.resolve_row("cconv", sims)
    assert (plain.label, plain.model, plain.overrides, plain.skip) == (
        "CConv (CPU training)",
        "cconv",
        (),
        "",
    )
    exact = uo.resolve_row("cconv_exact", sims)  # no row file of its own: the plain one with both stages
    assert exact.label == "CConv (CPU training) + exact collision + MPS pressure"
    assert (exact.model, exact.overrides, exact.skip) == ("cconv", BOTH, "")
    missing = uo.resolve_row("cconv_finetuned_exact", sims)
    assert "no simulator 'cconv_finetuned_exact'" in missing.skip
    line, metrics = uo.run_row(uo.SCENES["random_s1000"], missing, argparse.Namespace())
    assert metrics is None and line["rollout"] == f"skipped: {missing.skip}" and line["command"] == ""


def test_a_row_file_gives_its_model_overrides():
    assert uo.model_overrides("table3_dam_cconv_exact", "cconv") == BOTH


def _args(tmp_path):
    return argparse.Namespace(
        runs_dir=str(tmp_path), reference_dir=str(tmp_path / "ref"), threads=1, duration=0.6
    )


def _no_run(*args, **kwargs):
    raise AssertionError(f"a run was started: {args}")


def test_a_row_whose_weights_are_missing_is_skipped_not_run(tmp_path, monkeypatch):
    monkeypatch.setattr(uo.subprocess, "run", _no_run)
    row = uo.Row("cconv", "CConv (CPU training)", "cconv", (f"model.weights={tmp_path / 'none'}",))
    line, metrics = uo.run_row(uo.SCENES["random_s1000"], row, _args(tmp_path))
    assert metrics is None
    assert line["rollout"].startswith("skipped: weights missing: no CConv weights at ")
    assert str(tmp_path / "none" / "cconv.pt") in line["rollout"]


def test_a_row_with_metrics_is_read_not_rerun_and_its_columns_are_its_numbers(tmp_path, monkeypatch):
    monkeypatch.setattr(uo.subprocess, "run", _no_run)
    out = tmp_path / "random_s1000" / "gns_exact"
    out.mkdir(parents=True)
    metrics = {
        "model": "gns + exact collision + MPS pressure",
        "complete": False,
        "steps": 30,
        "dt": 0.008,
        "simulator": {"exact_after_collision": True, "exact_after_pressure": True},
        "summary": {
            "chamfer_mm": {"mean": 12.34, "max": 45.67},
            "density_error": {"model": {"mean": 0.0123}, "reference": {"mean": 0.0045}},
        },
    }
    (out / "metrics.json").write_text(json.dumps(metrics))
    # one boundary particle at the origin; fluid at 0.4, 0.6, 0.75 and 2 l0 from it, in one frame
    rollout = {
        "position": np.array([[[0.4, 0, 0], [0, 0.6, 0], [0, 0, 0.75], [2.0, 0, 0]]]) * L0,
        "boundary_position": np.zeros((1, 3)),
        "attrs": {"l0": L0},
    }
    monkeypatch.setattr(uo, "read_trajectory", lambda path: rollout)
    row = uo.Row("gns_exact", "GNS (CPU size) + exact collision + MPS pressure", "gns", BOTH)
    line, read = uo.run_row(uo.SCENES["random_s1000"], row, _args(tmp_path))
    assert read == metrics
    assert line["simulator"] == "GNS (CPU size) + exact collision + MPS pressure"
    assert line["rollout"] == "stops at step 31 (0.248 s)"
    assert line["Chamfer to MPS mean / max (mm)"] == "12.3 / 45.7"
    assert line["density error mean (MPS)"] == "0.0123 (0.0045)"
    assert line["closest to a boundary particle (l0)"] == "0.400"
    assert line["particle-frames < 0.5 / 0.7 l0"] == "2.50e-01 / 5.00e-01"
    # the command reruns it: 0.6 s in GNS's 8 ms steps, frames every 40 ms, into the same folder
    assert "steps=75 write_every=5" in line["command"] and f"out_dir={out}" in line["command"]
    assert "model.exact_after.collision=true model.exact_after.pressure=true" in line["command"]
