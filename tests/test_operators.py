"""MPS operators against lattice oracles, hand-computed values and invariances."""

from __future__ import annotations

import functools
import math
from functools import cache

import pytest
import torch

from lagfluid.neighbors import csr, pair_kernels
from lagfluid.physics import operators as ops

L0 = 0.05
SIDE = 13  # 13^3 simple-cubic lattice
DTYPES = [torch.float32, torch.float64]
# Interior lattice constants, from sums over the integer offsets (exact to float64 rounding).
N0_21 = 14.418575408286713  # number density, re = 2.1 l0
N0_31 = 54.32120938182034  # number density, re = 3.1 l0
LAM_31 = 3.2434216760380647  # lambda / l0^2, re = 3.1 l0
RTOL = {torch.float32: 1e-5, torch.float64: 1e-10}


def brute_edges(pos: torch.Tensor, r: float) -> torch.Tensor:
    """All ordered pairs 0 < |x_j - x_i| < r, as [j, i] (independent of lagfluid.neighbors)."""
    p = pos.detach().to(torch.float64)
    d = torch.cdist(p, p)
    i, j = torch.nonzero((d < r) & (d > 0), as_tuple=True)
    return torch.stack([j, i])


@cache
def _lattice(dtype: torch.dtype, re_factor: float):
    axis = torch.arange(SIDE)
    idx = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
    # Centred at the origin: smaller coordinates, smaller float32 rounding.
    pos = ((idx - (SIDE - 1) / 2).to(torch.float64) * L0).to(dtype)
    margin = math.floor(re_factor)  # sites at least this many layers in have every neighbour
    interior = ((idx >= margin) & (idx <= SIDE - 1 - margin)).all(dim=1)
    return pos, brute_edges(pos, re_factor * L0), interior, idx


def lattice(dtype: torch.dtype, re_factor: float):
    pos, ei, interior, idx = _lattice(dtype, re_factor)
    return pos.clone(), ei.clone(), interior.clone(), idx.clone()


def close(actual, expected, dtype, rtol=None, atol=0.0):
    torch.testing.assert_close(
        torch.as_tensor(actual, dtype=torch.float64),
        torch.as_tensor(expected, dtype=torch.float64).expand_as(torch.as_tensor(actual)),
        rtol=RTOL[dtype] if rtol is None else rtol,
        atol=atol,
    )


# ----------------------------------------------------------------------------------------- kernel
@pytest.mark.parametrize("dtype", DTYPES)
def test_kernel_values(dtype):
    re = 2.1 * L0
    r = torch.tensor([0.0, 5e-9, re / 4, re / 2, re * 0.999, re, 1.5 * re], dtype=dtype)
    w = ops.kernel(r, re)
    assert w.dtype == dtype and w.shape == r.shape
    expected = torch.tensor([0.0, 0.0, 3.0, 1.0, 1 / 0.999 - 1, 0.0, 0.0], dtype=torch.float64)
    close(w, expected, dtype, rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=1e-6)


def test_kernel_gradient_finite_at_excluded_pairs():
    r = torch.tensor([0.0, 1e-9, 0.05, 0.2], dtype=torch.float64, requires_grad=True)
    ops.kernel(r, 0.105).sum().backward()
    assert torch.isfinite(r.grad).all()
    torch.testing.assert_close(r.grad, torch.tensor([0.0, 0.0, -0.105 / 0.05**2, 0.0], dtype=torch.float64))


