"""The integrator: every forward update beside its inverse (the training target), and the scheme uses them."""

import pytest
import torch

from lagfluid import integrate
from lagfluid.physics.mps import CollisionRule, ExactAdvection, ExactPressure
from lagfluid.physics.scheme import SplitStepSimulator
from lagfluid.physics.settings import SolverSettings
from lagfluid.physics.step_context import SplitStepFields
from lagfluid.scenes import build_scene

EPS32 = torch.finfo(torch.float32).eps
DT = 0.002


def _fields(n=500, seed=0):
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(n, 3, generator=g)
    vel = 2.0 * torch.randn(n, 3, generator=g)
    acc = 10.0 * torch.randn(n, 3, generator=g)
    return pos, vel, acc


def _rounding_bound(vel, acc, dt):
    # ((v + a dt) - v) / dt is exact up to the rounding of v + a dt and of the difference: a few ulps of
    # |v| + |a| dt, divided by dt
    return 4 * EPS32 * (vel.abs() + (acc * dt).abs() + 1e-30) / dt


def test_semi_implicit_euler_inverse_is_the_identity_in_float32():
    pos, vel, acc = _fields()
    new_pos, new_vel = integrate.semi_implicit_euler(pos, vel, acc, DT)
    assert new_pos.dtype == torch.float32
    back = integrate.acceleration_target(vel, new_vel, DT)
    assert bool(((back - acc).abs() <= _rounding_bound(vel, acc, DT)).all())
    # and the velocity the position update used is recovered from the positions
    v_fd = integrate.velocity_from_positions(pos, new_pos, DT)
    assert bool(((v_fd - new_vel).abs() <= 4 * EPS32 * (pos.abs() + new_pos.abs()) / DT).all())


def test_three_frames_give_gns_acceleration_target():
    pos, vel, acc = (t.double() for t in _fields(200))
    prev = pos - vel * DT  # a frame before, moving at vel
    nxt, _ = integrate.semi_implicit_euler(pos, vel, acc, DT)
    torch.testing.assert_close(
        integrate.acceleration_from_positions(prev, pos, nxt, DT), acc, rtol=0, atol=1e-6
    )


def test_split_step_updates_invert_exactly_enough():
    pos, vel, acc = _fields()
    x_star, v_star = integrate.advect(pos, vel, acc, DT)
    assert bool(
        ((integrate.advection_target(vel, v_star, DT) - acc).abs() <= _rounding_bound(vel, acc, DT)).all()
    )
    v_col = v_star + 0.1 * torch.randn_like(v_star)
    x_col = integrate.collide(x_star, v_star, v_col, DT)
    dv = integrate.collision_target(v_star, v_col)
    torch.testing.assert_close(
        (x_col - x_star) / DT, dv, rtol=0, atol=float(8 * EPS32 * x_col.abs().max() / DT)
    )
    x_new, v_new = integrate.correct(x_col, v_col, acc, DT)
    back = integrate.correction_target(v_col, v_new, DT)
    assert bool(((back - acc).abs() <= _rounding_bound(v_col, acc, DT)).all())
    # x += a_p dt^2 (the authors' form), up to the rounding of positions of size ~1
    torch.testing.assert_close(
        x_new - x_col, acc * DT * DT, rtol=0, atol=float(4 * EPS32 * x_new.abs().max())
    )
    assert torch.equal(integrate.drift(pos, vel, DT), pos + vel * DT)


def test_updates_leave_their_inputs_alone():
    pos, vel, acc = _fields()
    copies = [t.clone() for t in (pos, vel, acc)]
    integrate.semi_implicit_euler(pos, vel, acc, DT)
    integrate.correct(pos, vel, acc, DT)
    integrate.collide(pos, vel, acc, DT)
    assert all(torch.equal(a, b) for a, b in zip(copies, (pos, vel, acc), strict=True))


def test_the_split_step_scheme_is_the_integrator_and_its_fields_are_declared():
    state = build_scene("dam", fluid_size=[4, 4, 5], tank_size=[10, 6])
    sim = SplitStepSimulator("mps", SolverSettings(), ExactAdvection(), CollisionRule(), ExactPressure())
    new = sim.step(state, record=True)
    f, nf = sim.last_fields, state.n_fluid
    assert isinstance(f, SplitStepFields)
    x_star, v_star = integrate.advect(state.pos[:nf], state.vel[:nf], f.advection_acceleration, DT)
    assert torch.equal(x_star, f.pos_star) and torch.equal(v_star, f.vel_star)
    assert torch.equal(integrate.collide(f.pos_star, f.vel_star, f.vel_collided, DT), f.pos_collided)
    a_p = integrate.correction_target(f.vel_collided, new.vel[:nf], DT)
    x_new, _ = integrate.correct(f.pos_collided, f.vel_collided, a_p, DT)
    torch.testing.assert_close(x_new, new.pos[:nf], rtol=0, atol=1e-6)


def test_a_stage_recording_an_undeclared_field_is_an_error():
    from lagfluid.errors import ConfigError
    from lagfluid.physics.settings import lattice_constants
    from lagfluid.physics.step_context import StepContext
    from lagfluid.physics.timing import StageTimer

    state = build_scene("dam", fluid_size=[3, 3, 3], tank_size=[8, 6])
    settings = SolverSettings()
    ctx = StepContext(
        state, settings, lattice_constants(0.05, settings), None, StageTimer(), fields=SplitStepFields()
    )
    with pytest.raises(ConfigError, match=r"unknown step field\(s\) \['pos_stra'\]"):
        ctx.record(pos_stra=state.pos)
