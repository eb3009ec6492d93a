"""Radius graphs: every backend against brute force and an independent oracle; batching, receivers,
loops, overflow, input checks; edge geometry; the CSR kernel adjacency and its gradients."""

from __future__ import annotations

import itertools
import math
import re
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import lagfluid.neighbors.search as nb
from lagfluid.neighbors import (
    NeighborOverflowError,
    available_backends,
    edge_vectors,
    kernel_adjacency,
    radius_graph,
    restrict_radius,
)

L0 = 0.05
FAST = [b for b in available_backends() if b != "brute"]
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def lattice(m: int, dim: int = 3, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Simple-cubic lattice of m^dim points, spacing L0, as exact as the dtype allows."""
    grid = torch.stack(torch.meshgrid(*[torch.arange(m)] * dim, indexing="ij"), dim=-1).reshape(-1, dim)
    return (grid.to(torch.float64) * L0).to(dtype)


def oracle(pos: torch.Tensor, r: float, batch=None, receivers=None, loop=False) -> torch.Tensor:
    """All pairs |x_j - x_i| < r by numpy float64 broadcasting, sorted by (i, j): independent of lagfluid."""
    x = pos.double().numpy()
    d = np.sqrt(((x[None, :, :] - x[:, None, :]) ** 2).sum(-1))  # d[i, j]
    mask = d < r
    if not loop:
        np.fill_diagonal(mask, False)
    if batch is not None:
        b = batch.numpy()
        mask &= b[:, None] == b[None, :]
    if receivers is not None:
        mask &= receivers.numpy()[:, None]
    i, j = np.nonzero(mask)
    return torch.from_numpy(np.stack([j, i])).long()


def lattice_degree(factor: float, dim: int) -> int:
    """Number of nonzero integer vectors shorter than ``factor`` (interior degree on a unit lattice)."""
    k = math.ceil(factor)
    return sum(
        1
        for v in itertools.product(range(-k, k + 1), repeat=dim)
        if any(v) and sum(c * c for c in v) < factor * factor
    )


def assert_sorted_strict(edge_index: torch.Tensor, pos: torch.Tensor, r: float) -> None:
    j, i = edge_index
    key = i * pos.shape[0] + j
    assert bool((key[1:] > key[:-1]).all()), "edges not sorted by (target, source) or repeated"
    assert bool((edge_vectors(pos, edge_index)[1] < r).all())


# ------------------------------------------------------------------------------------------ correctness
@pytest.mark.parametrize("backend", FAST)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [1, 2, 57, 400])
@pytest.mark.parametrize("dim", [3, 2])
def test_random_points_match_brute_and_oracle(backend, dtype, n, dim):
    gen = torch.Generator().manual_seed(n + dim)
    pos = torch.rand(n, dim, generator=gen, dtype=torch.float64).to(dtype)
    r = 0.21
    ref = radius_graph(pos, r, backend="brute")
    out = radius_graph(pos, r, backend=backend)
    assert out.dtype == torch.long and out.shape[0] == 2
    assert torch.equal(out, ref)
    assert torch.equal(ref, oracle(pos, r))
    assert_sorted_strict(out, pos, r)
    if n > 2:
        assert out.shape[1] > 0


def test_empty_input_and_auto_backend():
    assert radius_graph(torch.zeros(0, 3), 0.1).shape == (2, 0)
    assert radius_graph(torch.zeros(0, 3), 0.1, backend="cell_list").shape == (2, 0)
    assert radius_graph(torch.zeros(1, 3), 0.1).shape == (2, 0)
    assert radius_graph(torch.zeros(1, 3), 0.1, loop=True).tolist() == [[0], [0]]
    pos = torch.rand(100, 3, generator=torch.Generator().manual_seed(0))
    assert torch.equal(radius_graph(pos, 0.3), radius_graph(pos, 0.3, backend="brute"))


@pytest.mark.parametrize("backend", [*FAST, "brute"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("factor", [0.92, 2.1, 3.1])
def test_lattice_interior_degree(backend, dtype, factor):
    m = 9  # centre node (4, 4, 4) is 4 spacings from every face: its 3.1 l0 ball is complete
    pos = lattice(m, dtype=dtype)
    r = factor * L0
    out = radius_graph(pos, r, backend=backend)
    assert torch.equal(out, oracle(pos, r))
    degree = torch.bincount(out[1], minlength=pos.shape[0])
    centre = (4 * m + 4) * m + 4
    expected = {0.92: 0, 2.1: 6 + 12 + 8 + 6, 3.1: 122}[factor]
    assert expected == lattice_degree(factor, 3)
    assert int(degree[centre]) == expected
    # The degree is the same for every node whose ball fits inside the lattice.
    idx = torch.arange(m)
    k = math.ceil(factor)
    inner = ((idx >= k) & (idx < m - k)).nonzero().flatten()
    interior = ((inner[:, None, None] * m + inner[None, :, None]) * m + inner[None, None, :]).flatten()
    assert bool((degree[interior] == expected).all())


@pytest.mark.parametrize("backend", [*FAST, "brute"])
@pytest.mark.parametrize(("radius", "degree"), [(1.0, 0), (2.0, 26), (3.0, 6 + 12 + 8 + 6 + 24 + 24 + 12)])
def test_pairs_at_exactly_the_radius_are_not_neighbours(backend, radius, degree):
    """On a unit lattice (exact in floating point) pairs at 1, 2, 3 lie on the radius: ``< r`` drops them.

    Degrees: integer vectors with |v|^2 < r^2 (|v|^2 = 1, 2, 3, 4, 5, 6, 8: 6, 12, 8, 6, 24, 24, 12; no 7).
    """
    grid = torch.stack(torch.meshgrid(*[torch.arange(9)] * 3, indexing="ij"), dim=-1).reshape(-1, 3)
    pos = grid.to(torch.float64)
    out = radius_graph(pos, radius, backend=backend)
    assert torch.equal(out, oracle(pos, radius))
    centre = (4 * 9 + 4) * 9 + 4
    assert int(torch.bincount(out[1], minlength=len(pos))[centre]) == degree == lattice_degree(radius, 3)


@pytest.mark.parametrize("backend", [*FAST, "brute"])
def test_square_lattice_2d(backend):
    pos = lattice(9, dim=2)
    for factor, expected in ((2.1, 12), (3.1, 28)):
        assert lattice_degree(factor, 2) == expected
        out = radius_graph(pos, factor * L0, backend=backend)
        assert int(torch.bincount(out[1], minlength=81)[4 * 9 + 4]) == expected
        assert torch.equal(out, oracle(pos, factor * L0))


@pytest.mark.parametrize("cells_per_radius", [1, 2, 3, 4])
def test_cell_list_cell_sizes(cells_per_radius):
    gen = torch.Generator().manual_seed(1)
    pos = lattice(7) + 0.2 * L0 * torch.rand(343, 3, generator=gen, dtype=torch.float64)
    r = 2.6 * L0
    recv = torch.arange(0, 343, 3)
    i, j = nb._search_cell_list(pos, r, None, recv, cells_per_radius)
    i, j = nb._sort_pairs(i, j, 343)
    mask = torch.zeros(343, dtype=torch.bool)
    mask[recv] = True
    assert torch.equal(torch.stack([j, i]), oracle(pos, r, receivers=mask))


@pytest.mark.parametrize("backend", FAST)
def test_far_flung_particle(backend):
    # One particle 1e7 m away: the cell list's keys would overflow int64 without compressing gaps.
    pos = torch.cat([lattice(5), torch.tensor([[1.0e7, 1.0e7, 1.0e7], [1.0e7, 1.0e7, 1.0e7 + 0.04]])])
    r = 1.5 * L0
    out = radius_graph(pos, r, backend=backend)
    assert torch.equal(out, radius_graph(pos, r, backend="brute"))
    assert [125, 126] in out.t().tolist()


def test_numba_cell_list_falls_back_to_the_kd_tree_on_a_huge_box(monkeypatch):
    # The compiled cell list keeps a dense cell table; a box with too many cells per particle goes to SciPy.
    from lagfluid.neighbors import pair_kernels

    if "numba" not in available_backends():
        pytest.skip("numba not installed")
    pos = torch.cat([lattice(5), torch.tensor([[3.0, 3.0, 3.0], [3.0, 3.0, 3.04]])])
    r = 1.5 * L0
    assert pair_kernels.cell_search(pos, r, None, torch.arange(len(pos))) is None  # ~80^3 cells, 127 points
    calls = []
    real = nb._search_scipy
    monkeypatch.setattr(nb, "_search_scipy", lambda *a: calls.append(1) or real(*a))
    out = radius_graph(pos, r, backend="numba")
    assert calls and torch.equal(out, radius_graph(pos, r, backend="brute"))


def test_auto_picks_numba_on_the_cpu_and_scipy_without_it(monkeypatch):
    from lagfluid.neighbors import pair_kernels

    if "numba" in available_backends():
        assert nb._resolve_backend("auto", torch.device("cpu")) == "numba"
    monkeypatch.setattr(pair_kernels, "_compiled", lambda: None)
    assert "numba" not in available_backends()
    assert nb._resolve_backend("auto", torch.device("cpu")) == "scipy"
    with pytest.raises(ValueError, match="numba"):
        radius_graph(lattice(3), 1.5 * L0, backend="numba")


# ------------------------------------------------------------------------------------------ options
@pytest.mark.parametrize("backend", [*FAST, "brute"])
def test_batching_is_block_diagonal(backend):
    gen = torch.Generator().manual_seed(2)
    a = torch.rand(150, 3, generator=gen, dtype=torch.float64)
    b = a[:120] + 0.01  # overlaps scene a in space: a shared search would join them everywhere
    r = 0.2
    pos = torch.cat([a, b])
    batch = torch.cat([torch.zeros(150, dtype=torch.long), torch.full((120,), 7)])
    alone = torch.cat([radius_graph(a, r, backend=backend), radius_graph(b, r, backend=backend) + 150], dim=1)
    out = radius_graph(pos, r, batch=batch, backend=backend)
    assert torch.equal(out, alone)
    assert bool((batch[out[0]] == batch[out[1]]).all())
    assert torch.equal(out, oracle(pos, r, batch=batch))
    # Unsorted (interleaved) graph ids give the same graph, permuted.
    perm = torch.randperm(270, generator=gen)
    out_p = radius_graph(pos[perm], r, batch=batch[perm], backend=backend)
    assert torch.equal(out_p, oracle(pos[perm], r, batch=batch[perm]))


@pytest.mark.parametrize("backend", [*FAST, "brute"])
def test_receivers_only_targets(backend):
    gen = torch.Generator().manual_seed(3)
    pos = torch.rand(300, 3, generator=gen, dtype=torch.float64)
    receivers = torch.zeros(300, dtype=torch.bool)
    receivers[:120] = True  # "fluid" first, then boundary, as ParticleState sorts them
    receivers[200] = True
    r = 0.18
    out = radius_graph(pos, r, receivers=receivers, backend=backend)
    full = radius_graph(pos, r, backend=backend)
    assert torch.equal(out, full[:, receivers[full[1]]])
    assert bool(receivers[out[1]].all())
    assert bool((~receivers[out[0]]).any()), "non-receivers must still appear as sources"
    batch = (torch.arange(300) % 2).long()
    out_b = radius_graph(pos, r, receivers=receivers, batch=batch, loop=True, backend=backend)
    assert torch.equal(out_b, oracle(pos, r, batch=batch, receivers=receivers, loop=True))
    every = radius_graph(pos, r, receivers=torch.ones(300, dtype=torch.bool), backend=backend)
    assert torch.equal(every, full)
    none = radius_graph(pos, r, receivers=torch.zeros(300, dtype=torch.bool), backend=backend)
    assert none.shape == (2, 0)


@pytest.mark.parametrize("backend", [*FAST, "brute"])
def test_loop(backend):
    pos = lattice(4) + 0.001
    r = 1.5 * L0
    out = radius_graph(pos, r, loop=True, backend=backend)
    plain = radius_graph(pos, r, backend=backend)
    loops = torch.arange(64).repeat(2, 1)
    assert out.shape[1] == plain.shape[1] + 64
    assert torch.equal(out, oracle(pos, r, loop=True))
    expected = torch.cat([plain, loops], dim=1)
    order = torch.argsort(expected[1] * 64 + expected[0])
    assert torch.equal(out, expected[:, order])


@pytest.mark.parametrize("backend", [*FAST, "brute"])
def test_overflow_raises_never_truncates(backend):
    pos = lattice(7)
    r, degree = 2.1 * L0, 32  # interior degree at 2.1 l0
    with pytest.raises(NeighborOverflowError, match=r"32 neighbours.*max_num_neighbors=31") as err:
        radius_graph(pos, r, max_num_neighbors=31, backend=backend)
    assert err.value.count == 32 and err.value.cap == 31 and isinstance(err.value, ValueError)
    assert f"particle {err.value.node}" in str(err.value)
    assert torch.equal(radius_graph(pos, r, max_num_neighbors=degree, backend=backend), oracle(pos, r))
    with pytest.raises(NeighborOverflowError, match="33 neighbours"):
        radius_graph(pos, r, max_num_neighbors=degree, loop=True, backend=backend)


TC_DEFAULT_CAP = 32  # torch_cluster.radius's silent default cap


def fake_torch_cluster(calls: list) -> SimpleNamespace:
    """Stand-in with torch_cluster.radius's contract: sorted batches, silent truncation at the cap."""

    def radius(
        x, y, r, batch_x=None, batch_y=None, max_num_neighbors=TC_DEFAULT_CAP, num_workers=1, batch_size=None
    ):
        if batch_x is not None:
            assert bool((batch_x[1:] >= batch_x[:-1]).all()) and bool((batch_y[1:] >= batch_y[:-1]).all())
        mask = torch.cdist(y.double(), x.double()) <= r
        if batch_x is not None:
            mask &= batch_y[:, None] == batch_x[None, :]
        mask &= torch.cumsum(mask.long(), dim=1) <= max_num_neighbors  # drops the rest, silently
        calls.append(max_num_neighbors)
        row, col = torch.nonzero(mask, as_tuple=True)
        return torch.stack([row, col])

    return SimpleNamespace(radius=radius)


def test_torch_cluster_adapter_with_fake(monkeypatch):
    calls: list = []
    monkeypatch.setattr(nb, "_import_torch_cluster", lambda: fake_torch_cluster(calls))
    assert "torch_cluster" in available_backends()
    gen = torch.Generator().manual_seed(4)
    pos = lattice(7) + 0.1 * L0 * torch.rand(343, 3, generator=gen, dtype=torch.float64)
    r = 3.1 * L0
    batch = torch.randint(0, 3, (343,), generator=gen)  # unsorted
    receivers = torch.rand(343, generator=gen) < 0.6
    ref = oracle(pos, r, batch=batch, receivers=receivers)
    assert torch.equal(radius_graph(pos, r, batch=batch, receivers=receivers, backend="torch_cluster"), ref)
    # A cap far below the degree: saturated centres are searched again exactly, nothing is lost.
    monkeypatch.setattr(nb, "_TORCH_CLUSTER_DEFAULT_CAP", 10)
    assert torch.equal(radius_graph(pos, r, backend="torch_cluster"), oracle(pos, r))
    assert calls[-1] == 10
    top = int(torch.bincount(oracle(pos, r)[1]).max())
    assert torch.equal(radius_graph(pos, r, max_num_neighbors=top, backend="torch_cluster"), oracle(pos, r))
    assert calls[-1] == top + 2
    with pytest.raises(NeighborOverflowError, match=f"{top} neighbours"):
        radius_graph(pos, r, max_num_neighbors=top - 1, backend="torch_cluster")


def test_torch_cluster_real():
    pytest.importorskip("torch_cluster")
    pos = lattice(8, dtype=torch.float32)
    batch = (torch.arange(512) % 2).long()
    for factor in (0.92, 2.1, 3.1):
        r = factor * L0
        out = radius_graph(pos, r, batch=batch, backend="torch_cluster")
        assert torch.equal(out, radius_graph(pos, r, batch=batch, backend="brute"))


@CUDA
@pytest.mark.parametrize("backend", ["auto", "cell_list", "brute", "scipy"])
def test_cuda_matches_cpu(backend):
    gen = torch.Generator().manual_seed(5)
    pos = lattice(8, dtype=torch.float32) + 0.1 * L0 * torch.rand(512, 3, generator=gen)
    receivers = torch.arange(512) < 300
    for factor in (0.92, 2.1, 3.1):
        ref = radius_graph(pos, factor * L0, receivers=receivers, backend="brute")
        out = radius_graph(pos.cuda(), factor * L0, receivers=receivers.cuda(), backend=backend)
        assert out.device.type == "cuda"
        assert torch.equal(out.cpu(), ref)


# ------------------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [
        ({"pos": torch.zeros(4, 3, dtype=torch.long)}, "torch.int64"),
        ({"pos": torch.zeros(4, 4)}, "(4, 4)"),
        ({"pos": torch.zeros(4)}, "(4,)"),
        ({"pos": [[0.0, 0.0, 0.0]]}, "list"),
        ({"pos": torch.tensor([[0.0, 0, 0], [1, float("nan"), 0]])}, "particle 1"),
        ({"pos": torch.tensor([[0.0, 0, 0], [1, 0, float("inf")]])}, "inf"),
        ({"r": 0.0}, "0.0"),
        ({"r": -0.1}, "-0.1"),
        ({"r": float("nan")}, "nan"),
        ({"r": float("inf")}, "inf"),
        ({"r": "big"}, "'big'"),
        ({"backend": "kdtree"}, "'kdtree'"),
        ({"batch": torch.zeros(3, dtype=torch.long)}, "length N=4"),
        ({"batch": torch.zeros(4)}, "torch.float32"),
        ({"receivers": torch.ones(4, dtype=torch.long)}, "torch.int64"),
        ({"receivers": torch.ones(5, dtype=torch.bool)}, "(5,)"),
        ({"max_num_neighbors": -1}, "-1"),
    ],
)
def test_bad_input_raises_value_error(kwargs, needle):
    args = {"pos": torch.rand(4, 3), "r": 0.1, **kwargs}
    with pytest.raises(ValueError) as err:
        radius_graph(args.pop("pos"), args.pop("r"), **args)
    assert needle in str(err.value)


