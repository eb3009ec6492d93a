"""Every metric against a case computed by hand (lagfluid.metrics)."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from lagfluid.metrics import (
    MetricInputError,
    chamfer_distance,
    field_metrics,
    kinetic_energy,
    kinetic_energy_error,
    mse_horizons,
    normalized_mae,
    position_mse,
    summarize,
)
from lagfluid.physics.reference import exact_context, exact_ppe, mps_constants, ppe_relative_residual
from lagfluid.physics.settings import SolverSettings
from lagfluid.run import CONF_DIR
from lagfluid.state import ParticleState
from lagfluid.tasks.config import build_initial_state, build_simulator


# ------------------------------------------------------------------------------------------- field metrics
def test_density_error_and_divergence_of_two_particles_by_hand():
    # l0 = 1, re = 2.1: two particles 1 apart have w = 2.1/1 - 1 = 1.1, so n = 1.1 each; with n0 = 1 both are
    # interior (1.1 >= 0.97) and |n/n0 - 1| = 0.1. v = (0,0,0) and (1,0,0):
    # div_i = 3/n0 * (v_j - v_i).(x_j - x_i)/r^2 * w = 3 * 1 * 1.1 = 3.3 for both. A third fluid particle far
    # away has n = 0 (free surface) and takes no part.
    pos = torch.tensor([[0.0, 0, 0], [1, 0, 0], [10, 0, 0]], dtype=torch.float64)
    vel = torch.tensor([[0.0, 0, 0], [1, 0, 0], [5, 5, 5]], dtype=torch.float64)
    ptype = torch.ones(3, dtype=torch.int64)
    m = field_metrics(pos, vel, ptype, n0=1.0, re_density=2.1, re_gradient=2.1)
    assert m.interior_particles == 2
    assert m.density_error == pytest.approx(0.1, rel=1e-12)
    assert m.velocity_divergence == pytest.approx(3.3, rel=1e-12)


def test_density_error_averages_compression_and_expansion_as_magnitudes():
    # Two pairs far apart, n0 = 1.05, re = 2.1 (l0 = 1). Pair 1 at spacing 1: n = 1.1, n/n0 - 1 = +0.0476.
    # Pair 2 at spacing r with w(r) = 2.1/r - 1 = 0.98 n0: n/n0 - 1 = -0.02 (still interior: >= 0.97).
    # The error is the mean magnitude, (2 * 0.0476 + 2 * 0.02) / 4; a signed mean would give 0.0138.
    r = 2.1 / (1 + 0.98 * 1.05)
    pos = torch.tensor([[0.0, 0, 0], [1, 0, 0], [10, 0, 0], [10 + r, 0, 0]], dtype=torch.float64)
    m = field_metrics(pos, torch.zeros_like(pos), torch.ones(4, dtype=torch.int64), 1.05, 2.1, 2.1)
    assert m.interior_particles == 4
    assert m.density_error == pytest.approx((2 * (1.1 / 1.05 - 1) + 2 * 0.02) / 4, rel=1e-12)


def test_velocity_divergence_averages_expansion_and_compression_as_magnitudes():
    # Two pairs far apart, l0 = 1, re = 2.1, n0 = 1: every particle sees w = 2.1/1 - 1 = 1.1 (interior).
    # Pair 1 separates at 1 m/s: div = 3/n0 * (+1) * 1.1 = +3.3 for both; pair 2 closes at 1 m/s: -3.3.
    # The metric is the mean magnitude, 3.3; the magnitude of the mean would be 0.
    pos = torch.tensor([[0.0, 0, 0], [1, 0, 0], [10, 0, 0], [11, 0, 0]], dtype=torch.float64)
    vel = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 0, 0], [-1, 0, 0]], dtype=torch.float64)
    m = field_metrics(pos, vel, torch.ones(4, dtype=torch.int64), n0=1.0, re_density=2.1, re_gradient=2.1)
    assert m.interior_particles == 4
    assert m.velocity_divergence == pytest.approx(3.3, rel=1e-12)


def test_kinetic_energy_of_runs_at_two_spacings_uses_each_runs_particle_mass(tmp_path):
    """The same block moving at 1 m/s as 8 particles of l0 = 0.05 and as 1 of l0 = 0.1: the same energy."""
    from lagfluid.data.store import TrajectoryWriter
    from lagfluid.physics.settings import SolverSettings
    from lagfluid.tasks.evaluate.compare import compare

    def write(path, l0, n):
        k = np.arange(n) * l0
        pos = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3) + 1.0
        attrs = {"dt": 0.002, "l0": l0, "density": 1000.0, "dim": 3}
        with TrajectoryWriter(path, len(pos), np.zeros((1, 3)), np.array([2]), attrs) as w:
            for step in range(3):
                t = 0.002 * step
                moving = np.tile([1.0, 0, 0], (len(pos), 1))
                w.append(t, pos + moving * t, moving, np.zeros(len(pos)))
        return path

    fine, coarse = write(tmp_path / "fine.h5", 0.05, 2), write(tmp_path / "coarse.h5", 0.1, 1)
    out = compare(coarse, fine, SolverSettings())
    energy = 0.5 * 1000.0 * 0.1**3  # J: 1 kg of water at 1 m/s
    assert out["kinetic_energy_J"]["model"] == pytest.approx([energy] * 3, rel=1e-6)
    assert out["kinetic_energy_J"]["reference"] == pytest.approx([energy] * 3, rel=1e-6)
    assert out["kinetic_energy_error_rel_peak"] == pytest.approx([0.0] * 3, abs=1e-6)


def test_frames_meet_the_reference_despite_float32_drift_and_a_miss_is_said(tmp_path, caplog):
    """A 16 ms model whose dt reads 0.016000001 (float32) meets a reference stored every 16 ms at every frame
    (1e-9 s of drift a frame); frames 5 ms apart meet one stored every 16 ms at t = 0 only, and the log says
    the metrics are of that frame alone instead of passing a Chamfer distance of 0 off as a perfect model."""
    from lagfluid.data.store import TrajectoryWriter
    from lagfluid.physics.settings import SolverSettings
    from lagfluid.tasks.evaluate.compare import compare

    pos = np.stack(np.meshgrid(*[np.arange(3) * 0.05] * 3, indexing="ij"), -1).reshape(-1, 3) + 1.0

    def write(path, dt, frames, every):
        attrs = {"dt": dt, "l0": 0.05, "density": 1000.0, "dim": 3}
        with TrajectoryWriter(path, len(pos), np.zeros((1, 3)), np.array([2]), attrs) as w:
            for k in range(frames):
                w.append(dt * every * k, pos, np.zeros_like(pos), np.zeros(len(pos)))
        return path

    ref = write(tmp_path / "ref.h5", 0.002, 64, 8)  # every 16 ms to 1 s
    with caplog.at_level("WARNING", logger="lagfluid.tasks.evaluate.compare"):
        out = compare(write(tmp_path / "drift.h5", 0.016000001, 60, 1), ref, SolverSettings())
    assert out["step"] == list(range(60)) and not caplog.records
    with caplog.at_level("WARNING", logger="lagfluid.tasks.evaluate.compare"):
        out = compare(write(tmp_path / "off.h5", 0.005, 5, 1), ref, SolverSettings())
    assert out["step"] == [0] and "5 stored frames, but 1 at a time" in caplog.text


def test_field_metrics_without_interior_particles_are_zero():
    pos = torch.tensor([[0.0, 0, 0], [10, 0, 0]], dtype=torch.float64)
    m = field_metrics(pos, torch.zeros_like(pos), torch.ones(2, dtype=torch.int64), 1.0, 2.1, 2.1)
    assert (m.density_error, m.velocity_divergence, m.interior_particles) == (0.0, 0.0, 0)


def test_summarize_mean_and_max_over_frames():
    assert summarize([1.0, 2.0, 6.0]) == {"mean": 3.0, "max": 6.0}
    assert math.isnan(summarize([1.0, float("nan")])["mean"])
    assert summarize([float("nan"), 1.0, 3.0, math.inf], finite_only=True) == {"mean": 2.0, "max": 3.0}
    assert all(math.isnan(v) for v in summarize([]).values())


# ------------------------------------------------------------------------------------------- Chamfer
def test_chamfer_distance_by_hand_and_asymmetric():
    pred = np.array([[0.0, 0, 0], [1, 0, 0]])
    ref = np.array([[0.0, 0, 0.5], [3, 0, 0]])
    # pred -> ref: 0.5 and |(1, 0, -0.5)| = sqrt(1.25); ref -> pred: 0.5 and 2
    assert chamfer_distance(pred, ref) == pytest.approx((0.5 + math.sqrt(1.25)) / 2, rel=1e-15)
    assert chamfer_distance(ref, pred) == pytest.approx(1.25, rel=1e-15)
    assert chamfer_distance(torch.tensor(pred), torch.tensor(pred)) == 0.0


def test_chamfer_distance_matches_brute_force():
    rng = np.random.default_rng(0)
    a, b = rng.random((50, 3)), rng.random((70, 3))
    brute = np.linalg.norm(a[:, None] - b[None], axis=2).min(axis=1).mean()
    assert chamfer_distance(a, b) == pytest.approx(brute, rel=1e-12)


@pytest.mark.parametrize(
    ("pred", "ref", "match"),
    [
        (np.zeros((0, 3)), np.zeros((2, 3)), "non-empty"),
        (np.zeros((2, 3)), np.zeros((2, 2)), "dimension"),
        (np.full((2, 3), np.nan), np.zeros((2, 3)), "NaN"),
    ],
)
def test_chamfer_distance_rejects_bad_input(pred, ref, match):
    with pytest.raises(MetricInputError, match=match):
        chamfer_distance(pred, ref)


# ------------------------------------------------------------------------------------------- position MSE
def test_position_mse_by_hand():
    pred = np.array([[0.0, 0, 0], [1, 1, 1]])
    ref = np.array([[0.0, 0, 1], [1, 1, 1]])
    # one coordinate off by 1 among N D = 6
    assert position_mse(pred, ref) == pytest.approx(1 / 6, rel=1e-15)
    assert position_mse(ref, ref) == 0.0
    with pytest.raises(MetricInputError, match="particle by particle"):
        position_mse(pred, ref[:1])


def test_mse_horizons_at_and_mean_to_step():
    out = mse_horizons([0, 1, 2, 5, 10], [0.0, 1.0, 2.0, 3.0, 4.0], [1, 5, 50])
    assert out["at_step"] == {"1": 1.0, "5": 3.0}  # 50 is past the run
    assert out["mean_to_step"] == {"1": 1.0, "5": 2.0}  # mean over steps 1, 2, 5 (not frame 0)
    with pytest.raises(MetricInputError, match="horizons"):
        mse_horizons([0, 1], [0.0, 1.0], [0])


# ------------------------------------------------------------------------------------------- kinetic energy
def test_kinetic_energy_by_hand():
    vel = np.array([[1.0, 0, 0], [0, 2, 0]])
    assert kinetic_energy(vel, particle_mass=2.0) == pytest.approx(0.5 * 2 * (1 + 4))
    with pytest.raises(MetricInputError, match="particle_mass"):
        kinetic_energy(vel, 0.0)


def test_kinetic_energy_error_is_relative_to_the_references_peak_not_to_each_frame():
    # A dam at rest at t = 0: the reference's energy starts at 0 and peaks at 4 J. At frame 1 the model has
    # 0.07 J against 0.01 J: 600 % of that frame's energy, but 0.06 / 4 = 1.5 % of the peak.
    model = [0.0, 0.07, 1.5, 3.0, 4.4]
    ref = [0.0, 0.01, 1.0, 4.0, 3.6]
    assert kinetic_energy_error(model, ref) == pytest.approx([0.0, 0.015, 0.125, 0.25, 0.2], rel=1e-12)
    assert kinetic_energy_error(ref, ref) == [0.0] * 5
    # a reference that never moves has no scale: 0 where the model is at rest too, inf where it moves
    assert kinetic_energy_error([0.0, 0.5], [0.0, 0.0]) == [0.0, math.inf]
    with pytest.raises(MetricInputError, match="one length"):
        kinetic_energy_error([1.0, 2.0], [1.0])


# ------------------------------------------------------------------------------------------- normalised MAE
def test_normalized_mae_scalars_eq30_by_hand():
    # |1.1 - 1|/1 = 0.1 and |2 - 4|/4 = 0.5; the zero target is left out
    assert normalized_mae([1.1, 2.0, 5.0], [1.0, 4.0, 0.0]) == pytest.approx(0.3)


def test_normalized_mae_vectors_eq32_by_hand():
    pred = np.array([[3.0, 4, 0], [0, 0, 1], [1, 1, 1]])
    target = np.array([[3.0, 0, 0], [0, 0, 2], [0, 0, 0]])
    # ||(0,4,0)|| / 3 and ||(0,0,-1)|| / 2; the zero vector is left out
    assert normalized_mae(pred, target) == pytest.approx((4 / 3 + 1 / 2) / 2)
    assert normalized_mae(target, target) == 0.0
    assert math.isnan(normalized_mae([1.0], [0.0]))
    with pytest.raises(MetricInputError, match="same non-empty"):
        normalized_mae(pred, target[:, :2])


# ------------------------------------------------------------------------------------------- PPE residual
@pytest.fixture(scope="module")
def mps_pressure_step():
    """A dam_small MPS step in float64 with its intermediates: (simulator, input state, fields, settings)."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["scene=dam_small", "dtype=float64", "device=cpu"])
    state = build_initial_state(cfg)
    sim = build_simulator(cfg)
    sim.reset(state)
    for _ in range(3):
        state = sim.step(state)
    sim.step(state, record=True)
    return sim, state, sim.last_fields, SolverSettings.from_config(cfg.solver)


