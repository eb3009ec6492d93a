"""Tests for the MPS pressure Poisson equation: assembly against a dense oracle, SPD-ness, solves."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from lagfluid.neighbors import pair_kernels
from lagfluid.physics.ppe import PPEInfo, assemble_ppe, ppe_residual, ppe_source, solve_ppe
from lagfluid.physics.ppe import solve as ppe_solve
from lagfluid.physics.ppe import system as ppe_system

RHO = 1000.0
L0 = 0.05
RE_LAP, RE_N = 3.1 * L0, 2.1 * L0


@dataclass
class Scene:
    pos: np.ndarray  # (N, 3)
    ptype: np.ndarray  # (N,) 1 fluid, 2 wall, 3 dummy
    edge_index: torch.Tensor  # (2, E) j -> i
    dist: np.ndarray  # (E,)
    coef: np.ndarray  # (E,) 2d/(lambda n0_lap) w_ij
    solve: np.ndarray  # (N,) bool
    dirichlet: np.ndarray  # (N,) bool
    n0: float


def _lattice_constants() -> tuple[float, float, float]:
    """n0 (radius 2.1 l0), n0_lap and lambda (radius 3.1 l0) of a full cubic lattice."""
    g = np.arange(-4, 5)
    off = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) * L0
    r = np.linalg.norm(off, axis=1)
    r = r[r > 0]
    n0 = np.sum(np.where(r < RE_N, RE_N / r - 1, 0.0))
    w = np.where(r < RE_LAP, RE_LAP / r - 1, 0.0)
    n0_lap = w.sum()
    lam = np.sum(r * r * w) / n0_lap
    return float(n0), float(n0_lap), float(lam)


def make_tank(nx: int, ny: int, nz: int, layers: int = 3, above: int = 2, blob: bool = False) -> Scene:
    """A fluid block in a container (1 wall + dummy layers on floor and sides), free surface on top.

    With ``blob=True`` a second, fully enclosed fluid cube (no free surface) is added far away.
    """
    pts, types = [], []
    for i in range(-layers, nx + layers):
        for j in range(-layers, ny + layers):
            for k in range(-layers, nz + above):
                if 0 <= i < nx and 0 <= j < ny and k >= 0:
                    if k < nz:
                        pts.append((i, j, k))
                        types.append(1)
                    continue
                d = max(max(-i, i - nx + 1, 0), max(-j, j - ny + 1, 0), max(-k, 0))
                pts.append((i, j, k))
                types.append(2 if d == 1 else 3)
    pos = np.array(pts, float) * L0
    ptype = np.array(types)
    forced_inner = np.zeros(len(pos), bool)
    if blob:
        g = np.arange(4)
        cube = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) * L0 + 10.0
        pos = np.concatenate([pos, cube])
        ptype = np.concatenate([ptype, np.ones(len(cube), int)])
        forced_inner = np.concatenate([forced_inner, np.ones(len(cube), bool)])
    tree = cKDTree(pos)
    dmat = tree.sparse_distance_matrix(tree, RE_LAP, output_type="coo_matrix")
    keep = dmat.row != dmat.col
    i, j, r = dmat.row[keep], dmat.col[keep], dmat.data[keep]
    order = np.lexsort((j, i))  # CSR order: by centre, then neighbour
    i, j, r = i[order], j[order], r[order]
    n0, n0_lap, lam = _lattice_constants()
    n = np.bincount(i, weights=np.where(r < RE_N, RE_N / r - 1, 0.0), minlength=len(pos))
    coef = 2 * 3 / (lam * n0_lap) * (RE_LAP / r - 1)
    surface = (n < 0.97 * n0) & ~forced_inner
    solve = (ptype != 3) & ~surface
    dirichlet = (ptype != 3) & surface
    edge_index = torch.from_numpy(np.stack([j, i]).astype(np.int64))
    return Scene(pos, ptype, edge_index, r, coef, solve, dirichlet, n0)


def assemble(scene: Scene, dtype=torch.float64, **kw):
    return assemble_ppe(
        scene.edge_index,
        torch.tensor(scene.coef, dtype=dtype),
        torch.from_numpy(scene.solve),
        RHO,
        dirichlet_mask=torch.from_numpy(scene.dirichlet),
        **kw,
    )


def dense_oracle(scene: Scene, factor: float = 2.0) -> np.ndarray:
    """A = -(1/rho) L on the solved set, built entry by entry (the definition, no vectorisation)."""
    index = np.flatnonzero(scene.solve)
    pos_of = {int(p): a for a, p in enumerate(index)}
    a = np.zeros((len(index), len(index)))
    has_dirichlet = np.zeros(len(index), bool)
    src, dst = scene.edge_index.numpy()
    for e in range(src.size):
        i, j, c = int(dst[e]), int(src[e]), scene.coef[e] / RHO
        if i not in pos_of:
            continue
        if scene.solve[j]:
            a[pos_of[i], pos_of[j]] -= c
            a[pos_of[i], pos_of[i]] += c
        elif scene.dirichlet[j]:
            a[pos_of[i], pos_of[i]] += c
            has_dirichlet[pos_of[i]] = True
    # Components without a Dirichlet row: breadth-first search, then the diagonal doubling.
    reached = has_dirichlet.copy()
    frontier = list(np.flatnonzero(reached))
    while frontier:
        row = frontier.pop()
        for col in np.flatnonzero(a[row]):
            if not reached[col]:
                reached[col] = True
                frontier.append(col)
    a[~reached, ~reached] *= factor
    return a


@pytest.fixture(scope="module")
def tank() -> Scene:
    return make_tank(5, 5, 6)  # ~1.7k particles, ~200 unknowns


@pytest.fixture(scope="module")
def big_tank() -> Scene:
    return make_tank(9, 9, 10)  # ~4.4k particles, ~1.1k unknowns


def hydrostatic(scene: Scene, index: torch.Tensor) -> torch.Tensor:
    z = scene.pos[index.numpy(), 2]
    return torch.from_numpy(RHO * 9.8065 * (z.max() + L0 - z))


# ---------------------------------------------------------------------------------------------- assembly
def test_hand_checked_1d_chain():
    # x = 0, 1, 2, 3 (l0 = 1): particles 0, 1 solved, 2 free surface, 3 dummy; re = 2.5, coef = w.
    pos = np.array([0.0, 1.0, 2.0, 3.0])
    pairs = [(j, i) for i in range(4) for j in range(4) if i != j and abs(pos[i] - pos[j]) < 2.5]
    src, dst = np.array(pairs).T
    coef = 2.5 / np.abs(pos[src] - pos[dst]) - 1.0  # 1.5 at distance 1, 0.25 at distance 2
    system = assemble_ppe(
        torch.from_numpy(np.stack([src, dst])),
        torch.from_numpy(coef),
        torch.tensor([True, True, False, False]),
        2.0,
        dirichlet_mask=torch.tensor([False, False, True, False]),
    )
    expected = np.array(
        [
            [(1.5 + 0.25) / 2, -1.5 / 2],  # row 0: solved 1 (1.5), free-surface 2 (0.25, diagonal only)
            [-1.5 / 2, (1.5 + 1.5) / 2],  # row 1: solved 0, free-surface 2; dummy 3 ignored
        ]
    )
    np.testing.assert_allclose(system.matrix.to_dense().numpy(), expected, rtol=1e-15)
    assert system.index.tolist() == [0, 1]
    assert not bool(system.isolated.any())


def test_solved_particle_with_only_dummy_neighbours(caplog):
    # Particle 0 (solved) sees only dummy particle 2; 1 (solved) sees 0 and free-surface 3.
    edge_index = torch.tensor([[2, 0, 1, 3], [0, 1, 0, 1]])
    coef = torch.tensor([1.0, 2.0, 2.0, 1.0], dtype=torch.float64)
    solve = torch.tensor([True, True, False, False])
    dirichlet = torch.tensor([False, False, False, True])
    with pytest.raises(ValueError, match="symmetric"):  # without 1 -> 0 the solved pair is one-way
        assemble_ppe(edge_index[:, [0, 1, 3]], coef[[0, 1, 3]], solve, 1.0, dirichlet_mask=dirichlet)
    system = assemble_ppe(edge_index, coef, solve, 1.0, dirichlet_mask=dirichlet)
    np.testing.assert_allclose(system.matrix.to_dense().numpy(), [[2.0, -2.0], [-2.0, 3.0]])
    # Now 0 loses its only solved neighbour too: an all-zero row gets a typical diagonal, loudly.
    solve = torch.tensor([True, False, False, False])
    with caplog.at_level(logging.WARNING, logger="lagfluid.physics.ppe"):
        system = assemble_ppe(edge_index, coef, solve, 1.0, dirichlet_mask=torch.zeros(4, dtype=torch.bool))
    assert float(system.matrix.to_dense()[0, 0]) > 0
    assert any("no fluid/wall/free-surface neighbour" in r.getMessage() for r in caplog.records)
    p, info = solve_ppe(system, torch.ones(1, dtype=torch.float64))
    assert info.converged and torch.isfinite(p).all()


def test_matches_dense_oracle_and_is_spd(tank):
    system = assemble(tank)
    a = system.matrix.to_dense().numpy()
    assert system.num_unknowns == tank.solve.sum() > 100
    assert system.index.tolist() == np.flatnonzero(tank.solve).tolist()
    np.testing.assert_allclose(a, dense_oracle(tank), rtol=1e-13, atol=1e-15)
    np.testing.assert_array_equal(a, a.T)
    assert np.linalg.eigvalsh(a).min() > 0
    # CSR invariants (sorted, unique columns) hold: torch's own validator accepts the matrix.
    m = system.matrix
    torch.sparse_csr_tensor(m.crow_indices(), m.col_indices(), m.values(), m.shape, check_invariants=True)


def test_row_sums_interior_zero_surface_dominant(tank):
    system = assemble(tank)
    a = system.matrix.to_dense().numpy()
    row_sum = a.sum(axis=1)
    # Rows with a free-surface neighbour: strictly dominant; others (incl. walls beside dummies): sum 0.
    src, dst = tank.edge_index.numpy()
    near_surface = np.zeros(len(tank.pos), bool)
    near_surface[dst[tank.dirichlet[src]]] = True
    near = near_surface[system.index.numpy()]
    assert near.any() and (~near).any()
    scale = np.abs(np.diag(a)).max()
    np.testing.assert_allclose(row_sum[~near], 0.0, atol=1e-12 * scale)
    assert (row_sum[near] > 1e-6 * scale).all()
    # Wall rows with dummy neighbours are among the zero-sum rows: dummy takes no part.
    wall_rows = (tank.ptype[system.index.numpy()] == 2) & ~near
    assert wall_rows.any()


def test_unsorted_edges_give_the_same_matrix(tank):
    perm = torch.randperm(tank.edge_index.shape[1], generator=torch.Generator().manual_seed(0))
    shuffled = assemble_ppe(
        tank.edge_index[:, perm],
        torch.from_numpy(tank.coef)[perm],
        torch.from_numpy(tank.solve),
        RHO,
        dirichlet_mask=torch.from_numpy(tank.dirichlet),
    )
    torch.testing.assert_close(
        shuffled.matrix.to_dense(), assemble(tank).matrix.to_dense(), rtol=1e-14, atol=0
    )


def test_isolated_cluster_is_detected_and_regularised():
    scene = make_tank(3, 3, 4, blob=True)
    blob = np.zeros(len(scene.pos), bool)
    blob[-64:] = True
    for components in ("scipy", "torch"):
        system = assemble(scene, components=components)
        assert system.n_isolated_components == 1
        np.testing.assert_array_equal(system.isolated.numpy(), blob[system.index.numpy()])
    a = system.matrix.to_dense().numpy()
    np.testing.assert_allclose(a, dense_oracle(scene), rtol=1e-13, atol=1e-15)
    assert np.linalg.eigvalsh(a).min() > 0
    # No free surface anywhere: the tank and the blob are two isolated components.
    for components in ("scipy", "torch"):
        enclosed = assemble_ppe(
            scene.edge_index,
            torch.from_numpy(scene.coef),
            torch.from_numpy(scene.ptype != 3),
            RHO,
            dirichlet_mask=torch.zeros(len(scene.pos), dtype=torch.bool),
            components=components,
        )
        assert bool(enclosed.isolated.all()) and enclosed.n_isolated_components == 2
    # Without the remedy the enclosed blob's block is singular (zero row sums): the reason for it.
    plain = assemble(scene, isolated_diagonal_factor=1.0).matrix.to_dense().numpy()
    iso = system.isolated.numpy()
    assert abs(np.linalg.eigvalsh(plain[np.ix_(iso, iso)]).min()) < 1e-10 * np.abs(plain).max()
    # A compressed blob still solves to a finite, positive pressure.
    b = torch.full((system.num_unknowns,), 50.0, dtype=torch.float64)
    for method in ("scipy_cg", "torch_cg"):
        p, info = solve_ppe(system, b, method=method)
        assert info.converged and torch.isfinite(p).all() and bool((p[system.isolated] > 0).all())


def test_fully_enclosed_scene_every_row_isolated(tank):
    # No free surface at all: every solved particle, wall included, is one isolated component.
    solve = tank.ptype != 3
    system = assemble_ppe(
        tank.edge_index,
        torch.from_numpy(tank.coef),
        torch.from_numpy(solve),
        RHO,
        dirichlet_mask=torch.zeros(len(solve), dtype=torch.bool),
    )
    assert bool(system.isolated.all()) and system.n_isolated_components == 1
    p, info = solve_ppe(system, torch.ones(system.num_unknowns, dtype=torch.float64))
    assert info.converged and torch.isfinite(p).all()


def _drop_solved_pair_edge(s: Scene) -> dict:
    src, dst = s.edge_index.numpy()
    e = int(np.flatnonzero(s.solve[src] & s.solve[dst])[0])
    keep = torch.ones(s.edge_index.shape[1], dtype=torch.bool)
    keep[e] = False
    return {"edge_index": s.edge_index[:, keep], "coef": torch.from_numpy(s.coef)[keep]}


@pytest.mark.parametrize(
    ("name", "change", "match"),
    [
        ("overlap", lambda s: {"dirichlet_mask": torch.from_numpy(s.solve)}, "overlap"),
        ("negative", lambda s: {"coef": -torch.from_numpy(s.coef)}, "coef"),
        ("nan", lambda s: {"coef": torch.from_numpy(s.coef).clone().fill_(float("nan"))}, "coef"),
        ("short coef", lambda s: {"coef": torch.from_numpy(s.coef)[:-1]}, "coef"),
        ("range", lambda s: {"edge_index": s.edge_index + len(s.pos)}, "edge_index"),
        ("one way", lambda s: _drop_solved_pair_edge(s), "symmetric"),
        (
            "duplicate",
            lambda s: {
                "edge_index": torch.cat([s.edge_index, s.edge_index], 1),
                "coef": torch.from_numpy(np.concatenate([s.coef, s.coef])),
            },
            "duplicate",
        ),
        ("density", lambda s: {"density": 0.0}, "density"),
    ],
)
def test_assembly_rejects_bad_input(tank, name, change, match):
    args = {
        "edge_index": tank.edge_index,
        "coef": torch.from_numpy(tank.coef),
        "solve_mask": torch.from_numpy(tank.solve),
        "density": RHO,
        "dirichlet_mask": torch.from_numpy(tank.dirichlet),
    }
    args.update(change(tank))
    with pytest.raises(ValueError, match=match):
        assemble_ppe(**args)


# ---------------------------------------------------------------------------------------------- solve
@pytest.mark.parametrize("method", ["scipy_cg", "torch_cg", "pyamg"])
def test_manufactured_hydrostatic_solution(big_tank, method):
    if method == "pyamg":
        pytest.importorskip("pyamg")
    system = assemble(big_tank)
    p_star = hydrostatic(big_tank, system.index)
    b = torch.from_numpy(system.to_scipy() @ p_star.numpy())
    p, info = solve_ppe(system, b, tol=1e-10, maxiter=1000, method=method)
    assert isinstance(info, PPEInfo) and info.method == method
    assert info.converged and info.residual <= 1e-10 and info.iterations > 0
    torch.testing.assert_close(p, p_star, rtol=1e-7, atol=1e-6 * float(p_star.max()))


def test_scipy_and_torch_agree_and_auto_picks_by_device_and_threads(big_tank):
    system = assemble(big_tank)
    rng = np.random.default_rng(1)
    b = torch.from_numpy(rng.normal(size=system.num_unknowns))
    p_sc, i_sc = solve_ppe(system, b, tol=1e-9, method="scipy_cg")
    p_to, i_to = solve_ppe(system, b, tol=1e-9, method="torch_cg")
    threads = torch.get_num_threads()
    try:  # auto on the CPU: SciPy's single-threaded SpMV on one thread, torch's with more
        torch.set_num_threads(1)
        p_au, i_au = solve_ppe(system, b, tol=1e-9)
        assert i_au.method == "scipy_cg"
        torch.set_num_threads(2)
        assert solve_ppe(system, b, tol=1e-9)[1].method == "torch_cg"
    finally:
        torch.set_num_threads(threads)
    assert i_sc.converged and i_to.converged
    assert abs(i_sc.iterations - i_to.iterations) <= 1  # same algorithm, same preconditioner
    scale = float(p_sc.abs().max())
    torch.testing.assert_close(p_to, p_sc, rtol=0, atol=1e-7 * scale)
    torch.testing.assert_close(p_au, p_sc, rtol=0, atol=1e-7 * scale)


@pytest.mark.parametrize("method", ["scipy_cg", "torch_cg"])
def test_nonconvergence_is_reported(big_tank, method, caplog):
    system = assemble(big_tank)
    b = torch.from_numpy(np.random.default_rng(2).normal(size=system.num_unknowns))
    with caplog.at_level(logging.WARNING, logger="lagfluid.physics.ppe"):
        p, info = solve_ppe(system, b, maxiter=1, method=method)
    assert not info.converged and info.iterations == 1
    assert 1e-6 < info.residual < 1.0  # one CG step: better than p = 0, far from converged
    assert torch.isfinite(p).all()
    assert any(
        "did not converge" in r.getMessage() and "1 iterations" in r.getMessage() for r in caplog.records
    )
    assert info.residual == pytest.approx(ppe_residual(system, p, b), rel=1e-9)


@pytest.mark.parametrize("method", ["scipy_cg", "torch_cg", "pyamg"])
def test_warm_start_from_exact_solution(big_tank, method):
    if method == "pyamg":
        pytest.importorskip("pyamg")
    system = assemble(big_tank)
    b = torch.from_numpy(np.random.default_rng(3).normal(size=system.num_unknowns))
    p_exact, _ = solve_ppe(system, b, tol=1e-13, maxiter=2000, method="scipy_cg")
    p, info = solve_ppe(system, b, x0=p_exact, tol=1e-6, method=method)
    assert info.converged and info.iterations <= 1
    torch.testing.assert_close(p, p_exact, rtol=0, atol=1e-5 * float(p_exact.abs().max()))
    # A perturbed guess still needs fewer iterations than a cold start.
    _, cold = solve_ppe(system, b, tol=1e-6, method=method)
    _, warm = solve_ppe(system, b, x0=p_exact * 1.01, tol=1e-6, method=method)
    assert warm.iterations < cold.iterations


def test_absolute_and_relative_tolerance(big_tank):
    system = assemble(big_tank)
    b = 1e3 * torch.from_numpy(np.random.default_rng(4).normal(size=system.num_unknowns))
    bnorm = float(torch.linalg.vector_norm(b))
    _, rel = solve_ppe(system, b, tol=1e-6, tol_mode="rel")
    _, ab = solve_ppe(system, b, tol=1e-6 * bnorm / 10, tol_mode="abs", maxiter=1000)
    assert rel.converged and rel.residual <= 1e-6
    assert ab.converged and ab.residual <= 1e-7 and ab.iterations > rel.iterations


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("method", ["scipy_cg", "torch_cg"])
def test_float32_and_float64(big_tank, dtype, method):
    system = assemble(big_tank, dtype=dtype)
    assert system.matrix.values().dtype == dtype
    p_star = hydrostatic(big_tank, system.index)
    b = torch.from_numpy(assemble(big_tank).to_scipy() @ p_star.numpy()).to(dtype)
    p, info = solve_ppe(system, b, tol=1e-6, method=method)
    assert p.dtype == dtype and info.converged
    torch.testing.assert_close(p.double(), p_star, rtol=1e-4, atol=1e-4 * float(p_star.max()))
    if method == "torch_cg":
        # Iterating in float32 itself (dtype=None) still gets to a loose tolerance.
        p32, info32 = solve_ppe(system, b, tol=1e-4, method=method, compute_dtype=None)
        assert p32.dtype == dtype and info32.converged


def test_numpy_and_scipy_inputs(tank):
    system = assemble(tank)
    b = np.random.default_rng(5).normal(size=system.num_unknowns)
    p, info = solve_ppe(system.to_scipy(), b, tol=1e-9)
    assert isinstance(p, np.ndarray) and info.converged
    assert ppe_residual(system.to_scipy(), p, b) == pytest.approx(info.residual, rel=1e-9)


def test_bad_solve_input(tank):
    system = assemble(tank)
    k = system.num_unknowns
    b = torch.ones(k, dtype=torch.float64)
    with pytest.raises(ValueError, match="b contains NaN"):
        solve_ppe(system, torch.full((k,), float("nan"), dtype=torch.float64))
    with pytest.raises(ValueError, match=rf"b must have shape \({k},\)"):
        solve_ppe(system, torch.ones(k + 1, dtype=torch.float64))
    with pytest.raises(ValueError, match="x0"):
        solve_ppe(system, b, x0=torch.ones(k - 1, dtype=torch.float64))
    with pytest.raises(ValueError, match="x0 contains NaN"):
        solve_ppe(system, b, x0=torch.full((k,), float("inf"), dtype=torch.float64))
    with pytest.raises(ValueError, match="method"):
        solve_ppe(system, b, method="lu")
    with pytest.raises(ValueError, match="tol_mode"):
        solve_ppe(system, b, tol_mode="relative")


def test_empty_system_and_zero_rhs(tank):
    none = torch.zeros(len(tank.pos), dtype=torch.bool)
    system = assemble_ppe(tank.edge_index, torch.from_numpy(tank.coef), none, RHO, dirichlet_mask=none)
    assert system.num_unknowns == 0 and system.matrix.shape == (0, 0)
    p, info = solve_ppe(system, torch.zeros(0, dtype=torch.float64))
    assert p.shape == (0,) and info.converged and info.iterations == 0
    full = assemble(tank)
    p, info = solve_ppe(full, torch.zeros(full.num_unknowns), x0=torch.ones(full.num_unknowns))
    assert info.converged and bool((p == 0).all())


def test_pyamg_missing_falls_back_loudly(tank, monkeypatch, caplog):
    monkeypatch.setattr(ppe_solve, "pyamg_available", lambda: False)
    system = assemble(tank)
    with caplog.at_level(logging.WARNING, logger="lagfluid.physics.ppe"):
        _, info = solve_ppe(system, torch.ones(system.num_unknowns, dtype=torch.float64), method="pyamg")
    assert info.method == "scipy_cg" and info.converged
    assert any("PyAMG is not installed" in r.getMessage() for r in caplog.records)


# ---------------------------------------------------------------------------------------------- source
def test_source_sign_compression_gives_positive_pressure(big_tank):
    system = assemble(big_tank)
    n_all = len(big_tank.pos)
    dt = 0.002
    # Compressed (n > n0) and converging (div v < 0) fluid: b > 0 and p > 0 everywhere.
    b = ppe_source(torch.full((n_all,), -0.5), torch.full((n_all,), 1.01 * big_tank.n0), big_tank.n0, dt)
    assert bool((b > 0).all())
    p, info = solve_ppe(system, system.gather(b.double()))
    assert info.converged and bool((p > 0).all())
    # Expanded and diverging: the opposite sign.
    b = ppe_source(torch.full((n_all,), 0.5), torch.full((n_all,), 0.99 * big_tank.n0), big_tank.n0, dt)
    p, info = solve_ppe(system, system.gather(b.double()))
    assert info.converged and bool((p < 0).all())
    # The formula of FGN_ORIGINAL item 5, term by term.
    div, n = torch.tensor([0.3], dtype=torch.float64), torch.tensor([1.02 * big_tank.n0], dtype=torch.float64)
    expected = -0.8 * 0.3 / dt + 0.2 * 0.02 / dt**2
    assert float(ppe_source(div, n, big_tank.n0, dt)) == pytest.approx(expected, rel=1e-6)


def test_scatter_gather_roundtrip(tank):
    system = assemble(tank)
    values = torch.arange(len(tank.pos), dtype=torch.float64)
    restricted = system.gather(values)
    full = system.scatter(restricted)
    assert torch.equal(full[system.index], values[system.index])
    assert bool((full[~torch.from_numpy(tank.solve)] == 0).all())


def test_trusted_assembly_and_scipy_merge_equal_the_checked_torch_path(tank, monkeypatch):
    # The solver assembles with check=False on its own (sorted, symmetric) graphs and merges the diagonal
    # with SciPy on the CPU: both must give the very same CSR arrays as the checked, all-torch path.
    checked = assemble(tank, dtype=torch.float32)
    trusted = assemble(tank, dtype=torch.float32, check=False)

    def torch_merge(crow, cols, off, diag, k, idt):
        rows = torch.repeat_interleave(torch.arange(k), torch.diff(crow))
        crow2, col, val, _ = ppe_system._csr_with_diagonal(rows, cols, off, diag, k)
        return torch.sparse_csr_tensor(crow2.to(idt), col.to(idt), val, (k, k), check_invariants=False)

    monkeypatch.setattr(ppe_system, "_csr_plus_diagonal_scipy", torch_merge)
    all_torch = assemble(tank, dtype=torch.float32)
    for other in (trusted, all_torch):
        assert torch.equal(other.matrix.crow_indices(), checked.matrix.crow_indices())
        assert torch.equal(other.matrix.col_indices(), checked.matrix.col_indices())
        assert torch.equal(other.matrix.values(), checked.matrix.values())
        assert torch.equal(other.isolated, checked.isolated) and torch.equal(other.index, checked.index)


def test_pcg_jacobi_matches_scipy_cg(big_tank):
    # Our BLAS-free loop is SciPy's Jacobi CG written out: same iterates up to round-off.
    import scipy.sparse.linalg as spla

    a = assemble(big_tank).to_scipy()
    b = np.random.default_rng(3).normal(size=a.shape[0])
    x0 = np.random.default_rng(4).normal(size=a.shape[0])
    inv_diag = 1.0 / a.diagonal()
    precond = spla.LinearOperator(a.shape, matvec=lambda r: inv_diag * r.ravel(), dtype=np.float64)
    iters: list[int] = []
    for start in (None, x0):
        iters.clear()
        ref, _ = spla.cg(a, b, x0=start, rtol=0.0, atol=1e-9, maxiter=500, M=precond, callback=iters.append)
        x, n = ppe_solve._pcg_jacobi(a, b, start, 1e-9, 500)
        assert abs(n - len(iters)) <= 1
        assert np.linalg.norm(b - a @ x) <= 1e-9
        np.testing.assert_allclose(x, ref, rtol=0, atol=1e-8 * np.abs(ref).max())


def _csr_arrays(system):
    m = system.matrix
    return m.crow_indices(), m.col_indices(), m.values(), system.isolated, system.index


@pytest.mark.skipif(ppe_system._ppe_kernels() is None, reason="numba not installed")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", ["tank", "blob", "enclosed", "empty_row", "zero_weights"])
def test_compiled_assembly_equals_the_torch_assembly(monkeypatch, caplog, dtype, case):
    # The solver's CPU assembly (check=False: compiled row passes and a breadth-first search) must give
    # the very arrays of the torch assembly, the remedies for isolated components and empty rows included.
    scene = make_tank(3, 3, 4, blob=case == "blob")
    edge_index, coef = scene.edge_index, torch.tensor(scene.coef, dtype=dtype)
    solve, dirichlet = torch.from_numpy(scene.solve), torch.from_numpy(scene.dirichlet)
    if case == "enclosed":  # no free surface: the whole tank is one isolated component
        solve, dirichlet = torch.from_numpy(scene.ptype != 3), torch.zeros_like(dirichlet)
    if case == "empty_row":  # a solved particle whose every neighbour is a dummy
        lonely = int(np.flatnonzero(scene.solve)[0])
        others = edge_index[1] == lonely
        solve = solve.clone()
        dirichlet = dirichlet.clone()
        neighbours = edge_index[0][others]
        solve[neighbours], dirichlet[neighbours] = False, False
    if case == "zero_weights":  # pairs exactly at re couple nothing
        coef = coef.clone()
        coef[::7] = 0.0
        coef[edge_index[1] == edge_index[0][::7][0]] = 0.0
    caplog.set_level(logging.WARNING, logger="lagfluid.physics.ppe")
    compiled = assemble_ppe(edge_index, coef, solve, RHO, dirichlet_mask=dirichlet, check=False)
    assert pair_kernels.backend_for("ppe_assembly", coef) is ppe_system._assemble_compiled
    monkeypatch.setattr(pair_kernels, "applies", lambda *tensors: False)  # every torch (or SciPy) body
    reference = assemble_ppe(edge_index, coef, solve, RHO, dirichlet_mask=dirichlet, check=False)
    for got, want in zip(_csr_arrays(compiled), _csr_arrays(reference), strict=True):
        assert got.dtype == want.dtype and torch.equal(got, want)
    assert compiled.n_isolated_components == reference.n_isolated_components
    # (the lonely particle is a component of its own without a free-surface neighbour)
    expected_components = {"blob": 1, "enclosed": 1, "empty_row": 1}.get(case, 0)
    assert compiled.n_isolated_components == expected_components
    if case == "empty_row":
        assert any("no fluid/wall/free-surface neighbour" in r.getMessage() for r in caplog.records)
