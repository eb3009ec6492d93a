"""Dataset generation (task=generate) and the PyG datasets over it, on tiny random scenes (seconds)."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from torch_geometric.data import Batch, Data
from torch_geometric.loader import DataLoader

from lagfluid.data.datasets import (
    AdvectionSamples,
    CollisionSamples,
    PressureSamples,
    StepWindows,
    TrajectoryWindows,
    load_metadata,
)
from lagfluid.data.layout import read_scene_info, scene_path, split_counts
from lagfluid.data.statistics import RunningStats, dataset_statistics
from lagfluid.data.store import TrajectoryFileError, read_trajectory
from lagfluid.errors import LagfluidError, RolloutError
from lagfluid.neighbors import radius_graph
from lagfluid.physics import operators as ops
from lagfluid.physics.settings import SolverSettings, lattice_constants
from lagfluid.rollout import Guard
from lagfluid.run import CONF_DIR, check_command_line
from lagfluid.state import ParticleType
from lagfluid.tasks.generate import generate

# sample_every=1: frame s + 1 is the state after sample s's step, so the pressure correction and the clamp
# can be checked against the trajectory too.
REPO = Path(__file__).resolve().parents[1]
TINY = ("task=generate", "scene=random", "data=tiny", "data.sample_every=1", "steps=5", "progress=false")


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def _generate(out_dir, *overrides):
    cfg = _compose(*TINY, f"data.out_dir={out_dir}", *overrides)
    return cfg, generate(cfg)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny")
    cfg, meta = _generate(out)
    return out, cfg, meta


def _copy(dataset, tmp_path):
    out = tmp_path / "data"
    shutil.copytree(dataset[0], out)
    return out


def test_generate_writes_scene_files_and_metadata(dataset):
    out, cfg, meta = dataset
    files = sorted((out / "scenes").iterdir())
    assert [f.name for f in files] == [f"scene_{k:05d}.h5" for k in range(3)]  # no .part left
    assert json.loads((out / "metadata.json").read_text()) == json.loads(json.dumps(meta))
    assert meta["splits"] == {
        k: [f"scenes/scene_{i:05d}.h5"] for i, k in enumerate(("train", "valid", "test"))
    }
    assert meta["dt"] == 0.002 and meta["dim"] == 3 and meta["sample_every"] == 1 and meta["steps"] == 5
    assert meta["default_connectivity_radius"] == pytest.approx(3.1 * 0.05)
    assert np.asarray(meta["bounds"]).shape == (3, 2)
    # the commit the data was made from: this checkout's (a clone in CI), or '' outside a repository
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True)
    assert meta["git_commit"] == (head.stdout.strip() if head.returncode == 0 else "")
    for key in ("vel_mean", "vel_std", "acc_mean", "acc_std"):
        assert len(meta[key]) == 3
    for name in ("speed", "acceleration", "pressure", "density_ratio", "collision_delta_velocity"):
        assert meta["statistics"][name]["count"] > 0
    info = read_scene_info(files[0])
    assert info.complete and info.n_fluid == 64 and info.samples == 5 and info.frames == 6
    assert info.collision_samples == 2 * 2 and info.attrs["seed"] == cfg.seed
    assert meta["counts"]["train"] == {
        "scenes": 1,
        "frames": 6,
        "advection_samples": 5,
        "pressure_samples": 5,
        "collision_samples": 4,
    }
    traj = read_trajectory(files[1])  # the trajectory part is an ordinary rollout file
    assert traj["position"].shape == (6, 64, 3) and int(traj["attrs"]["scene_index"]) == 1
    # each scene is built with seed + index: different fluid placements
    assert not np.array_equal(traj["position"][0], read_trajectory(files[0])["position"][0])


def test_statistics_come_from_the_train_split_only(dataset):
    out, _, meta = dataset
    train = dataset_statistics([out / p for p in meta["splits"]["train"]])
    everything = dataset_statistics(sorted((out / "scenes").glob("*.h5")))
    assert meta["statistics"] == json.loads(json.dumps(train["statistics"]))
    assert meta["statistics"]["speed"] != everything["statistics"]["speed"]
    with h5py.File(out / meta["splits"]["train"][0]) as f:
        speed = np.linalg.norm(f["00000/velocity"][()][f["samples/frame"][()]], axis=-1)
        pressure = f["samples/pressure/pressure"][()]
    assert meta["statistics"]["speed"]["mean"] == pytest.approx(speed.mean(), rel=1e-6)
    assert meta["statistics"]["speed"]["std"] == pytest.approx(speed.std(), rel=1e-5)
    assert meta["statistics"]["pressure"]["max"] == pytest.approx(pressure.max(), rel=1e-6)


def test_running_stats_merge_batches_exactly():
    x = np.random.default_rng(0).normal(3.0, 0.01, size=(1000, 3))
    st = RunningStats()
    for chunk in np.array_split(x, [1, 10, 500]):
        st.update(chunk)
    r = st.result()
    np.testing.assert_allclose(r["mean"], x.mean(0), rtol=1e-12)
    np.testing.assert_allclose(r["std"], x.std(0), rtol=1e-9)


def test_samples_satisfy_the_update_identities(dataset):
    out, _, _ = dataset
    for k in range(3):
        with h5py.File(scene_path(out, k)) as f:
            g, s = f["00000"], f["samples"]
            dt = np.float32(g.attrs["dt"])
            frame = s["frame"][()]
            assert s["step"][()].tolist() == frame.tolist() == list(range(5))
            x, v = g["position"][()], g["velocity"][()]
            acc = s["advection/acceleration"][()]
            x2, v2 = s["pressure/position"][()], s["pressure/velocity"][()]
            v_star = v[frame] + acc * dt
            x_star = x[frame] + v_star * dt
            # x** = x* + (v** - v*) dt, in the solver's float32 operations: exact
            np.testing.assert_array_equal(x2, x_star + (v2 - v_star) * dt)
            # nu = 1e-6: the advection acceleration is gravity up to a tiny viscous term
            np.testing.assert_allclose(acc, np.broadcast_to(g.attrs["gravity"], acc.shape), atol=1e-3)
            # pressure correction: x^{n+1} - x** = dt (v^{n+1} - v**)
            np.testing.assert_allclose((x[frame + 1] - x2) / dt, v[frame + 1] - v2, atol=1e-4)


def test_pressure_samples_are_the_non_free_surface_particles(dataset):
    out, _, _ = dataset
    settings = SolverSettings()
    l0 = 0.05
    n0 = lattice_constants(l0, settings).n0
    solved_fluid = solved_walls = 0
    for k in range(3):
        with h5py.File(scene_path(out, k)) as f:
            g, s = f["00000"], f["samples/pressure"]
            nf = g["position"].shape[1]
            boundary, btype = g["boundary_position"][()], g["boundary_type"][()]
            ptype = np.concatenate([np.ones(nf, np.int64), btype])
            offsets, index = s["offsets"][()], s["index"][()]
            for i in range(len(offsets) - 1):
                rows = index[offsets[i] : offsets[i + 1]]
                pos = torch.from_numpy(np.concatenate([s["position"][i], boundary]))
                n = ops.number_density(
                    pos, radius_graph(pos, settings.re_density * l0), settings.re_density * l0
                )
                n = n.numpy()
                inside = n >= settings.surface_beta * n0
                np.testing.assert_allclose(
                    s["number_density"][offsets[i] : offsets[i + 1]], n[rows], rtol=1e-5
                )
                fluid = rows < nf
                # fluid: exactly the particles off the free surface
                assert rows[fluid].tolist() == np.nonzero(inside[:nf])[0].tolist()
                # boundary: walls (never dummies) off the surface within two re_laplacian hops of the fluid at
                # x**: every wall within one radius, none beyond two (triangle inequality), up to rounding
                assert np.all(ptype[rows[~fluid]] == ParticleType.WALL) and np.all(inside[rows])
                dist = torch.cdist(pos[nf:].double(), pos[:nf].double()).min(dim=1).values.numpy()
                walls = (ptype[nf:] == ParticleType.WALL) & inside[nf:]
                must = np.nonzero(walls & (dist < settings.re_laplacian * l0 * (1 - 1e-5)))[0] + nf
                never = np.nonzero(dist > 2 * settings.re_laplacian * l0 * (1 + 1e-5))[0] + nf
                assert set(must.tolist()) <= set(rows.tolist()) and not set(never.tolist()) & set(
                    rows.tolist()
                )
                # the trajectory stores the clamped pressure of the same step: max(p, 0) on the unknowns,
                # 0 on the free surface
                p_next = g["pressure"][i + 1]
                p = s["pressure"][offsets[i] : offsets[i + 1]]
                np.testing.assert_allclose(p_next[rows[fluid]], np.maximum(p[fluid], 0), rtol=1e-6)
                assert np.all(p_next[np.nonzero(~inside[:nf])[0]] == 0)
                solved_fluid += int(fluid.sum())
                solved_walls += int((~fluid).sum())
    assert solved_fluid > 0 and solved_walls > 0


def test_collision_samples_are_what_the_collision_rule_gives(dataset):
    out, _, _ = dataset
    settings = SolverSettings()
    hits = wall_hits = 0
    for k in range(3):
        with h5py.File(scene_path(out, k)) as f:
            c = f["samples/collision"]
            l0, e = c.attrs["l0"], c.attrs["restitution"]
            assert e == settings.restitution and c.attrs["re_collision"] == settings.re_collision
            bpos, btype = c["boundary_position"][()].astype(np.float64), c["boundary_type"][()]
            for i in range(c["position"].shape[0]):
                fpos = c["position"][i].astype(np.float64)
                fvel = c["velocity"][i].astype(np.float64)
                pos = np.concatenate([fpos, bpos])
                vel = np.concatenate([fvel, np.zeros_like(bpos)])
                ptype = np.concatenate([np.ones(len(fpos), np.int64), btype])
                dv = np.zeros_like(fvel)  # brute-force oracle of the rule (all pairs, float64)
                for a in range(len(fpos)):
                    r = pos - pos[a]
                    d2 = (r**2).sum(1)
                    approach = ((vel[a] - vel) * r).sum(1)
                    near = (d2 < (settings.re_collision * l0) ** 2) & (d2 > 0) & (ptype != ParticleType.DUMMY)
                    hit = near & (approach > 0)
                    factor = 0.5 * (1 + e) * approach[hit] / d2[hit]
                    dv[a] = -(factor[:, None] * r[hit]).sum(0)
                    hits += int(hit.sum())
                    wall_hits += int((hit & (ptype == ParticleType.WALL)).sum())
                np.testing.assert_allclose(c["delta_velocity"][i], dv, atol=1e-4, rtol=1e-4)
    assert hits > 50 and wall_hits > 0


def _two_scene_batch(ds):
    # the first sample of two different scenes (items are numbered scene by scene)
    first_of = {}
    for i in range(len(ds)):
        first_of.setdefault(int(ds[i].scene), i)
    picked = [first_of[s] for s in sorted(first_of)[:2]]
    return next(iter(DataLoader(ds[picked], batch_size=2)))


@pytest.mark.parametrize("cls", [AdvectionSamples, PressureSamples, CollisionSamples, TrajectoryWindows])
def test_datasets_load_as_data_and_batch_block_diagonally(dataset, cls):
    out, _, meta = dataset
    kwargs = {"history": 2} if cls is TrajectoryWindows else {}
    ds = cls(out, split=None, **kwargs)
    expected = {
        AdvectionSamples: 15,
        PressureSamples: 15,
        CollisionSamples: 12,
        TrajectoryWindows: 3 * (6 - 1 - 2),
    }[cls]
    assert len(ds) == expected and len(cls(out, split="train", **kwargs)) == expected // 3
    item = ds[0]
    assert isinstance(item, Data) and item.edge_index is None  # models build their own graphs
    assert item.pos.dtype == torch.float32 and item.ptype.dtype == torch.int64
    nf = int((item.ptype == ParticleType.FLUID).sum())
    if cls is PressureSamples:
        assert item.y.shape == item.density.shape == (item.num_nodes,)
        assert not bool((item.ptype == ParticleType.DUMMY).any())
    else:
        assert item.y.shape == (nf, 3)
    batch = _two_scene_batch(ds)
    assert isinstance(batch, Batch) and batch.num_graphs == 2 and len(set(batch.scene.tolist())) == 2
    assert batch.batch.shape == (batch.num_nodes,) and batch.batch.unique().tolist() == [0, 1]
    r = meta["default_connectivity_radius"]
    edges = radius_graph(batch.pos, r, batch=batch.batch)
    assert edges.shape[1] > 0 and bool((batch.batch[edges[0]] == batch.batch[edges[1]]).all())
    # the scenes share the tank: without the batch vector there would be cross-sample edges
    mixed = radius_graph(batch.pos, r)
    assert bool((batch.batch[mixed[0]] != batch.batch[mixed[1]]).any())
    # labels line up with the fluid rows of the batch
    fluid = batch.ptype == ParticleType.FLUID
    assert batch.y.shape[0] == (batch.num_nodes if cls is PressureSamples else int(fluid.sum()))
    if cls is not PressureSamples:
        assert batch.batch[fluid].tolist() == sorted(batch.batch[fluid].tolist())


def test_advection_item_holds_the_file_arrays_and_the_pruned_boundary_changes_no_fluid_edge(dataset):
    out, _, meta = dataset
    full = AdvectionSamples(out, split="valid", boundary_radius=None)
    pruned = AdvectionSamples(out, split="valid")
    a, b = full[3], pruned[3]
    with h5py.File(out / meta["splits"]["valid"][0]) as f:
        np.testing.assert_array_equal(a.y.numpy(), f["samples/advection/acceleration"][3])
        np.testing.assert_array_equal(a.pos[:64].numpy(), f["00000/position"][3])
        nb = f["00000/boundary_position"].shape[0]
        g, nu = f["00000"].attrs["gravity"], f["00000"].attrs["viscosity"]
    assert a.num_nodes == 64 + nb > b.num_nodes > 64
    assert a.gravity.tolist() == [pytest.approx(list(g))] and float(a.viscosity) == pytest.approx(nu)
    assert int(a.step) == 3 and int(a.scene) == 1

    def fluid_edges(item, r):  # (target, source position) of every edge into a fluid particle, sorted
        e = radius_graph(item.pos, r, receivers=item.ptype == ParticleType.FLUID)
        rows = np.column_stack([e[1].numpy(), item.pos[e[0]].numpy()])
        return rows[np.lexsort(rows.T[::-1])]

    for r_l0 in (0.92, 1.86, 3.1):  # every radius up to the pruning radius sees the same neighbours
        np.testing.assert_array_equal(fluid_edges(a, r_l0 * 0.05), fluid_edges(b, r_l0 * 0.05))


def test_resume_regenerates_only_what_is_missing(dataset, tmp_path):
    out = _copy(dataset, tmp_path)
    before = {k: scene_path(out, k).stat().st_mtime_ns for k in range(3)}
    reference = {k: read_trajectory(scene_path(out, k))["position"] for k in range(3)}
    scene_path(out, 1).unlink()  # a lost scene
    scene_path(out, 2).unlink()  # an interrupted one: only its .part (garbage) is left
    scene_path(out, 2).with_name("scene_00002.h5.part").write_bytes(b"half a file")
    (out / "metadata.json").unlink()
    _, meta = _generate(out)
    assert scene_path(out, 0).stat().st_mtime_ns == before[0]  # finished scene untouched
    for k in (1, 2):
        assert scene_path(out, k).stat().st_mtime_ns != before[k]
        np.testing.assert_array_equal(read_trajectory(scene_path(out, k))["position"], reference[k])
    assert sorted(p.name for p in (out / "scenes").iterdir()) == [f"scene_{k:05d}.h5" for k in range(3)]
    assert meta["statistics"] == dataset[2]["statistics"]
    # a finished file made with other settings is never mixed in
    with pytest.raises(LagfluidError, match="another configuration"):
        _generate(out, "steps=4")


def test_solver_keys_added_later_keep_old_fingerprints_at_their_neutral_value():
    from lagfluid.physics.settings import NEUTRAL_SOLVER_KEYS
    from lagfluid.tasks.generate import DataSpec

    spec = DataSpec.from_config(_compose(*TINY))
    before_the_keys = {k: v for k, v in spec.solver.items() if k not in NEUTRAL_SOLVER_KEYS}
    assert set(NEUTRAL_SOLVER_KEYS) <= set(spec.solver)  # the config has them, at their neutral values
    old = replace(spec, solver=before_the_keys)
    assert spec.fingerprint(0) == old.fingerprint(0)  # a dataset made before they existed still resumes
    for key, value in {"pressure_gradient": "corrected", "source_density_reference_dt": 0.002}.items():
        assert replace(spec, solver={**spec.solver, key: value}).fingerprint(0) != spec.fingerprint(0), key


def test_scene_index_jobs_make_one_scene_each_and_the_last_writes_metadata(tmp_path):
    assert _generate(tmp_path, "data.scene_index=2")[1] is None
    assert [p.name for p in (tmp_path / "scenes").iterdir()] == ["scene_00002.h5"]
    assert not (tmp_path / "metadata.json").exists()
    assert _generate(tmp_path, "data.scene_index=0")[1] is None
    meta = _generate(tmp_path, "data.scene_index=1")[1]
    assert meta is not None and (tmp_path / "metadata.json").is_file() and meta["num_scenes"] == 3


def test_materials_vary_per_scene_within_the_ranges(tmp_path):
    _, meta = _generate(
        tmp_path,
        "steps=2",
        "data.materials.vary=true",
        "data.materials.gravity=[1.0,100.0]",
        "data.materials.viscosity=[1e-4,0.1]",
    )
    g = [np.linalg.norm(s["gravity"]) for s in meta["scenes"]]
    nu = [s["viscosity"] for s in meta["scenes"]]
    assert all(1.0 <= x <= 100.0 for x in g) and all(1e-4 <= x <= 0.1 for x in nu)
    assert len(set(g)) == 3 and len(set(nu)) == 3
    assert all(s["gravity"][0] == s["gravity"][1] == 0 and s["gravity"][2] < 0 for s in meta["scenes"])
    ds = AdvectionSamples(tmp_path, split=None)
    for i in range(0, len(ds), 2):
        item = ds[i]
        assert float(item.viscosity) == pytest.approx(nu[int(item.scene)], rel=1e-6)
        assert float(item.gravity[0, 2]) == pytest.approx(-g[int(item.scene)], rel=1e-6)
        # a = nu lap(v) + g: on average the viscous term is small next to g
        assert float(item.y[:, 2].mean()) == pytest.approx(-g[int(item.scene)], rel=0.05)


def test_a_scene_stopped_by_the_guard_is_kept_apart_and_named(tmp_path):
    stopped = r"scene 0 \(scene_00000.h5, seed 0\) stopped: step \d+: .*reduce dt"
    with pytest.raises(LagfluidError, match=stopped):
        _generate(tmp_path, "dt=0.05", "num_scenes=1")
    assert (tmp_path / "scenes" / "scene_00000.failed.h5").is_file()
    assert not scene_path(tmp_path, 0).exists() and not (tmp_path / "metadata.json").exists()
    _generate(tmp_path, "steps=1", "num_scenes=1")  # fixed settings: the stale failure is cleared
    assert [p.name for p in (tmp_path / "scenes").iterdir()] == ["scene_00000.h5"]


@pytest.mark.parametrize(
    ("kind", "policy", "kept"),
    [("left_domain", "keep", True), ("left_domain", "error", False), ("courant", "keep", False)],
)
def test_mps_stopped_by_a_splash_out_of_the_domain_is_kept_shorter_only_when_asked(
    tmp_path, monkeypatch, kind, policy, kept
):
    # A guard that stops the solver at step 4 of 8 as if a particle had flown over the rim (or too fast).
    real_check = Guard.check

    def check(self, state):
        if state.step >= 4:
            raise RolloutError(f"step {state.step}: planted stop", kind=kind)
        real_check(self, state)

    monkeypatch.setattr(Guard, "check", check)
    args = ("num_scenes=1", "steps=8", "data.sample_every=2", f"data.on_fluid_leaving={policy}")
    if not kept:
        with pytest.raises(LagfluidError, match="planted stop"):
            _generate(tmp_path, *args)
        assert (tmp_path / "scenes" / "scene_00000.failed.h5").is_file()
        assert not scene_path(tmp_path, 0).exists()
        return
    _, meta = _generate(tmp_path, *args)
    scene = meta["scenes"][0]
    # steps 0, 2 sampled and stored; step 4's state failed the guard: the scene ends at step 3's state
    assert scene["stopped_at_step"] == 3 and "planted stop" in scene["stop_reason"]
    assert scene["samples"] == 2 and scene["frames"] == 2
    assert len(AdvectionSamples(tmp_path, split=None)) == 2


def test_on_fluid_leaving_refuses_other_values(tmp_path):
    with pytest.raises(LagfluidError, match=r"data.on_fluid_leaving must be 'error' or 'keep', got 'drop'"):
        _generate(tmp_path, "num_scenes=1", "data.on_fluid_leaving=drop")


def test_split_counts():
    f = {"train": 0.8, "valid": 0.1, "test": 0.1}
    assert split_counts(20, f) == {"train": 16, "valid": 2, "test": 2}
    assert split_counts(8, f) == {"train": 6, "valid": 1, "test": 1}
    assert split_counts(3, f) == {"train": 1, "valid": 1, "test": 1}
    assert split_counts(2, f) == {"train": 2, "valid": 0, "test": 0}
    with pytest.raises(LagfluidError, match="no training scene"):
        split_counts(2, {"train": 0.1, "valid": 0.5, "test": 0.4})


def test_metadata_without_a_key_it_needs_is_named(dataset, tmp_path):
    from lagfluid.models.training_range import training_range

    out = _copy(dataset, tmp_path)
    path, whole = out / "metadata.json", json.loads((out / "metadata.json").read_text())
    # a user's or hand-edited metadata.json: the file and the key in one line, not a KeyError from deep inside
    path.write_text(json.dumps({k: v for k, v in whole.items() if k != "l0"}))
    with pytest.raises(TrajectoryFileError, match=r"metadata\.json lacks the key 'l0'$"):
        training_range([out], {})  # what task=train reads first
    path.write_text(json.dumps({k: v for k, v in whole.items() if k != "splits"}))
    with pytest.raises(TrajectoryFileError, match=r"metadata\.json lacks the key 'splits'$"):
        TrajectoryWindows(out, "train", history=2)
    path.write_text(json.dumps({**whole, "splits": {"train": whole["splits"]["train"]}}))
    with pytest.raises(TrajectoryFileError, match=r"metadata\.json lacks the key 'splits\.valid'"):
        AdvectionSamples(out, "valid")
    path.write_text(json.dumps(whole))
    assert len(AdvectionSamples(out, "valid")) > 0


def test_bad_inputs_are_clear_errors(dataset, tmp_path):
    out = _copy(dataset, tmp_path)
    with pytest.raises(TrajectoryFileError, match="dataset directory not found"):
        AdvectionSamples(tmp_path / "nope")
    with pytest.raises(TrajectoryFileError, match=r"metadata\.json not found"):
        load_metadata(out / "scenes")
    with pytest.raises(LagfluidError, match="unknown split 'training'"):
        PressureSamples(out, split="training")
    with h5py.File(scene_path(out, 0), "a") as f:
        f.attrs["format_version"] = 99
    with pytest.raises(TrajectoryFileError, match=r"scene_00000\.h5 has format_version 99"):
        AdvectionSamples(out, split="train")
    with h5py.File(scene_path(out, 1), "a") as f:
        del f["samples/pressure"]
    with pytest.raises(TrajectoryFileError, match=r"scene_00001\.h5 lacks the group '/samples/pressure'"):
        PressureSamples(out, split="valid")
    scene_path(out, 2).write_bytes(b"not hdf5")
    with pytest.raises(TrajectoryFileError, match=r"cannot read .*scene_00002\.h5"):
        CollisionSamples(out, split="test")
    with pytest.raises(LagfluidError, match=r"data.scene_index must be in \[0, 3\)"):
        _generate(tmp_path / "x", "data.scene_index=3")
    with pytest.raises(LagfluidError, match="leave no training scene"):
        _generate(tmp_path / "x", "num_scenes=2", "data.splits.valid=0.5", "data.splits.test=0.5")
    assert check_command_line(["data=huge"]) == (
        "lagfluid: unknown data 'huge'; available: cpu, cpu_onpolicy, dlf_frames, dlf_frames_edge, paper, "
        "tiny"
    )


def test_top_level_steps_and_num_scenes_follow_the_task():
    assert _compose().steps == 500  # simulate keeps its default
    cfg = _compose("task=generate", "data=paper")
    assert (cfg.steps, cfg.num_scenes, cfg.data.sample_every) == (1000, 20, 4)
    cfg = _compose("task=generate", "data=cpu", "steps=7", "num_scenes=2")
    assert (cfg.steps, cfg.num_scenes) == (7, 2)


def test_cli_generate_with_the_issue_command(tmp_path):
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "lagfluid.run",
            "task=generate",
            "scene=random",
            "data=tiny",
            "num_scenes=2",
            "steps=3",
            f"data.out_dir={tmp_path / 'd'}",
            f"out_dir={tmp_path / 'run'}",
            "progress=false",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env={**__import__("os").environ, "OMP_NUM_THREADS": "1"},
    )
    assert out.returncode == 0, out.stderr
    meta = load_metadata(tmp_path / "d")
    assert meta["num_scenes"] == 2 and meta["steps"] == 3 and meta["counts"]["train"]["scenes"] == 2


def test_next_steps_are_the_solver_steps_after_each_sample(tmp_path):
    # sample_every=2, next_steps=3: a sample's 2nd next step is the next frame; the steps stop at 8, so the
    # last sample (step 6) has only 2 of its 3 and is left out
    out = tmp_path / "next"
    _, meta = _generate(out, "data.sample_every=2", "data.next_steps=3", "steps=8", "data.num_scenes=1")
    assert meta["next_steps"] == 3
    with h5py.File(out / meta["scenes"][0]["file"]) as f:
        nxt, frames = f["samples/next/position"][()], f["00000/position"][()]
        assert nxt.shape[:2] == (3, 3) and f["samples/step"].shape == (4,)
        for s in range(3):
            assert np.array_equal(nxt[s, 1], frames[s + 1])
        assert not np.array_equal(nxt[0, 0], frames[0]) and not np.array_equal(nxt[0, 0], nxt[0, 1])
    windows = StepWindows(out, None, steps=2, boundary_radius=None)
    item = windows[1]
    assert len(windows) == 3 and item.y.shape == (64, 2, 3)
    assert torch.equal(item.y[:, 1], torch.from_numpy(frames[2])) and item.bounds.shape == (1, 2, 3)
    assert torch.equal(item.pos[:64], torch.from_numpy(frames[1]))


def test_step_windows_name_a_dataset_without_next_steps(dataset):
    with pytest.raises(TrajectoryFileError, match=r"data\.next_steps=2"):
        StepWindows(dataset[0], "train", steps=2)


def test_generation_killed_by_sigkill_resumes_to_the_uninterrupted_dataset(tmp_path):
    """A real kill -9 in the middle of a scene: the rerun keeps finished scenes and redoes the rest."""
    killed, whole = tmp_path / "killed", tmp_path / "whole"
    command = [sys.executable, "-m", "lagfluid.run", *TINY, "steps=12", "threads=1", f"data.out_dir={killed}"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(command, cwd=REPO, env=env, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not scene_path(killed, 0).exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    assert proc.wait() == -signal.SIGKILL, "the generation ended before it could be killed"
    assert not (killed / "metadata.json").exists()
    first = scene_path(killed, 0).stat().st_mtime_ns
    subprocess.run(command, cwd=REPO, env=env, check=True, stderr=subprocess.DEVNULL)
    assert scene_path(killed, 0).stat().st_mtime_ns == first  # the finished scene was kept
    _, meta = _generate(whole, "steps=12")
    for k in range(3):
        a, b = read_trajectory(scene_path(whole, k)), read_trajectory(scene_path(killed, k))
        for name in ("position", "velocity", "pressure"):
            np.testing.assert_array_equal(a[name], b[name], err_msg=f"scene {k} {name}")
    assert json.loads((killed / "metadata.json").read_text())["statistics"] == meta["statistics"]


def test_a_recorded_training_range_keeps_only_the_quantities_asked_for():
    # GNS and CConv step by their own time (a frame, 20 ms): the data's solver dt in their checkpoint's
    # range made every rollout warn "trained on dt 0.002 s; this scene has 0.02".
    from lagfluid.models.training_range import range_from_checkpoint_meta

    meta = {"range": {"dt": [0.002, 0.002], "l0": [0.05, 0.05], "gravity": [9.8065, 9.8065]}}
    kept = range_from_checkpoint_meta(meta, ("l0", "gravity", "viscosity"))
    assert kept == {"l0": [0.05, 0.05], "gravity": [9.8065, 9.8065]}
    assert range_from_checkpoint_meta(meta) == meta["range"]