def _state_at_pressure_stage(state: ParticleState, fields: dict) -> ParticleState:
    pos, vel, nf = state.pos.clone(), state.vel.clone(), state.n_fluid
    pos[:nf], vel[:nf] = fields.pos_collided, fields.vel_collided
    return ParticleState(pos=pos, vel=vel, ptype=state.ptype, params=state.params, check=False)


def test_ppe_residual_of_the_solver_pressure_is_its_tolerance(mps_pressure_step):
    sim, state, fields, settings = mps_pressure_step
    ctx = exact_context(_state_at_pressure_stage(state, fields), settings, mps_constants(state, settings))
    system, _ = exact_ppe(ctx)
    # the same system as the solver's: the same unknowns, and its own reported residual (relative, float64)
    assert torch.equal(system.scatter(torch.ones(system.num_unknowns)).bool(), fields.ppe_solved)
    residual = ppe_relative_residual(ctx, fields.pressure_unclamped)
    assert residual == pytest.approx(sim.last_info["ppe_residual"], rel=1e-3, abs=1e-12)
    assert residual < 1e-6


def test_both_ppe_sources_use_the_dt_scaled_density_weight(mps_pressure_step):
    """The solver's pressure stage and exact_ppe weigh the density term by density_source_weight(dt)."""
    from dataclasses import replace

    sim, state, fields, settings = mps_pressure_step
    assert settings.source_density_reference_dt is None and state.params.dt == 0.002
    # 0.05 at a reference of 1 ms is 0.2 at 2 ms: the same system and source as the authors' weight ...
    same = replace(settings, source_density=0.05, source_density_reference_dt=0.001)
    # ... while 0.2 at a reference of 1 ms is 0.8 at 2 ms
    other = replace(settings, source_density_reference_dt=0.001)
    at_stage = _state_at_pressure_stage(state, fields)
    variants = (settings, same, other)
    sources = [exact_ppe(exact_context(at_stage, s, mps_constants(state, s)))[1] for s in variants]
    assert torch.equal(sources[0], sources[1]) and not torch.allclose(sources[0], sources[2])
    pressures = []
    for s in variants:
        sim.settings = s
        pressures.append(sim.step(state).pressure)
    sim.settings = settings
    assert torch.equal(pressures[0], pressures[1]) and not torch.allclose(pressures[0], pressures[2])