def test_unknown_backend_lists_available():
    with pytest.raises(ValueError, match=r"scipy.*cell_list.*brute"):
        radius_graph(torch.rand(4, 3), 0.1, backend="kdtree")
    if nb._import_torch_cluster() is None:
        with pytest.raises(ValueError, match="torch_cluster is not installed"):
            radius_graph(torch.rand(4, 3), 0.1, backend="torch_cluster")


# ------------------------------------------------------------------------------------------ geometry
def test_edge_vectors_and_restrict_radius():
    gen = torch.Generator().manual_seed(6)
    pos = lattice(6) + 0.2 * L0 * torch.rand(216, 3, generator=gen, dtype=torch.float64)
    big = radius_graph(pos, 3.1 * L0)
    rel, dist = edge_vectors(pos, big)
    assert torch.allclose(rel, pos[big[0]] - pos[big[1]], rtol=0, atol=0)
    assert torch.allclose(dist, rel.norm(dim=1), rtol=1e-15, atol=0)
    for factor in (3.1, 2.1, 1.2, 0.92):
        small, mask = restrict_radius(big, dist, factor * L0)
        assert mask.shape == dist.shape and mask.dtype == torch.bool
        for backend in FAST:
            assert torch.equal(small, radius_graph(pos, factor * L0, backend=backend))
    with pytest.raises(ValueError, match="-1"):
        restrict_radius(big, dist, -1)


