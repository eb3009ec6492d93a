"""task=evaluate: a model against the MPS reference (lagfluid.tasks.evaluate), dam_small, a few steps."""

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import pytest
import torch
from hydra import compose, initialize_config_dir

from lagfluid.errors import ConfigError
from lagfluid.registry import UnknownNameError
from lagfluid.run import CONF_DIR, check_command_line
from lagfluid.tasks.evaluate import (
    cached_reference_problem,
    evaluate,
    expected_frames,
    key_hash,
    reference_key,
)

STEPS = 4
OUTPUTS = ("rollout.h5", "metrics.json", "error_vs_time.png", "pressure_slice.png")
BASE = ("task=evaluate", "scene=dam_small", f"steps={STEPS}", "threads=1", "progress=false")


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(
            config_name="config",
            overrides=[*BASE, "evaluate.figures=false", *overrides],
        )


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    """``python -m lagfluid.run task=evaluate model=mps ...`` once; the reference cache it fills is shared."""
    root = tmp_path_factory.mktemp("evaluate")
    out, ref = root / "mps", root / "reference"
    cmd = [
        sys.executable,
        "-m",
        "lagfluid.run",
        "task=evaluate",
        "model=mps",
        "scene=dam_small",
        f"steps={STEPS}",
        "threads=1",
        "progress=false",
        f"out_dir={out}",
        f"evaluate.reference_dir={ref}",
        "evaluate.horizons=[1,2,4,100]",
    ]
    done = subprocess.run(
        cmd, capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"}
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return out, ref, json.loads((out / "metrics.json").read_text())


def test_cli_evaluate_writes_every_output(cli_run):
    out, ref, metrics = cli_run
    for name in OUTPUTS:
        assert (out / name).stat().st_size > 1000, name
    assert metrics["task"] == "evaluate" and metrics["model"] == "mps" and metrics["complete"]
    assert metrics["steps"] == STEPS and metrics["frames_compared"] == STEPS + 1
    reference = Path(metrics["reference"]["path"])
    assert reference.parent.parent == ref and reference.parent.name.startswith("dam_small-")
    assert metrics["reference"]["reused"] is False
    assert reference.parent.name.endswith(metrics["reference"]["key_hash"])
    frames = metrics["frames"]
    for key in ("chamfer_mm", "position_mse_m2", "kinetic_energy_error_rel_peak", "ppe_relative_residual"):
        assert len(frames[key]) == STEPS + 1, key
    for key in ("density_error", "velocity_divergence_per_s", "kinetic_energy_J"):
        assert len(frames[key]["model"]) == len(frames[key]["reference"]) == STEPS + 1
    assert metrics["pressure_slice"]["particles"]["model"] > 0
    assert metrics["pressure_slice"]["field"] == "pressure"  # MPS predicts a pressure


def test_mps_against_itself_has_zero_error(cli_run):
    _, _, metrics = cli_run
    frames = metrics["frames"]
    # same solver, same initial state, same settings: the two rollouts are identical, bit for bit
    assert frames["position_mse_m2"] == [0.0] * (STEPS + 1)
    assert frames["chamfer_mm"] == [0.0] * (STEPS + 1)
    assert frames["kinetic_energy_error_rel_peak"] == [0.0] * (STEPS + 1)
    assert frames["density_error"]["model"] == frames["density_error"]["reference"]
    assert frames["kinetic_energy_J"]["model"][-1] > 0  # the fluid moves: zero error is not zero motion
    horizons = metrics["summary"]["position_mse_horizons_m2"]
    assert horizons["at_step"] == {"1": 0.0, "2": 0.0, "4": 0.0}  # 100 is past the run
    # one-step errors: undefined at frame 0 (no step), ~0 after (the exact stages themselves)
    assert frames["advection_nmae"][0] is None and frames["ppe_relative_residual"][0] is None
    assert all(v is not None and v < 1e-6 for v in frames["advection_nmae"][1:])
    assert all(v is not None and v < 1e-5 for v in frames["ppe_relative_residual"][1:])


def test_reference_is_reused_when_the_config_matches(cli_run, tmp_path):
    _, ref, first = cli_run
    path = Path(first["reference"]["path"])
    before = path.stat().st_mtime_ns
    cfg = _compose("model=mps", f"out_dir={tmp_path}", f"evaluate.reference_dir={ref}")
    metrics = evaluate(cfg)
    assert metrics["reference"]["reused"] is True and metrics["reference"]["path"] == str(path)
    assert path.stat().st_mtime_ns == before
    assert metrics["frames"]["position_mse_m2"] == [0.0] * (STEPS + 1)


def test_a_cached_reference_with_a_damaged_chunk_is_recomputed_not_a_raw_h5py_error(cli_run, tmp_path):
    _, _, first = cli_run
    cached = Path(first["reference"]["path"])
    cfg = _compose("model=mps", f"out_dir={tmp_path / 'out'}", f"evaluate.reference_dir={tmp_path / 'ref'}")
    copy = tmp_path / "ref" / cached.parent.name / "rollout.h5"
    copy.parent.mkdir(parents=True)
    shutil.copy(cached, copy)
    with h5py.File(copy, "r") as f:  # the last frame's chunk of the positions
        chunk = f["00000"]["position"].id.get_chunk_info(STEPS)
    with copy.open("r+b") as f:
        f.seek(chunk.byte_offset + chunk.size // 2)
        f.write(b"\x00\xff" * 8)
    key, frames = reference_key(cfg), expected_frames(STEPS, 1)
    assert "unreadable dataset position" in cached_reference_problem(copy, key, frames)
    metrics = evaluate(cfg)
    assert metrics["reference"]["reused"] is False and metrics["reference"]["path"] == str(copy)
    assert cached_reference_problem(copy, key, frames) is None  # recomputed in place


def test_reference_is_recomputed_for_another_dt(cli_run, tmp_path):
    _, ref, first = cli_run
    cfg = _compose("model=mps", "dt=0.001", f"out_dir={tmp_path}", f"evaluate.reference_dir={ref}")
    metrics = evaluate(cfg)
    assert metrics["reference"]["reused"] is False
    assert metrics["reference"]["path"] != first["reference"]["path"]
    assert metrics["reference"]["key"]["dt"] == 0.001 and metrics["dt"] == 0.001


def test_an_incomplete_or_foreign_cache_is_recomputed_not_used(cli_run, tmp_path):
    _, ref, first = cli_run
    path = Path(first["reference"]["path"])
    cfg = _compose("model=mps", f"out_dir={tmp_path}", f"evaluate.reference_dir={ref}")
    key, frames = reference_key(cfg), expected_frames(STEPS, 1)
    assert key_hash(key) == first["reference"]["key_hash"]
    assert cached_reference_problem(path, key, frames) is None
    assert "frames" in cached_reference_problem(path, key, frames + 1)
    assert "another configuration" in cached_reference_problem(path, {**key, "dt": 1.0}, frames)
    assert "not found" in cached_reference_problem(path.with_name("missing.h5"), key, frames)
    with h5py.File(path, "a") as f:  # as if the run had been interrupted
        f["00000"].attrs["complete"] = False
    assert "incomplete" in cached_reference_problem(path, key, frames)
    metrics = evaluate(cfg)
    assert metrics["reference"]["reused"] is False and metrics["reference"]["path"] == str(path)
    assert cached_reference_problem(path, key, frames) is None  # recomputed, complete and stamped again


def test_fgn_original_against_mps(cli_run, tmp_path):
    _, ref, _ = cli_run
    cfg = _compose(  # the authors' networks as shipped (the model's default weights)
        "model=fgn_original",
        f"out_dir={tmp_path}",
        f"evaluate.reference_dir={ref}",
        "evaluate.figures=true",
        "evaluate.slice.time=0.0035",
        "evaluate.slice.axis=x",
    )
    metrics = evaluate(cfg)
    frames = metrics["frames"]
    assert metrics["complete"] and metrics["reference"]["reused"] is True  # the reference is model-free
    assert frames["position_mse_m2"][0] == 0.0 and frames["position_mse_m2"][-1] > 0
    assert frames["chamfer_mm"][-1] > 0
    # learned stages: finite, non-zero one-step errors against the exact stages
    assert all(0 < v < math.inf for v in frames["advection_nmae"][1:])
    assert all(0 < v < math.inf for v in frames["ppe_relative_residual"][1:])
    assert metrics["pressure_slice"]["step"] == 2 and metrics["pressure_slice"]["axis"] == "x"  # nearest
    assert (tmp_path / "pressure_slice.png").is_file() and (tmp_path / "error_vs_time.png").is_file()
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["summary"]["chamfer_mm"]["max"] == pytest.approx(max(frames["chamfer_mm"]))


def test_hybrid_one_step_errors_follow_its_stages(cli_run, tmp_path, untrained_weights):
    # exact advection and collision, an untrained pressure network: the advection error is the exact
    # stage's (~0), the PPE residual is the network's (far from 0)
    _, ref, _ = cli_run
    cfg = _compose(
        "model=hybrid",
        f"model.weights={untrained_weights}",
        f"out_dir={tmp_path}",
        f"evaluate.reference_dir={ref}",
    )
    metrics = evaluate(cfg)
    frames = metrics["frames"]
    assert metrics["reference"]["reused"] is True and len(frames["step"]) >= 2
    assert all(v < 1e-6 for v in frames["advection_nmae"][1:])
    assert all(v > 1e-2 for v in frames["ppe_relative_residual"][1:])


class _Exploding:
    """A plugin-style simulator (no intermediates): MPS whose velocities turn NaN at step 2."""

    name = "exploding"
    dt = None
    history_length = 0
    max_courant = None
    parameters = 0
    last_fields = None

    def __init__(self, cfg):
        from lagfluid.models.mps_simulator import build_mps

        self.inner = build_mps(cfg)
        self.last_info = {}

    @property
    def last_timings(self):
        return self.inner.last_timings

    def reset(self, state, history=()):
        self.inner.reset(state)

    def step(self, state, *, record=False):
        new = self.inner.step(state)
        if new.step >= 2:
            new.vel[0] = float("nan")
        return new

    def attributes(self):
        return {}


def test_a_model_that_blows_up_is_evaluated_up_to_the_stop(cli_run, tmp_path, monkeypatch):
    from lagfluid import registry

    _, ref, _ = cli_run
    monkeypatch.setitem(registry._REGISTERED, "exploding", _Exploding)
    cfg = _compose("model.name=exploding", f"out_dir={tmp_path}", f"evaluate.reference_dir={ref}")
    metrics = evaluate(cfg)
    assert metrics["complete"] is False and "non-finite velocity" in metrics["stop_reason"]
    assert metrics["frames"]["step"] == [0, 1] and metrics["steps"] == 1
    assert metrics["frames"]["position_mse_m2"] == [0.0, 0.0]
    # a simulator without recorded intermediates has no one-step errors
    assert all(math.isnan(v) for v in metrics["frames"]["advection_nmae"])
    assert json.loads((tmp_path / "metrics.json").read_text())["frames"]["advection_nmae"] == [None, None]


class _Frozen:
    """A simulator that never moves the fluid: its errors against MPS are computable by hand."""

    name, dt, history_length, max_courant, parameters, last_fields = "frozen", None, 0, None, 0, None

    def __init__(self, cfg):
        self.last_info, self.last_timings = {}, {}

    def reset(self, state, history=()):
        pass

    def step(self, state, *, record=False):
        nf = state.n_fluid
        return state.advanced_fluid(state.pos[:nf], torch.zeros_like(state.vel[:nf]), state.params.dt)

    def attributes(self):
        return {}


def test_a_model_that_differs_from_mps_gets_the_errors_computed_by_hand(cli_run, tmp_path, monkeypatch):
    """Unlike MPS against itself, these numbers are not zero: each is recomputed here from the files."""
    from lagfluid import registry
    from lagfluid.data.store import read_trajectory
    from lagfluid.metrics import chamfer_distance, kinetic_energy, position_mse

    _, ref_dir, _ = cli_run
    monkeypatch.setitem(registry._REGISTERED, "frozen", _Frozen)
    metrics = evaluate(
        _compose("model.name=frozen", f"out_dir={tmp_path}", f"evaluate.reference_dir={ref_dir}")
    )
    ref = read_trajectory(metrics["reference"]["path"])
    model = read_trajectory(tmp_path / "rollout.h5")
    start, mass = model["position"][0], 1000.0 * 0.05**3
    frames = metrics["frames"]
    assert frames["step"] == list(range(STEPS + 1))
    for k in range(STEPS + 1):
        assert frames["chamfer_mm"][k] == pytest.approx(
            1e3 * chamfer_distance(start, ref["position"][k]), rel=1e-6
        )
        assert frames["position_mse_m2"][k] == pytest.approx(
            position_mse(start, ref["position"][k]), rel=1e-6
        )
        energy = kinetic_energy(ref["velocity"][k], mass)
        assert frames["kinetic_energy_J"]["reference"][k] == pytest.approx(energy, rel=1e-6)
    assert frames["chamfer_mm"][-1] > 0.1 and frames["position_mse_m2"][-1] > 0  # MPS's column did move
    assert frames["kinetic_energy_J"]["model"][1:] == [0.0] * STEPS
    # |0 - E(t)| / max E: the frozen model's error grows with MPS's energy, 1 at MPS's peak
    energies = [kinetic_energy(ref["velocity"][k], mass) for k in range(STEPS + 1)]
    expected = [e / max(energies) for e in energies]
    assert frames["kinetic_energy_error_rel_peak"] == pytest.approx(expected, rel=1e-6)
    # the frozen fluid keeps its initial density error at every frame
    assert frames["density_error"]["model"] == pytest.approx(
        [frames["density_error"]["model"][0]] * (STEPS + 1)
    )


class _FrozenWithoutPressure(_Frozen):
    name, predicts_pressure = "frozen_no_pressure", False


def test_the_figures_of_a_model_without_pressure_show_speed(cli_run, tmp_path, monkeypatch):
    from lagfluid import registry
    from lagfluid.viz import field_values

    _, ref_dir, _ = cli_run
    monkeypatch.setitem(registry._REGISTERED, "frozen_no_pressure", _FrozenWithoutPressure)
    seen = []
    monkeypatch.setattr(
        "lagfluid.tasks.evaluate.figures.field_values",
        lambda *args: seen.append(args[0]) or field_values(*args),
    )
    cfg = _compose(
        "model.name=frozen_no_pressure",
        f"out_dir={tmp_path}",
        f"evaluate.reference_dir={ref_dir}",
        "evaluate.figures=true",
    )
    metrics = evaluate(cfg)
    assert metrics["pressure_slice"]["field"] == "speed" and seen == ["speed", "speed"]  # both panels
    assert (tmp_path / "pressure_slice.png").is_file()


def test_unknown_model_is_a_clear_error_before_any_reference_run(tmp_path):
    assert check_command_line(["task=evaluate", "model=mps"]) is None
    assert "unknown model 'nope'" in check_command_line(["task=evaluate", "model=nope"])
    cfg = _compose("model=mps", "model.name=nope", f"out_dir={tmp_path / 'out'}")
    cfg.evaluate.reference_dir = str(tmp_path / "reference")
    with pytest.raises(UnknownNameError, match=r"unknown model 'nope'; available: .*mps"):
        evaluate(cfg)
    assert not (tmp_path / "reference").exists()


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("evaluate.slice.axis=z", "evaluate.slice.axis must be x or y.*'z'"),
        ("evaluate.horizons=[0,10]", r"evaluate.horizons must be steps >= 1, got \[0, 10\]"),
        ("evaluate.slice.width=0", "evaluate.slice.width must be > 0"),
        ("evaluate.slice.time=-1", "evaluate.slice.time must be a time >= 0"),
        ("steps=0", "steps >= 1"),
    ],
)
def test_bad_evaluate_options_name_the_value(override, message, tmp_path):
    cfg = _compose("model=mps", override, f"out_dir={tmp_path}", f"evaluate.reference_dir={tmp_path}/ref")
    with pytest.raises(ConfigError, match=message):
        evaluate(cfg)
