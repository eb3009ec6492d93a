import pytest
import torch

from lagfluid.state import ParticleState, ParticleType, SceneError, SceneParams


def _arrays():
    pos = torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
    return pos, torch.zeros_like(pos), torch.tensor([3, 1, 2, 1])


def test_from_arrays_sorts_by_type_stably():
    pos, vel, ptype = _arrays()
    s = ParticleState.from_arrays(pos, vel, ptype)
    assert s.ptype.tolist() == [1, 1, 2, 3]
    assert s.pos[:, 0].tolist() == [1.0, 3.0, 2.0, 0.0]
    assert s.n_fluid == 2 and int(s.wall_mask.sum()) == 1 and int(s.dummy_mask.sum()) == 1
    assert s.pressure.shape == (4,) and s.pressure.dtype == s.pos.dtype


def test_to_dtype_and_clone_are_independent():
    s = ParticleState.from_arrays(*_arrays())
    d = s.to(dtype=torch.float64)
    assert d.pos.dtype == torch.float64 and d.ptype.dtype == torch.int64
    c = s.clone()
    c.pos += 1
    assert not torch.equal(c.pos, s.pos)


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda p, v, t: (p, v, torch.tensor([1, 1, 2, 7])), "unknown particle type 7"),
        (lambda p, v, t: (p, v, torch.tensor([2, 2, 3, 3])), "no fluid particles"),
        (lambda p, v, t: (p.index_fill(0, torch.tensor([1]), float("nan")), v, t), "not finite"),
        (lambda p, v, t: (p[:, :2], v, t), "shape"),
    ],
)
def test_bad_state_is_a_clear_error(mutate, message):
    with pytest.raises(SceneError, match=message):
        ParticleState.from_arrays(*mutate(*_arrays()))


def test_unsorted_state_is_rejected():
    pos, vel, _ = _arrays()
    with pytest.raises(SceneError, match="sorted"):
        ParticleState(pos=pos, vel=vel, ptype=torch.tensor([2, 1, 1, 3]))


def test_fluid_outside_bounds_is_rejected_and_reported():
    pos, vel, ptype = _arrays()
    bounds = torch.tensor([[-0.5, -1, -1], [2.5, 1, 1]])
    with pytest.raises(SceneError, match=r"fluid particle 1 at \[3.0"):
        ParticleState.from_arrays(pos, vel, ptype, bounds=bounds)


@pytest.mark.parametrize(
    ("field", "value"), [("dt", 0.0), ("l0", -1.0), ("density", float("nan")), ("viscosity", -1e-6)]
)
def test_bad_params_name_the_value(field, value):
    with pytest.raises(SceneError, match=field):
        SceneParams(**{field: value})


def test_params_defaults_are_the_authors():
    p = SceneParams()
    assert p.gravity == (0.0, 0.0, -9.8065) and p.dt == 0.002 and p.l0 == 0.05 and p.density == 1000.0
    assert p.with_overrides(dt=None).dt == 0.002 and p.with_overrides(dt=0.001).dt == 0.001


def test_particle_type_codes_match_the_authors_files():
    assert (ParticleType.FLUID, ParticleType.WALL, ParticleType.DUMMY) == (1, 2, 3)


def test_a_fluid_count_that_does_not_match_ptype_is_refused():
    state = ParticleState.from_arrays(
        torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]),
        torch.zeros(3, 3),
        torch.tensor([1, 1, 2]),
    )
    assert ParticleState(state.pos, state.vel, state.ptype, fluid_count=2).n_fluid == 2
    with pytest.raises(SceneError, match="fluid_count 3 does not match ptype's 2 FLUID rows"):
        ParticleState(state.pos, state.vel, state.ptype, fluid_count=3)