def test_edge_geometry():
    pos = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.4, 0.0]], dtype=torch.float64)
    rel, dist = ops.edge_geometry(pos, torch.tensor([[1, 0], [0, 1]]))
    torch.testing.assert_close(rel, torch.tensor([[0.3, 0.4, 0.0], [-0.3, -0.4, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(dist, torch.tensor([0.5, 0.5], dtype=torch.float64))


# ---------------------------------------------------------------------------- densities, lambda
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize(("re_factor", "expected"), [(2.1, N0_21), (3.1, N0_31)])
def test_number_density_lattice(dtype, re_factor, expected):
    pos, ei, interior, _ = lattice(dtype, re_factor)
    n = ops.number_density(pos, ei, re_factor * L0)
    assert n.shape == (pos.shape[0],) and n.dtype == dtype
    close(n[interior], expected, dtype)
    assert round(expected, 4) == {2.1: 14.4186, 3.1: 54.3212}[re_factor]
    # Every truncated neighbourhood has a smaller density (at 3.1 l0 the mildest truncation, one missing
    # (0, 0, 3) neighbour, costs w = 3.1/3 - 1 = 0.033); the corner has about a third of n0.
    assert float(n[~interior].max()) < expected - 0.03
    assert float(n[0]) < expected / 2


@pytest.mark.parametrize("dtype", DTYPES)
def test_free_surface_is_the_truncated_neighbourhoods_of_a_lattice(dtype):
    # At 2.1 l0 every site within 2 layers of a face misses neighbours. In the second layer only the (0, 0, 2)
    # kind is missing (w = 2.1/2 - 1 = 0.05 each, at most 3 of them: n >= 0.989 n0); a site of the outer layer
    # misses at least the nearest one (w = 1.1: n <= 0.73 n0). So beta = 0.97 flags the outer layer only,
    # beta = 0.999 every truncated site (n <= 0.9965 n0), and an interior site is never on the surface.
    pos, ei, interior, idx = lattice(dtype, 2.1)
    n = ops.number_density(pos, ei, 2.1 * L0)
    everything_truncated = ops.free_surface(n, N0_21, 0.999)
    assert everything_truncated.dtype == torch.bool and everything_truncated.shape == n.shape
    assert torch.equal(everything_truncated, ~interior)
    outer = ((idx == 0) | (idx == SIDE - 1)).any(dim=1)
    assert torch.equal(ops.free_surface(n, N0_21, 0.97), outer)
    # the rule itself, by hand: strictly below beta n0
    n_hand = torch.tensor([0.0, 0.969, 0.97, 1.2], dtype=dtype)
    assert ops.free_surface(n_hand, 1.0, 0.97).tolist() == [True, True, False, False]
    for beta in (0.0, 1.5, -0.1):
        with pytest.raises(ValueError, match="beta"):
            ops.free_surface(n, N0_21, beta)


def test_ppe_unknowns_are_fluid_and_walls_off_the_surface():
    ptype = torch.tensor([1, 1, 2, 2, 3, 3])  # fluid, wall, dummy
    surface = torch.tensor([False, True, False, True, False, True])
    assert ops.ppe_unknowns(ptype, surface).tolist() == [True, False, True, False, False, False]
    with pytest.raises(ValueError, match="same shape"):
        ops.ppe_unknowns(ptype, surface[:3])


@pytest.mark.parametrize("dtype", DTYPES)
def test_reference_density(dtype):
    pos, ei, interior, _ = lattice(dtype, 2.1)
    n = ops.number_density(pos, ei, 2.1 * L0)
    n0 = ops.reference_density(n, torch.ones_like(interior))
    assert n0.dim() == 0 and n0.dtype == dtype
    close(n0, N0_21, dtype)
    close(ops.reference_density(n), N0_21, dtype)
    corner = torch.zeros_like(interior)
    corner[0] = True
    assert float(ops.reference_density(n, corner)) == float(n[0])
    with pytest.raises(ValueError, match="no particle"):
        ops.reference_density(n, torch.zeros_like(interior))


@pytest.mark.parametrize("dtype", DTYPES)
def test_laplacian_lambda_lattice(dtype):
    pos, ei, interior, idx = lattice(dtype, 3.1)
    n0_lap, lam = ops.laplacian_lambda(pos, ei, 3.1 * L0, torch.ones_like(interior))
    assert n0_lap.dim() == 0 and lam.dim() == 0 and lam.dtype == dtype
    close(n0_lap, N0_31, dtype)
    close(lam, LAM_31 * L0**2, dtype)
    assert round(LAM_31, 4) == 3.2434
    # n0_lap and lambda come from the same (densest masked) particle; a mask that only holds a face
    # particle gives that particle's values, smaller than the interior ones (the far neighbours are missing).
    _, dist = ops.edge_geometry(pos, ei)
    w = ops.kernel(dist, 3.1 * L0)
    n = torch.zeros(pos.shape[0], dtype=dtype).index_add(0, ei[1], w)
    lam_i = torch.zeros(pos.shape[0], dtype=dtype).index_add(0, ei[1], dist**2 * w) / n
    face = torch.zeros_like(interior)
    k = int(torch.nonzero((idx == torch.tensor([6, 6, 12])).all(dim=1))[0, 0])
    face[k] = True
    n_face, lam_face = ops.laplacian_lambda(pos, ei, 3.1 * L0, face)
    close(n_face, n[k], dtype)
    close(lam_face, lam_i[k], dtype)
    assert float(lam_face) < float(lam) * 0.95 and float(n_face) < float(n0_lap) * 0.8
    with pytest.raises(ValueError):
        ops.laplacian_lambda(pos, ei, 3.1 * L0, torch.zeros_like(interior))


# ----------------------------------------------------------------------------------- gradients
A = (1.5, -2.0, 0.7)


def linear_field(pos, a=A, b=3.0):
    return pos @ torch.tensor(a, dtype=pos.dtype) + b


def atol_for(dtype, scale):
    return scale * (2e-4 if dtype == torch.float32 else 1e-10)


@pytest.mark.parametrize("dtype", DTYPES)
def test_gradient_linear_field_exact_in_interior(dtype):
    pos, ei, interior, _ = lattice(dtype, 2.1)
    g = ops.gradient(pos, ei, linear_field(pos), 2.1 * L0, N0_21)
    assert g.shape == (pos.shape[0], 3) and g.dtype == dtype
    close(
        g[interior],
        torch.tensor(A, dtype=torch.float64).expand(int(interior.sum()), 3),
        dtype,
        0,
        atol_for(dtype, 2),
    )
    # ... and not at the surface, where the neighbourhood is one-sided.
    assert float((g[~interior] - torch.tensor(A, dtype=dtype)).abs().max()) > 0.1


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("include_self", [True, False])
def test_min_pressure_gradient_linear_field_interior(dtype, include_self):
    # The extra (p_i - p_min,i) term multiplies sum_j e_j w_j / |e_j|^2, which vanishes on a point-
    # symmetric neighbourhood: in the interior the stabilised gradient of a linear field is exactly a
    # (no lattice factor).
    pos, ei, interior, _ = lattice(dtype, 2.1)
    g = ops.min_pressure_gradient(pos, ei, linear_field(pos), 2.1 * L0, N0_21, include_self=include_self)
    close(
        g[interior],
        torch.tensor(A, dtype=torch.float64).expand(int(interior.sum()), 3),
        dtype,
        0,
        atol_for(dtype, 2),
    )


@pytest.mark.parametrize("dtype", DTYPES)
def test_min_pressure_gradient_constant_and_shift(dtype):
    pos, ei, _, _ = lattice(dtype, 2.1)
    re = 2.1 * L0
    g0 = ops.min_pressure_gradient(pos, ei, torch.full((pos.shape[0],), 7.0, dtype=dtype), re, N0_21)
    assert bool((g0 == 0).all())
    p = torch.rand(pos.shape[0], generator=torch.Generator().manual_seed(0), dtype=torch.float64).to(dtype)
    g = ops.min_pressure_gradient(pos, ei, p, re, N0_21)
    g_shift = ops.min_pressure_gradient(pos, ei, p + 1.0, re, N0_21)
    scale = float(g.abs().max())
    close(g_shift, g, dtype, 0, scale * (1e-5 if dtype == torch.float32 else 1e-12))


def test_min_pressure_gradient_two_particles_by_hand():
    pos = torch.tensor([[0.0, 0.0, 0.0], [L0, 0.0, 0.0]], dtype=torch.float64)
    ei = torch.tensor([[1, 0], [0, 1]])
    re, n0 = 2.1 * L0, 10.0
    coef = 3 / n0 * (2.1 - 1) / L0  # d/n0 * w / r (the unit vector is +-x)
    p = torch.tensor([2.0, 5.0], dtype=torch.float64)
    # Particle 0: p_min = 2, term (5 - 2) along +x. Particle 1: p_min = min(5, 2) = 2, term (2 - 2) = 0.
    expected = torch.tensor([[3.0 * coef, 0, 0], [0, 0, 0]], dtype=torch.float64)
    torch.testing.assert_close(ops.min_pressure_gradient(pos, ei, p, re, n0), expected)
    # The plain gradient is the same at 0 but -3 coef * (-x) = +3 coef along x at 1.
    torch.testing.assert_close(
        ops.gradient(pos, ei, p, re, n0)[1], torch.tensor([3.0 * coef, 0, 0], dtype=torch.float64)
    )
    # Without p_i in the minimum, a single neighbour is its own minimum: no gradient at all.
    torch.testing.assert_close(
        ops.min_pressure_gradient(pos, ei, p, re, n0, include_self=False),
        torch.zeros(2, 3, dtype=torch.float64),
    )


@pytest.mark.parametrize("dtype", DTYPES)
def test_min_pressure_gradient_top_face_by_hand(dtype):
    # p = c z at the centre of the top face: neighbours have offsets e (in l0) with e_z <= 0, down to
    # e_z = -2, so p_min = p_i - 2 c l0 and grad = c d/n0 sum_e (e_z + 2) e / |e|^2 w(|e|).
    pos, ei, _, idx = lattice(dtype, 2.1)
    c = 4.0
    g = ops.min_pressure_gradient(pos, ei, c * pos[:, 2], 2.1 * L0, N0_21)
    k = int(torch.nonzero((idx == torch.tensor([6, 6, 12])).all(dim=1))[0, 0])
    expected = [0.0, 0.0, 0.0]
    for ex in range(-2, 3):
        for ey in range(-2, 3):
            for ez in range(-2, 1):
                r = math.sqrt(ex * ex + ey * ey + ez * ez)
                if 0 < r < 2.1:
                    for axis, e in enumerate((ex, ey, ez)):
                        expected[axis] += c * 3 / N0_21 * (ez + 2) * e / r**2 * (2.1 / r - 1)
    close(g[k], expected, dtype, 0, atol_for(dtype, 10))
    # The lattice factor at the top face: grad_z = -0.49 c, the opposite sign of the field's slope (the
    # p_min shift times sum_j e_j w_j / |e_j|^2, which is nonzero on a one-sided neighbourhood), while the
    # plain gradient gives +c/2 (half the neighbourhood).
    assert expected[2] == pytest.approx(-0.48959675 * c, rel=1e-6)
    plain = ops.gradient(pos, ei, c * pos[:, 2], 2.1 * L0, N0_21)[k]
    close(plain, [0.0, 0.0, 0.5 * c], dtype, 1e-6, atol_for(dtype, 10))


@pytest.mark.parametrize("dtype", DTYPES)
def test_min_pressure_gradient_is_repulsive(dtype):
    # Every term (p_j - p_min,i) >= 0: at the top face (all e_z <= 0) grad_z <= 0 for any pressure field,
    # so -grad p / rho never pulls a surface particle into the fluid. The plain gradient has no such sign.
    pos, ei, _, idx = lattice(dtype, 2.1)
    p = torch.rand(pos.shape[0], generator=torch.Generator().manual_seed(1), dtype=torch.float64).to(dtype)
    top = idx[:, 2] == SIDE - 1
    assert bool((ops.min_pressure_gradient(pos, ei, p, 2.1 * L0, N0_21)[top, 2] <= 0).all())
    assert bool((ops.gradient(pos, ei, p, 2.1 * L0, N0_21)[top, 2] > 0).any())


# ------------------------------------------------------------------- corrected pressure gradient
def jittered_lattice(dtype, re_factor, amplitude=0.2, seed=3):
    """The lattice with every site moved by up to ``amplitude`` l0 per axis (a disordered fluid)."""
    pos, _, interior, idx = lattice(torch.float64, re_factor)
    gen = torch.Generator().manual_seed(seed)
    pos = pos + (torch.rand(pos.shape, generator=gen, dtype=torch.float64) - 0.5) * 2 * amplitude * L0
    pos = pos.to(dtype)
    return pos, brute_edges(pos, re_factor * L0), interior, idx


@pytest.mark.parametrize("dtype", DTYPES)
def test_corrected_pressure_gradient_exact_for_linear_fields_on_a_disordered_lattice(dtype):
    # The corrective matrix makes the linear part exact at any non-degenerate neighbourhood, and for a
    # linear field every neighbour lies on the fit, so the stabilising term vanishes: the result is a.
    pos, ei, interior, _ = jittered_lattice(dtype, 2.1)
    p = linear_field(pos)
    g = ops.corrected_pressure_gradient(pos, ei, p, 2.1 * L0, N0_21)
    expected = torch.tensor(A, dtype=torch.float64).expand(int(interior.sum()), 3)
    close(g[interior], expected, dtype, 0, atol_for(dtype, 20))
    # ... where neither the minimum-pressure nor the plain MPS gradient is (this test can fail).
    for other in (ops.min_pressure_gradient, ops.gradient):
        error = (other(pos, ei, p, 2.1 * L0, N0_21)[interior].double() - expected).abs().max()
        assert float(error) > 0.1


def test_corrected_pressure_gradient_exact_in_2d():
    axis = torch.arange(11)
    idx = torch.stack(torch.meshgrid(axis, axis, indexing="ij"), dim=-1).reshape(-1, 2)
    gen = torch.Generator().manual_seed(4)
    xy = (idx - 5).double() * L0 + (
        torch.rand(idx.shape, generator=gen, dtype=torch.float64) - 0.5
    ) * 0.4 * L0
    pos = torch.cat([xy, torch.zeros(xy.shape[0], 1, dtype=torch.float64)], dim=1)
    ei = brute_edges(pos, 2.1 * L0)
    interior = ((idx >= 2) & (idx <= 8)).all(dim=1)
    p = 1.5 * pos[:, 0] - 2.0 * pos[:, 1] + 3.0
    g = ops.corrected_pressure_gradient(pos, ei, p, 2.1 * L0, 6.539, dim=2)
    close(g[interior], torch.tensor([1.5, -2.0, 0.0]).expand(int(interior.sum()), 3), torch.float64, 0, 1e-9)


@pytest.mark.parametrize("dtype", DTYPES)
def test_hydrostatic_column_shift_destabilises_the_minimum_gradient_only(dtype):
    # The mechanism behind the resting column's spurious motion. Hydrostatic p = rho g (z_top - z) at every
    # particle's actual height; one interior column displaced by delta along z. The minimum-pressure
    # gradient's repulsion (p_i - p_min ~ 2 rho g l0) then pushes the column further the way it moved: the
    # simple-cubic lattice is shear-unstable under load (~6.3 m/s^2 per l0 at g = 9.81). The corrected
    # gradient gives exactly g for any delta (neutral, as an inviscid fluid is to a shear).
    rho, g = 1000.0, 9.81
    pos0, ei, _, idx = lattice(torch.float64, 2.1)
    column = (idx[:, 0] == 6) & (idx[:, 1] == 6)
    k = int(torch.nonzero(column & (idx[:, 2] == 6))[0, 0])

    def support(op, delta):  # upward acceleration -grad_z p / rho of the column's centre particle
        pos = pos0.clone()
        pos[column, 2] += delta * L0
        pos = pos.to(dtype)
        p = rho * g * (pos[:, 2].max() + L0 - pos[:, 2])
        return float(-op(pos, ei, p, 2.1 * L0, N0_21)[k, 2]) / rho

    for delta in (-0.1, 0.1):
        assert support(ops.corrected_pressure_gradient, delta) == pytest.approx(g, rel=1e-4)
    # Sunk column: less support; raised column: more. Anti-restoring, as large as measured in the solver.
    stiffness = (support(ops.min_pressure_gradient, 0.1) - support(ops.min_pressure_gradient, -0.1)) / 0.2
    assert 4.0 < stiffness < 9.0
    # A single displaced particle is restored by the same repulsion (its own column neighbours push back).
    pos = pos0.clone()
    pos[k, 2] -= 0.1 * L0
    p = rho * g * (pos[:, 2].max() + L0 - pos[:, 2])
    assert float(-ops.min_pressure_gradient(pos.to(dtype), ei, p.to(dtype), 2.1 * L0, N0_21)[k, 2]) / rho > g


@pytest.mark.parametrize("dtype", DTYPES)
def test_corrected_pressure_gradient_pushes_a_compressed_pair_apart(dtype):
    # Two interior particles pressed together carry a pressure peak (what the PPE gives them): the
    # stabilising term separates them, as the minimum-pressure gradient does, by at most as much.
    pos, ei, _, idx = lattice(torch.float64, 2.1)
    a = int(torch.nonzero((idx == torch.tensor([6, 6, 6])).all(dim=1))[0, 0])
    b = int(torch.nonzero((idx == torch.tensor([7, 6, 6])).all(dim=1))[0, 0])
    pos[a, 0] += 0.2 * L0
    pos[b, 0] -= 0.2 * L0
    pos = pos.to(dtype)
    ei = brute_edges(pos, 2.1 * L0)
    p = linear_field(pos) + 0.0
    p[[a, b]] += 50.0
    corrected = ops.corrected_pressure_gradient(pos, ei, p, 2.1 * L0, N0_21)
    minimum = ops.min_pressure_gradient(pos, ei, p, 2.1 * L0, N0_21)
    linear = torch.tensor(A, dtype=dtype)
    # -grad p pushes a towards -x (away from b) and b towards +x, beyond the linear field's gradient.
    assert float(corrected[a, 0] - linear[0]) > 0 and float(corrected[b, 0] - linear[0]) < 0
    assert float((corrected[a] - linear).norm()) <= float((minimum[a] - linear).norm()) * 1.0001


@pytest.mark.parametrize("dtype", DTYPES)
def test_corrected_pressure_gradient_zero_constant_and_sparse(dtype):
    pos, ei, _, _ = jittered_lattice(dtype, 2.1)
    re = 2.1 * L0
    n = pos.shape[0]
    assert bool((ops.corrected_pressure_gradient(pos, ei, torch.zeros(n, dtype=dtype), re, N0_21) == 0).all())
    p = torch.rand(n, generator=torch.Generator().manual_seed(0), dtype=torch.float64).to(dtype)
    g = ops.corrected_pressure_gradient(pos, ei, p, re, N0_21)
    g_shift = ops.corrected_pressure_gradient(pos, ei, p + 1.0, re, N0_21)
    close(g_shift, g, dtype, 0, float(g.abs().max()) * (1e-4 if dtype == torch.float32 else 1e-11))
    # Two particles: a degenerate (rank-1) neighbourhood keeps the authors' minimum-pressure gradient.
    pair = torch.tensor([[0.0, 0.0, 0.0], [L0, 0.0, 0.0]], dtype=dtype)
    pair_edges, pair_p = torch.tensor([[1, 0], [0, 1]]), torch.tensor([2.0, 5.0], dtype=dtype)
    torch.testing.assert_close(
        ops.corrected_pressure_gradient(pair, pair_edges, pair_p, re, 10.0),
        ops.min_pressure_gradient(pair, pair_edges, pair_p, re, 10.0),
    )


# ---------------------------------------------------------------------------------- divergence
M = ((0.3, -1.2, 0.5), (0.8, 2.0, -0.4), (1.1, 0.6, -0.9))


@pytest.mark.parametrize("dtype", DTYPES)
def test_divergence_linear_field(dtype):
    pos, ei, interior, _ = lattice(dtype, 2.1)
    m = torch.tensor(M, dtype=dtype)
    vel = pos @ m.T + torch.tensor([1.0, -2.0, 0.5], dtype=dtype)
    div = ops.divergence(pos, ei, vel, 2.1 * L0, N0_21)
    assert div.shape == (pos.shape[0],) and div.dtype == dtype
    close(div[interior], 0.3 + 2.0 - 0.9, dtype, 0, atol_for(dtype, 3))
    # A velocity z-difference times the y-offset (the authors' GPU defect) would change the result.
    defect = torch.zeros_like(vel)
    defect[:, 2] = pos[:, 1]
    assert float(ops.divergence(pos, ei, defect, 2.1 * L0, N0_21)[interior].abs().max()) < atol_for(dtype, 1)


@pytest.mark.parametrize("dtype", DTYPES)
def test_divergence_of_rotation_is_zero_everywhere(dtype):
    # (v_j - v_i).(x_j - x_i) = e^T W e = 0 for antisymmetric W, at every particle, surface included.
    pos, ei, _, _ = lattice(dtype, 2.1)
    w = torch.tensor([[0.0, -2.0, 1.0], [2.0, 0.0, -0.5], [-1.0, 0.5, 0.0]], dtype=dtype)
    div = ops.divergence(pos, ei, pos @ w.T, 2.1 * L0, N0_21)
    close(div, 0.0, dtype, 0, atol_for(dtype, 3))


# ----------------------------------------------------------------------------------- Laplacian
def quadratic(pos):
    x, y, z = pos.unbind(dim=1)
    return x**2 + 2 * y**2 - z**2 + x * y


@pytest.mark.parametrize("dtype", DTYPES)
def test_laplacian_quadratic_linear_and_columns(dtype):
    pos, ei, interior, _ = lattice(dtype, 3.1)
    re = 3.1 * L0
    n0_lap, lam = N0_31, LAM_31 * L0**2
    lap = ops.laplacian(pos, ei, quadratic(pos), re, n0_lap, lam)
    assert lap.shape == (pos.shape[0],) and lap.dtype == dtype
    atol = 2e-3 if dtype == torch.float32 else 1e-9
    close(lap[interior], 4.0, dtype, 0, atol)
    close(ops.laplacian(pos, ei, linear_field(pos), re, n0_lap, lam)[interior], 0.0, dtype, 0, atol)
    cols = torch.stack([quadratic(pos), linear_field(pos), pos[:, 0] ** 2], dim=1)
    lap_cols = ops.laplacian(pos, ei, cols, re, n0_lap, lam)
    assert lap_cols.shape == cols.shape
    close(lap_cols[:, 0], lap, dtype, 0, atol * 1e-3)
    close(lap_cols[interior], torch.tensor([4.0, 0.0, 2.0]).expand(int(interior.sum()), 3), dtype, 0, atol)
    # The constants from laplacian_lambda (tensors) work the same as the Python floats.
    n0_t, lam_t = ops.laplacian_lambda(pos, ei, re, torch.ones_like(interior))
    close(ops.laplacian(pos, ei, quadratic(pos), re, n0_t, lam_t)[interior], 4.0, dtype, 0, atol)


@pytest.mark.parametrize("dtype", DTYPES)
def test_laplacian_weights(dtype):
    dist = torch.tensor([0.0, 0.5 * 3.1 * L0, 3.1 * L0], dtype=dtype)
    coef = ops.laplacian_weights(dist, 3.1 * L0, 50.0, 2e-3, dim=2)
    close(coef, torch.tensor([0.0, 4 / (2e-3 * 50.0), 0.0]), dtype)


# ------------------------------------------------------------------------ graph-level properties
def all_ops(pos, ei, num_nodes=None):
    """Every operator on fixed smooth + random fields, as a dict of (N, ...) outputs."""
    n = pos.shape[0]
    gen = torch.Generator().manual_seed(2)
    p = torch.rand(n, generator=gen, dtype=torch.float64).to(pos.dtype)
    v = torch.rand(n, 3, generator=gen, dtype=torch.float64).to(pos.dtype)
    return _ops_on(pos, ei, p, v, num_nodes)


def _ops_on(pos, ei, p, v, num_nodes=None):
    re_n, re_l = 2.1 * L0, 3.1 * L0
    near = ei[:, (pos[ei[0]] - pos[ei[1]]).norm(dim=1) < re_n]
    return {
        "number_density": ops.number_density(pos, near, re_n, num_nodes=num_nodes),
        "gradient": ops.gradient(pos, near, p, re_n, N0_21, num_nodes=num_nodes),
        "min_pressure_gradient": ops.min_pressure_gradient(pos, near, p, re_n, N0_21, num_nodes=num_nodes),
        "min_pressure_gradient_noself": ops.min_pressure_gradient(
            pos, near, p, re_n, N0_21, include_self=False, num_nodes=num_nodes
        ),
        "corrected_pressure_gradient": ops.corrected_pressure_gradient(
            pos, near, p, re_n, N0_21, num_nodes=num_nodes
        ),
        "divergence": ops.divergence(pos, near, v, re_n, N0_21, num_nodes=num_nodes),
        "laplacian": ops.laplacian(pos, ei, v, re_l, N0_31, LAM_31 * L0**2, num_nodes=num_nodes),
    }


@pytest.mark.parametrize("dtype", DTYPES)
def test_edges_into_a_subset_of_targets(dtype):
    pos, ei, _, idx = lattice(dtype, 3.1)
    full = all_ops(pos, ei)
    target = (idx[:, 2] < 5) | (idx[:, 0] == 7)  # a "fluid" block plus a sheet
    sub = ei[:, target[ei[1]]]
    part = all_ops(pos, sub, num_nodes=pos.shape[0])
    for name, out in part.items():
        assert out.shape == full[name].shape, name
        assert bool((out[~target] == 0).all()), name
        torch.testing.assert_close(out[target], full[name][target], rtol=0, atol=0, msg=name)
        assert bool((full[name][~target] != 0).any()), name  # the check above is not vacuous


@pytest.mark.parametrize("dtype", DTYPES)
def test_translation_invariance(dtype):
    pos, ei, _, _ = lattice(dtype, 3.1)
    pos = pos + 0.01 * torch.randn(
        pos.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64
    ).to(dtype)
    ei = brute_edges(pos, 3.1 * L0)
    shift = torch.tensor([0.37, -1.2, 2.5], dtype=dtype)
    base, moved = all_ops(pos, ei), all_ops(pos + shift, ei)
    for name in base:
        scale = float(base[name].abs().max())
        tol = scale * (2e-4 if dtype == torch.float32 else 1e-11)
        torch.testing.assert_close(moved[name], base[name], rtol=0, atol=tol, msg=name)


@pytest.mark.parametrize("dtype", DTYPES)
def test_permutation_equivariance(dtype):
    pos, _, _, _ = lattice(dtype, 3.1)
    gen = torch.Generator().manual_seed(4)
    pos = pos + 0.01 * torch.randn(pos.shape, generator=gen, dtype=torch.float64).to(dtype)
    ei = brute_edges(pos, 3.1 * L0)
    n = pos.shape[0]
    p = torch.rand(n, generator=gen, dtype=torch.float64).to(dtype)
    v = torch.rand(n, 3, generator=gen, dtype=torch.float64).to(dtype)
    perm = torch.randperm(n, generator=gen)  # new particle k is old particle perm[k]
    inv = torch.empty_like(perm)
    inv[perm] = torch.arange(n)
    ei_new = inv[ei][:, torch.randperm(ei.shape[1], generator=gen)]  # relabel and shuffle edge order
    base = _ops_on(pos, ei, p, v)
    permuted = _ops_on(pos[perm], ei_new, p[perm], v[perm])
    for name in base:
        scale = float(base[name].abs().max())
        tol = scale * (1e-5 if dtype == torch.float32 else 1e-12)
        torch.testing.assert_close(permuted[name], base[name][perm], rtol=0, atol=tol, msg=name)


# ------------------------------------------------------------------------------------ autograd
def test_autograd_through_values_and_positions():
    gen = torch.Generator().manual_seed(5)
    pos = torch.rand(25, 3, generator=gen, dtype=torch.float64) * 4 * L0
    ei = brute_edges(pos, 2.1 * L0)
    assert ei.shape[1] > 50
    p = torch.rand(25, generator=gen, dtype=torch.float64, requires_grad=True)
    v = torch.rand(25, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    x = pos.clone().requires_grad_(True)
    re = 2.1 * L0
    assert torch.autograd.gradcheck(lambda p: ops.gradient(pos, ei, p, re, N0_21), (p,))
    assert torch.autograd.gradcheck(lambda v: ops.divergence(pos, ei, v, re, N0_21), (v,))
    assert torch.autograd.gradcheck(lambda v: ops.laplacian(pos, ei, v, re, 10.0, 2e-3), (v,))
    assert torch.autograd.gradcheck(lambda p: ops.min_pressure_gradient(pos, ei, p, re, N0_21), (p,))
    assert torch.autograd.gradcheck(lambda p: ops.corrected_pressure_gradient(pos, ei, p, re, N0_21), (p,))
    assert torch.autograd.gradcheck(lambda x: ops.number_density(x, ei, re), (x,))
    assert torch.autograd.gradcheck(lambda x: ops.divergence(x, ei, v.detach(), re, N0_21), (x,))
    # A plain backward pass reaches the values.
    ops.gradient(pos, ei, p, re, N0_21).square().sum().backward()
    assert p.grad is not None and bool((p.grad != 0).any())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("dtype", DTYPES)
def test_cuda_matches_cpu(dtype):
    pos, ei, _, _ = lattice(dtype, 3.1)
    cpu = all_ops(pos, ei)
    gpu = all_ops(pos.cuda(), ei.cuda())
    for name in cpu:
        assert gpu[name].device.type == "cuda"
        scale = float(cpu[name].abs().max())
        tol = scale * (1e-5 if dtype == torch.float32 else 1e-12)
        torch.testing.assert_close(gpu[name].cpu(), cpu[name], rtol=0, atol=tol, msg=name)


def test_kernel_fast_path_equals_the_differentiable_one():
    # Without autograd the kernel takes a shorter sequence of passes; the numbers must be the same bits.
    re = 3.1 * 0.05
    dist = torch.cat(
        [
            torch.rand(10_000, dtype=torch.float64) * 0.2,
            torch.tensor(
                [0.0, 1e-9, 1e-8, re, re * (1 - 1e-16), float("inf"), float("nan")], dtype=torch.float64
            ),
        ]
    )
    for d in (dist, dist.float()):
        slow = ops.kernel(d.clone().requires_grad_(True), re).detach()
        assert torch.equal(ops.kernel(d, re), slow)


def _torch_only(m: pytest.MonkeyPatch) -> None:
    """Every kernel runs its torch body (the switch the compiled bodies are compared against)."""
    m.setattr(pair_kernels, "applies", lambda *tensors: False)


def _handed_to(monkeypatch: pytest.MonkeyPatch, torch_body: str) -> list[tuple]:
    """The calls of the operators' torch body ``torch_body`` from now on (each still runs)."""
    calls = []
    body = getattr(ops, torch_body)
    monkeypatch.setattr(ops, torch_body, lambda *a: calls.append(a) or body(*a))
    return calls


@pytest.mark.skipif(ops._operator_kernels() is None, reason="numba not installed")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("channels", [None, 3])
def test_compiled_laplacian_equals_the_torch_operations(monkeypatch, dtype, channels):
    # The compiled body (one pass per target row) gives the torch body's numbers to the bit, into a prefix of
    # the rows (num_nodes < N) too, and hands graphs not sorted by target to the torch body.
    gen = torch.Generator().manual_seed(7)
    pos = torch.rand(600, 3, generator=gen, dtype=dtype) * 0.4
    re = 3.1 * L0
    ei = brute_edges(pos, re)  # sorted by target, then source
    shape = (600,) if channels is None else (600, channels)
    values = torch.randn(shape, generator=gen, dtype=dtype)
    pos_dup = torch.cat([pos, pos[:1] + 1e-9])  # a near-coincident pair (r < 1e-8: weight 0)
    ei_dup = brute_edges(pos_dup, re)
    values_dup = torch.cat([values, values[:1]])
    for p, e, v, rows in (
        (pos, ei, values, None),
        (pos, ei[:, ei[1] < 250], values, 250),
        (pos_dup, ei_dup, values_dup, None),
    ):
        fast = ops.laplacian(p, e, v, re, 54.3, 3.24 * L0**2, num_nodes=rows)
        with monkeypatch.context() as m:
            _torch_only(m)
            slow = ops.laplacian(p, e, v, re, 54.3, 3.24 * L0**2, num_nodes=rows)
        assert fast.shape == slow.shape and torch.equal(fast, slow)
    assert pair_kernels.backend_for("laplacian", values, pos) is ops._laplacian_compiled
    handed = _handed_to(monkeypatch, "_laplacian_torch")
    constants = (re, 54.3, 3.24 * L0**2, 3, 600)
    ops._laplacian_compiled(ei, ops.edge_geometry(pos, ei)[1], values, *constants)
    assert handed == []
    shuffled = ei[:, torch.randperm(ei.shape[1], generator=gen)]
    ops._laplacian_compiled(shuffled, ops.edge_geometry(pos, shuffled)[1], values, *constants)
    assert len(handed) == 1
    bad = ei.clone()
    bad[0, 5] = 600  # a source beyond the values: handed over, reported by the torch body
    with pytest.raises((IndexError, RuntimeError)):
        ops._laplacian_compiled(bad, ops.edge_geometry(pos, ei)[1], values, *constants)
    assert len(handed) == 2
    with pytest.raises((IndexError, RuntimeError)):
        ops.laplacian(pos, bad, values, re, 54.3, 3.24 * L0**2, geometry=ops.edge_geometry(pos, ei))


@pytest.mark.skipif(ops._operator_kernels() is None, reason="numba not installed")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("include_self", [True, False])
def test_compiled_min_pressure_gradient_equals_the_torch_operations(monkeypatch, dtype, include_self):
    # One compiled pass per row gives the torch body's numbers to the bit, into a prefix of the rows too, with
    # sources left out as the torch body drops their edges (the dummy walls); unsorted graphs go to it.
    gen = torch.Generator().manual_seed(8)
    pos = torch.rand(600, 3, generator=gen, dtype=dtype) * 0.4
    re = 2.1 * L0
    ei = brute_edges(pos, re)
    p = torch.randn(600, generator=gen, dtype=dtype)
    sources = torch.rand(600, generator=gen) > 0.3
    pos_dup = torch.cat([pos, pos[:1] + 1e-9])  # a near-coincident pair (r < 1e-8: weight 0)
    ei_dup, p_dup = brute_edges(pos_dup, re), torch.cat([p, p[:1] - 1.0])
    cases = [
        (pos, ei, p, None, None),
        (pos, ei[:, ei[1] < 250], p, 250, sources),
        (pos_dup, ei_dup, p_dup, None, None),
    ]
    for x, e, pr, rows, src in cases:
        grad = functools.partial(
            ops.min_pressure_gradient,
            x,
            e,
            pr,
            re,
            N0_21,
            include_self=include_self,
            num_nodes=rows,
            sources=src,
        )
        fast = grad()
        with monkeypatch.context() as m:
            _torch_only(m)
            slow = grad()
            if src is not None:  # and the torch body with sources is the graph without those edges
                kept = e[:, src[e[0]]]
                plain = ops.min_pressure_gradient(
                    x, kept, pr, re, N0_21, include_self=include_self, num_nodes=rows
                )
                assert torch.equal(slow, plain)
        assert fast.shape == slow.shape and torch.equal(fast, slow)
        assert bool((fast != 0).any())
    assert pair_kernels.backend_for("min_pressure_gradient", pos, p) is ops._min_gradient_compiled
    handed = _handed_to(monkeypatch, "_min_gradient_torch")
    args = (re, N0_21, 3, include_self, 600, None, None)
    ops._min_gradient_compiled(pos, ei, p, *args)
    assert handed == []
    shuffled = ei[:, torch.randperm(ei.shape[1], generator=gen)]
    ops._min_gradient_compiled(pos, shuffled, p, *args)
    assert len(handed) == 1
    nan = p.clone()
    nan[ei[0, 0]] = float("nan")
    assert bool(torch.isnan(ops.min_pressure_gradient(pos, ei, nan, re, N0_21)[ei[1, 0]]).all())


@pytest.mark.skipif(ops._operator_kernels() is None, reason="numba not installed")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_number_density_equals_the_torch_operations(monkeypatch, dtype):
    gen = torch.Generator().manual_seed(9)
    pos = torch.rand(600, 3, generator=gen, dtype=dtype) * 0.4
    pos = torch.cat([pos, pos[:1] + 1e-9])  # a near-coincident pair (r < 1e-8: weight 0)
    re = 2.1 * L0
    ei = brute_edges(pos, re)
    for e, rows in ((ei, None), (ei[:, ei[1] < 250], 250), (ei[:, :0], None)):
        fast = ops.number_density(pos, e, re, num_nodes=rows)
        with monkeypatch.context() as m:
            _torch_only(m)
            slow = ops.number_density(pos, e, re, num_nodes=rows)
        assert fast.shape == slow.shape and torch.equal(fast, slow)
    assert pair_kernels.backend_for("number_density", pos) is ops._number_density_compiled
    handed = _handed_to(monkeypatch, "_number_density_torch")
    ops._number_density_compiled(ei, ops.edge_geometry(pos, ei)[1], re, 601, 601)
    assert handed == []
    shuffled = ei[:, torch.randperm(ei.shape[1], generator=gen)]
    ops._number_density_compiled(shuffled, ops.edge_geometry(pos, shuffled)[1], re, 601, 601)
    assert len(handed) == 1


@pytest.mark.skipif(ops._operator_kernels() is None, reason="numba not installed")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_kernel_equals_the_torch_operations(monkeypatch, dtype):
    re = 2.1 * L0
    gen = torch.Generator().manual_seed(10)
    dist = torch.cat(
        [torch.rand(20000, generator=gen, dtype=dtype) * 1.2 * re, torch.tensor([0.0, 1e-9, re], dtype=dtype)]
    )
    fast = ops.kernel(dist, re)
    with monkeypatch.context() as m:
        _torch_only(m)
        slow = ops.kernel(dist, re)
    assert torch.equal(fast, slow) and fast.dtype == dtype
    handed = _handed_to(monkeypatch, "_kernel_torch")
    ops._kernel_compiled(dist, re)
    ops._kernel_compiled(dist[:100], re)  # a few pairs: the torch body, cheaper than a call
    assert [a[0].numel() for a in handed] == [100]
    assert float(fast[-3:].abs().sum()) == 0.0 and bool((fast > 0).any())


@pytest.mark.skipif(ops._operator_kernels() is None, reason="numba not installed")
@pytest.mark.parametrize(("n", "e"), [(50, 400), (50, 0), (3, 1), (3000, 150_000)])
def test_the_check_pass_fills_the_row_pointer_searchsorted_would(n, e):
    import numpy as np

    kern = pair_kernels.load(csr.NUMBA)
    rng = np.random.default_rng(n + e)
    # empty rows at both ends and in the middle (targets drawn from a part of 0..n-1), several chunks
    dst = np.sort(rng.integers(n // 3, max(n // 3 + 1, n - n // 4), e))
    src = rng.integers(0, n, e)
    expected = np.searchsorted(dst, np.arange(n + 1), side="left")
    row_ptr = np.full(n + 1, -7, dtype=np.int64)
    assert kern.check_edges(dst, src, n, n, row_ptr) == (0, 0)
    assert np.array_equal(row_ptr, expected)
    key = np.unique(dst * n + src)  # sorted by target then source, each pair once
    pairs_dst, pairs_src = key // n, key % n
    row_ptr = np.full(n + 1, -7, dtype=np.int64)
    assert kern.check_pairs(pairs_dst, pairs_src, n, n, row_ptr) == (0, 0)
    assert np.array_equal(row_ptr, np.searchsorted(pairs_dst, np.arange(n + 1), side="left"))
    if e > 1:  # what the pass reports instead
        assert kern.check_edges(dst[::-1].copy(), src, n, n, row_ptr)[0] > 0
        assert kern.check_edges(dst, src, n, n - 1 - n // 4, row_ptr)[1] > 0  # a target out of range