def test_edge_vectors_gradient_with_self_loops():
    pos = (lattice(3) + 0.01).requires_grad_()
    edges = radius_graph(pos, 1.5 * L0, loop=True)
    _, dist = edge_vectors(pos, edges)
    assert bool((dist[edges[0] == edges[1]] == 0).all())
    (grad,) = torch.autograd.grad((dist**2).sum() + dist.sum(), pos)
    assert bool(torch.isfinite(grad).all())
    _, plain = edge_vectors(pos.detach(), edges)
    assert torch.equal(dist.detach(), plain)


# ------------------------------------------------------------------------------------------ adjacency
def loop_sum(edge_index, weight, x, n_target):
    out = torch.zeros((n_target, *x.shape[1:]), dtype=x.dtype)
    for e in range(edge_index.shape[1]):
        j, i = int(edge_index[0, e]), int(edge_index[1, e])
        out[i] += weight[e] * x[j]
    return out


def test_kernel_adjacency_matmul_equals_loop():
    gen = torch.Generator().manual_seed(7)
    pos = torch.rand(60, 3, generator=gen, dtype=torch.float64)
    edges = radius_graph(pos, 0.35)
    _, dist = edge_vectors(pos, edges)
    w = (0.35 / dist - 1.0).clamp(min=0)  # the MPS kernel
    x = torch.rand(60, 4, generator=gen, dtype=torch.float64)
    a = kernel_adjacency(edges, w, 60)
    assert a.layout == torch.sparse_csr and a.shape == (60, 60)
    assert torch.allclose(a @ x, loop_sum(edges, w, x, 60), rtol=1e-12, atol=1e-12)
    assert torch.allclose(a @ x[:, 0], loop_sum(edges, w, x[:, 0], 60), rtol=1e-12, atol=1e-12)
    dense = torch.zeros(60, 60, dtype=torch.float64)
    dense[edges[1], edges[0]] = w
    assert torch.equal(a.to_dense(), dense)
    # Unsorted edges are sorted (weights follow); a rectangular (targets, sources) matrix.
    perm = torch.randperm(edges.shape[1], generator=gen)
    assert torch.allclose(kernel_adjacency(edges[:, perm], w[perm], 60) @ x, a @ x, rtol=1e-12, atol=0)
    receivers = torch.arange(60) < 20
    sub = radius_graph(pos, 0.35, receivers=receivers)
    _, d_sub = edge_vectors(pos, sub)
    w_sub = (0.35 / d_sub - 1.0).clamp(min=0)
    rect = kernel_adjacency(sub, w_sub, (20, 60))
    assert rect.shape == (20, 60)
    assert torch.allclose(rect @ x, loop_sum(sub, w_sub, x, 20), rtol=1e-12, atol=1e-12)
    assert kernel_adjacency(sub[:, :0], w_sub[:0], 5).to_dense().abs().sum() == 0


