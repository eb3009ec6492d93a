"""Starting a rollout from frame t of a trajectory (``scene=trajectory``) and a simulator's history."""

from __future__ import annotations

from typing import ClassVar

import h5py
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from lagfluid import registry
from lagfluid.data.store import TrajectoryWriter, read_trajectory
from lagfluid.errors import ConfigError, SceneError
from lagfluid.run import CONF_DIR
from lagfluid.state import ParticleState
from lagfluid.tasks.config import build_initial_state, initial_history
from lagfluid.tasks.simulate import simulate

STEPS = 8  # the original rollout: frames 0 .. 8, every step (write_every=1)


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


@pytest.fixture(scope="module")
def original(tmp_path_factory):
    """``experiment=debug`` MPS rollout of STEPS steps: (path, trajectory arrays)."""
    out = tmp_path_factory.mktemp("original")
    simulate(_compose("experiment=debug", f"steps={STEPS}", "threads=1", f"out_dir={out}"))
    path = out / "rollout.h5"
    return path, read_trajectory(path)


def _start(path, frame, *overrides):
    return _compose(
        "experiment=debug", "scene=trajectory", f"scene.path={path}", f"scene.frame={frame}", *overrides
    )


# --------------------------------------------------------------------------------------- (a) the state
@pytest.mark.parametrize("frame", [3, -1])
def test_the_state_is_the_stored_frame(original, frame):
    path, traj = original
    state = build_initial_state(_start(path, frame))
    k = frame % (STEPS + 1)
    nf = state.n_fluid
    assert nf == traj["position"].shape[1]
    assert torch.equal(state.pos[:nf], torch.from_numpy(traj["position"][k]))
    assert torch.equal(state.vel[:nf], torch.from_numpy(traj["velocity"][k]))
    assert torch.equal(state.pressure[:nf], torch.from_numpy(traj["pressure"][k]))
    assert torch.equal(state.pos[nf:], torch.from_numpy(traj["boundary_position"]))
    assert state.ptype[nf:].tolist() == traj["boundary_type"].tolist()
    assert not state.vel[nf:].any()
    assert state.time == traj["time"][k] and state.step == k
    # the file's parameters, unless the config overrides them
    attrs = traj["attrs"]
    assert (
        state.params.dt == attrs["dt"] and state.params.l0 == attrs["l0"] and state.params.dim == attrs["dim"]
    )
    assert list(state.params.gravity) == list(attrs["gravity"])
    assert build_initial_state(_start(path, frame, "scene.params.viscosity=0.0")).params.viscosity == 0.0
    assert build_initial_state(_start(path, frame, "dt=0.001")).params.dt == 0.001
    # the domain the original run was guarded in (run_attributes store it)
    assert torch.equal(state.bounds, build_initial_state(_compose("experiment=debug")).bounds)


# -------------------------------------------------------------------------- (b) continuing MPS from k
def test_continuing_mps_from_frame_k_reproduces_the_original(original, tmp_path):
    path, traj = original
    k, n = 3, STEPS - 3
    metrics = simulate(_start(path, k, f"steps={n}", "threads=1", f"out_dir={tmp_path}"))
    assert metrics["complete"] and metrics["steps"] == n
    cont = read_trajectory(tmp_path / "rollout.h5")
    np.testing.assert_array_equal(cont["time"], traj["time"][k:])
    # The run is float32 like the file, so frame k is restored exactly; what differs is the PPE's warm start
    # (wall pressures are not stored and start at 0) and the rebuilt neighbour lists' summation order, so
    # CG stops elsewhere within its tolerance. Measured over 5 steps: 3e-8 m, 2e-7 m/s, 0.01 Pa of ~3 kPa.
    np.testing.assert_allclose(cont["position"], traj["position"][k:], rtol=0, atol=1e-6)  # 2e-5 l0
    np.testing.assert_allclose(cont["velocity"], traj["velocity"][k:], rtol=0, atol=1e-5)
    np.testing.assert_allclose(cont["pressure"], traj["pressure"][k:], rtol=0, atol=1.0)
    assert not np.array_equal(cont["position"][-1], traj["position"][0])  # the fluid did move


# ------------------------------------------------------------------------- (c) a simulator's history
class _HistorySimulator:
    """Free fall that records what ``reset`` received; the whole Simulator contract."""

    name = "history2"
    history_length = 2
    max_courant = None
    parameters = 0
    last_fields = None
    received: ClassVar[list[ParticleState]] = []  # what the last reset got: [state, *history]

    def __init__(self, cfg, dt=None):
        self.dt = dt
        self.last_timings: dict[str, float] = {}
        self.last_info: dict[str, float] = {}

    def reset(self, state: ParticleState, history=()) -> None:
        type(self).received = [state, *history]

    def step(self, state: ParticleState, *, record: bool = False) -> ParticleState:
        nf, dt = state.n_fluid, state.params.dt
        vel = state.vel.clone()
        vel[:nf] += dt * torch.tensor(state.params.gravity, dtype=vel.dtype)
        pos = state.pos.clone()
        pos[:nf] += dt * vel[:nf]
        return ParticleState(
            pos=pos, vel=vel, ptype=state.ptype, params=state.params, time=state.time + dt,
            step=state.step + 1, bounds=state.bounds, check=False,
        )  # fmt: skip

    def attributes(self) -> dict:
        return {}