def test_ppe_residual_of_scaled_and_zero_pressure_by_hand(mps_pressure_step):
    # exact solution p*: ||A (1 + a) p* - b|| / ||b|| = |a| ||b|| / ||b||; p = 0 gives ||b|| / ||b|| = 1
    _, state, fields, settings = mps_pressure_step
    ctx = exact_context(_state_at_pressure_stage(state, fields), settings, mps_constants(state, settings))
    p = fields.pressure_unclamped
    assert ppe_relative_residual(ctx, 1.25 * p) == pytest.approx(0.25, abs=1e-6)
    assert ppe_relative_residual(ctx, 0.5 * p) == pytest.approx(0.5, abs=1e-6)
    assert ppe_relative_residual(ctx, torch.zeros_like(p)) == pytest.approx(1.0, rel=1e-12)
    with pytest.raises(MetricInputError, match="one value per particle"):
        ppe_relative_residual(ctx, p[:10])


def test_metrics_know_no_simulator():
    # Simulator-neutral: importing the metrics loads neither a solver nor its stages or PPE.
    import subprocess
    import sys

    code = "import sys, lagfluid.metrics; print(sorted(m for m in sys.modules if m.startswith('lagfluid')))"
    root = Path(__file__).resolve().parents[1]  # this checkout's lagfluid, not an installed one
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=root)
    for module in (
        "physics.scheme",
        "physics.step_context",
        "physics.settings",
        "physics.mps",
        "physics.ppe",
        "physics.reference",
        "models",
    ):
        assert f"'lagfluid.{module}" not in run.stdout, run.stdout
    assert "'lagfluid.physics.operators'" in run.stdout  # (the check sees what was imported)