def test_kernel_adjacency_compiled_row_pointer_equals_the_torch_build(monkeypatch):
    # Sorted pairs take the one-pass compiled check; the CSR it builds is the torch body's, empty rows (the
    # last ones too) included, and pairs out of order, repeated or out of range go to the torch body.
    from lagfluid.neighbors import csr, pair_kernels

    gen = torch.Generator().manual_seed(3)
    pos = torch.rand(80, 3, generator=gen)
    edges = radius_graph(pos, 0.3, receivers=torch.arange(80) < 70)  # rows 70..79 empty
    w = torch.rand(edges.shape[1], generator=gen)
    fast = kernel_adjacency(edges, w, 80)
    with monkeypatch.context() as m:
        m.setattr(pair_kernels, "applies", lambda *a: False)
        slow = kernel_adjacency(edges, w, 80)
    for part in ("crow_indices", "col_indices", "values"):
        assert torch.equal(getattr(fast, part)(), getattr(slow, part)()), part
    if "numba" not in available_backends():
        return
    assert pair_kernels.backend_for("kernel_adjacency", edges[1], edges[0]) is csr._adjacency_compiled
    handed = []
    torch_body = csr._adjacency_torch
    monkeypatch.setattr(csr, "_adjacency_torch", lambda *a: handed.append(a[3:]) or torch_body(*a))
    csr._adjacency_compiled(edges[1], edges[0], w, 80, 80)
    assert handed == []  # sorted, in range: the compiled pass
    swapped = edges.clone()
    swapped[0, [0, 1]] = swapped[0, [1, 0]]  # two sources of one target out of order
    csr._adjacency_compiled(swapped[1], swapped[0], w, 80, 80)
    assert handed == [(80, 80)]
    assert int(edges[0].max()) == 79
    with pytest.raises(ValueError, match=r"source index out of range \[0, 79\)"):
        csr._adjacency_compiled(edges[1], edges[0], w, 80, 79)
    assert handed == [(80, 80), (80, 79)]