@pytest.fixture
def history_model(monkeypatch):
    """Register ``history2`` (own dt None) and ``history2_dt4`` (own dt 0.004 s) for this test."""
    monkeypatch.setitem(registry._REGISTERED, "history2", lambda cfg: _HistorySimulator(cfg))
    monkeypatch.setitem(registry._REGISTERED, "history2_dt4", lambda cfg: _HistorySimulator(cfg, dt=0.004))
    _HistorySimulator.received = []
    return _HistorySimulator


@pytest.mark.parametrize(("frame", "expected"), [(5, [3, 4]), (1, [0]), (0, [])])
def test_reset_receives_the_frames_before_k(original, history_model, tmp_path, frame, expected):
    path, traj = original
    cfg = _start(path, frame, "steps=2", f"out_dir={tmp_path}")
    cfg.model.name = "history2"
    simulate(cfg)
    state, *history = history_model.received
    assert state.time == traj["time"][frame]
    assert [h.step for h in history] == expected  # oldest first
    for h, k in zip(history, expected, strict=True):
        nf = h.n_fluid
        assert h.time == traj["time"][k]
        assert torch.equal(h.pos[:nf], torch.from_numpy(traj["position"][k]))
        assert torch.equal(h.vel[:nf], torch.from_numpy(traj["velocity"][k]))
        assert torch.equal(h.pos[nf:], state.pos[nf:]) and torch.equal(h.ptype, state.ptype)
        assert h.params == state.params


def test_no_history_for_scenes_built_from_scratch(history_model):
    cfg = _compose("experiment=debug")
    cfg.model.name = "history2"
    from lagfluid.tasks.config import build_simulator

    assert initial_history(cfg, build_simulator(cfg)) == []


# ------------------------------------------------------------------------------ (d) the clear errors
def test_frame_out_of_range_names_the_valid_range(original):
    path, _ = original
    for frame in (STEPS + 1, -(STEPS + 2)):
        with pytest.raises(
            SceneError, match=rf"frame {frame} is out of range .*valid frames are 0 \.\. {STEPS}"
        ):
            build_initial_state(_start(path, frame))


def test_a_history_at_another_spacing_names_both(original, history_model, tmp_path):
    path, _ = original
    cfg = _start(path, 4, "steps=2", f"out_dir={tmp_path / 'out'}")
    cfg.model.name = "history2_dt4"  # steps by 0.004 s; the file's frames are 0.002 s apart
    with pytest.raises(ConfigError, match=r"0\.002 s apart, but the simulator steps by dt=0\.004 s"):
        simulate(cfg)
    assert not (tmp_path / "out").exists()  # failed before out_dir was touched


def test_frames_not_uniformly_spaced_are_refused_for_a_history(original, history_model, tmp_path):
    _, traj = original
    uneven = tmp_path / "uneven.h5"
    nf = traj["position"].shape[1]
    attrs = {key: traj["attrs"][key] for key in ("dt", "l0", "gravity", "viscosity", "density", "dim")}
    with TrajectoryWriter(uneven, nf, traj["boundary_position"], traj["boundary_type"], attrs) as w:
        for k, time in zip((0, 1, 3), (0.0, 0.002, 0.006), strict=True):  # frames 0, 1 and the step after 2
            w.append(time, traj["position"][k], traj["velocity"][k], traj["pressure"][k])
    cfg = _start(uneven, 2, "steps=1", f"out_dir={tmp_path / 'out'}")
    cfg.model.name = "history2"
    with pytest.raises(SceneError, match=r"frames 0 \.\. 2 of .* are not uniformly spaced"):
        simulate(cfg)
    cfg.model.name = "mps"  # a simulator without history starts from any frame
    assert simulate(cfg)["complete"]


def test_missing_or_foreign_files_are_clear_errors(tmp_path):
    with pytest.raises(SceneError, match=r"trajectory file not found: .*nope\.h5"):
        build_initial_state(_start(tmp_path / "nope.h5", 0))
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f.create_dataset("x", data=[1.0])
    with pytest.raises(SceneError, match="is not a lagfluid trajectory file"):
        build_initial_state(_start(foreign, 0))
    text = tmp_path / "text.h5"
    text.write_text("not hdf5")
    with pytest.raises(SceneError, match=r"cannot read .* as HDF5"):
        build_initial_state(_start(text, 0))
    with pytest.raises(SceneError, match=r"scene=trajectory needs scene\.path="):
        build_initial_state(_compose("scene=trajectory"))


# ------------------------------------------------------------------------- evaluate: the same frame t
def test_evaluate_starts_model_and_reference_at_frame_k(original, tmp_path):
    from lagfluid.tasks.evaluate.reference import reference_key
    from lagfluid.tasks.evaluate.task import evaluate

    path, traj = original
    k = 4
    cfg = _start(
        path, k, "task=evaluate", "steps=2", "threads=1", "evaluate.figures=false",
        f"out_dir={tmp_path / 'eval'}", f"evaluate.reference_dir={tmp_path / 'ref'}",
    )  # fmt: skip
    metrics = evaluate(cfg)
    assert metrics["complete"] and metrics["frames_compared"] == 3
    assert metrics["frames"]["position_mse_m2"][0] == 0.0  # both start from frame k
    reference = read_trajectory(metrics["reference"]["path"])
    np.testing.assert_array_equal(reference["time"], traj["time"][k : k + 3])
    np.testing.assert_array_equal(reference["position"][0], traj["position"][k])
    key = metrics["reference"]["key"]
    assert key["scene"]["path"] == str(path) and key["scene"]["frame"] == k and "scene_file_sha256" in key
    assert reference_key(_start(path, k + 1, "task=evaluate", "steps=2")) != reference_key(cfg)