def test_kernel_adjacency_rejects_bad_edges():
    edges = torch.tensor([[0, 1, 1], [1, 0, 0]])
    with pytest.raises(ValueError, match="more than once"):
        kernel_adjacency(edges, torch.ones(3), 2)
    with pytest.raises(ValueError, match="out of range"):
        kernel_adjacency(torch.tensor([[0], [5]]), torch.ones(1), 3)
    with pytest.raises(ValueError, match=r"weight must have shape \(1,\), got \(2,\)"):
        kernel_adjacency(torch.tensor([[0], [1]]), torch.ones(2), 2)


def test_kernel_adjacency_gradients():
    gen = torch.Generator().manual_seed(8)
    pos = torch.rand(25, 3, generator=gen, dtype=torch.float64)
    edges = radius_graph(pos, 0.4)
    w = torch.rand(edges.shape[1], generator=gen, dtype=torch.float64, requires_grad=True)
    x = torch.rand(25, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    # Fast mode: a few random directional derivatives instead of one column per input entry.
    assert torch.autograd.gradcheck(lambda w, x: kernel_adjacency(edges, w, 25) @ x, (w, x), fast_mode=True)
    # Weights computed from positions: gradients reach pos through the CSR values.
    p = pos.clone().requires_grad_()
    _, dist = edge_vectors(p, edges)
    out = kernel_adjacency(edges, (0.4 / dist - 1.0), 25) @ x
    ref = loop_sum(edges, 0.4 / edge_vectors(p, edges)[1] - 1.0, x, 25)
    g1 = torch.autograd.grad(out.square().sum(), (p, x))
    g2 = torch.autograd.grad(ref.square().sum(), (p, x))
    for a, b in zip(g1, g2, strict=True):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("library", ["vesin", "warp"])
def test_the_benchmarks_optional_libraries_find_our_pairs(library):
    """vesin and warp-lang, timed beside our search by ``benchmarks.neighbors --verlet``, find the same pairs.

    A jittered block (no pair within rounding of r, where float formulas may differ); skipped without them.
    """
    pytest.importorskip(library)
    from benchmarks.neighbors import fluid_block, vesin_pairs, warp_pairs

    pos = fluid_block(600, jitter=0.2, seed=3)
    r = 2.1 * L0
    got = (vesin_pairs if library == "vesin" else warp_pairs)(pos, r)
    want = radius_graph(pos, r)
    assert want.shape[1] > 20 * 600
    assert torch.equal(got, want)


def test_the_verlet_benchmark_checks_every_way_against_the_previous_search():
    """``benchmarks.neighbors --verlet``'s rows on a small dam: every way finds the previous search's."""
    pytest.importorskip("numba")
    from benchmarks.neighbors import verlet_rows
    from lagfluid.neighbors.verlet import VerletNeighborList
    from lagfluid.scenes import build_scene

    state = build_scene("dam", fluid_size=[6, 6, 8], tank_size=[15, 8])
    nl = VerletNeighborList(2.1 * L0, 0.63 * L0)
    rows = verlet_rows("small", "rest", state, nl, "fgn", 1, {"copy_bytes_per_s": 1e10})
    by_way = {r["way"]: r for r in rows}
    assert all(r["same_pairs"] for r in rows)
    previous, present = by_way["previous search"], by_way["present search"]
    assert previous["pairs"] == present["pairs"] == by_way["present, whole update"]["pairs"] > 0
    assert present["scanned"] < previous["scanned"]  # the walls' rows are no longer searched
    assert present["floor_write_ms"] == round(1e3 * 16 * present["pairs"] / 1e10, 2)


def test_the_benchmarks_kept_flow_state_comes_back_equal_and_unpickles_nothing(tmp_path):
    """``benchmarks.neighbors.flow_state`` keeps a rollout's state as tensors and plain values (loaded with
    ``weights_only=True``) and gives the same state back."""
    import torch

    from benchmarks.neighbors import flow_state

    made = flow_state("dam_small", 0.004, "mps", tmp_path, 1)
    (kept,) = tmp_path.glob("*.pt")
    assert set(torch.load(kept, weights_only=True)) == {"tensors", "params", "time", "step"}
    back = flow_state("dam_small", 0.004, "mps", tmp_path, 1)
    assert back.step == made.step == 2 and back.params == made.params and back.time == made.time
    for name in ("pos", "vel", "ptype", "pressure", "bounds"):
        assert torch.equal(getattr(back, name), getattr(made, name)), name


# ------------------------------------------------------------------------- one point set into another
def stacked_between(sources, targets, r, backend="brute", source_batch=None, target_batch=None):
    """The pairs of the stacked search (sources first, targets receiving), target-target pairs dropped."""
    n_s = sources.shape[0]
    both = torch.cat([sources, targets])
    receivers = torch.zeros(both.shape[0], dtype=torch.bool)
    receivers[n_s:] = True
    batch = None if source_batch is None else torch.cat([source_batch, target_batch])
    edges = radius_graph(both, r, batch=batch, receivers=receivers, backend=backend)
    edges = edges[:, edges[0] < n_s]
    return torch.stack([edges[0], edges[1] - n_s])


def test_pairs_between_two_sets_by_hand():
    # sources on the x axis at 0 and 1 l0; targets at 0.5 l0 above the first, 1.5 l0 and 3 l0 along x
    sources = torch.tensor([[0.0, 0.0, 0.0], [L0, 0.0, 0.0]])
    targets = torch.tensor([[0.0, 0.0, 0.5 * L0], [1.5 * L0, 0.0, 0.0], [3 * L0, 0.0, 0.0]])
    out = nb.radius_graph_between(sources, targets, 1.2 * L0)
    # target 0: |s0 - t0| = 0.5 l0, |s1 - t0| = sqrt(1.25) l0 = 1.118 l0: both; target 1: 1.5 l0 and 0.5 l0:
    # s1 only; target 2: 3 and 2 l0: none. Sources are never paired with each other, targets neither.
    assert out.tolist() == [[0, 1, 1], [0, 0, 1]]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("dim", [3, 2])
def test_pairs_between_two_sets_equal_the_stacked_search(dtype, dim):
    gen = torch.Generator().manual_seed(7)
    lat = lattice(7, dim, dtype)  # pairs at exactly 1 and sqrt(2) l0: the cut decides them the same way
    sources = torch.cat([lat, (torch.rand(300, dim, generator=gen) * 0.4 - 0.05).to(dtype)])
    # targets: a shifted lattice (exact distances again), random points, and points off the sources' box
    targets = torch.cat([lat[::3] + L0, (torch.rand(200, dim, generator=gen) * 0.5 - 0.1).to(dtype)])
    targets = torch.cat([targets, torch.full((2, dim), 5.0, dtype=dtype)])
    for factor in (1.0, 2.1, math.sqrt(2)):
        r = factor * L0
        want = stacked_between(sources, targets, r)
        got = nb.radius_graph_between(sources, targets, r)
        assert torch.equal(got, want), f"r = {factor} l0"
        j, i = got
        # sorted by target, then source
        assert bool(((i[1:] > i[:-1]) | ((i[1:] == i[:-1]) & (j[1:] > j[:-1]))).all())


def test_pairs_between_two_sets_in_batches_and_empty_sets():
    gen = torch.Generator().manual_seed(3)
    sources, targets = torch.rand(80, 3, generator=gen) * 0.3, torch.rand(60, 3, generator=gen) * 0.3
    sb, tb = torch.arange(80) % 2, torch.arange(60) % 2
    got = nb.radius_graph_between(sources, targets, 2 * L0, source_batch=sb, target_batch=tb)
    assert torch.equal(got, stacked_between(sources, targets, 2 * L0, "brute", sb, tb))
    assert bool((sb[got[0]] == tb[got[1]]).all()) and got.shape[1] > 0
    assert nb.radius_graph_between(sources[:0], targets, L0).shape == (2, 0)
    assert nb.radius_graph_between(sources, targets[:0], L0).shape == (2, 0)


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [
        ({"targets": torch.zeros(3, 2)}, "must be (S, D) and (T, D)"),
        ({"targets": torch.zeros(3, 3, dtype=torch.float64)}, "must share a dtype"),
        ({"source_batch": torch.zeros(4, dtype=torch.long)}, "both source_batch and target_batch"),
        ({"targets": torch.tensor([[0.0, float("nan"), 0.0]])}, "not finite"),
        ({"r": -1.0}, "positive finite"),
    ],
)
def test_pairs_between_two_sets_refuse_bad_input(kwargs, needle):
    args = {"sources": torch.zeros(4, 3), "targets": torch.zeros(3, 3), "r": L0, **kwargs}
    with pytest.raises(ValueError, match=re.escape(needle)):
        nb.radius_graph_between(args.pop("sources"), args.pop("targets"), args.pop("r"), **args)
