"""Backends are chosen in one place, per kernel and tensors: ``pair_kernels.backend_for``.

Each kernel with a compiled (Numba) and a torch body is registered once; the dispatch gives the compiled body
for CPU float32/float64 tensors that need no gradient where Numba is installed, the torch body otherwise.
Each kernel's two bodies give the same numbers, checked here on cases small enough to work out by hand.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import baselines.cconv.conv as cconv_conv
from lagfluid import neighbors
from lagfluid.neighbors import pair_kernels
from lagfluid.neighbors.verlet import VerletNeighborList
from lagfluid.physics import operators as ops
from lagfluid.physics.ppe import system as ppe_system
from lagfluid.scenes import build_scene
from lagfluid.state import ParticleType

NUMBA = pair_kernels.available()
needs_numba = pytest.mark.skipif(not NUMBA, reason="numba not installed")


def _fake(device: str, dtype: torch.dtype = torch.float32, requires_grad: bool = False) -> SimpleNamespace:
    """What the dispatch reads of a tensor, on a device this machine may not have (a CUDA tensor, say)."""
    return SimpleNamespace(device=torch.device(device), dtype=dtype, requires_grad=requires_grad)


# ---------------------------------------------------------------------------------------------- dispatch


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cpu_float32_and_float64_take_the_compiled_body_where_numba_is(dtype):
    pos = torch.zeros(4, 3, dtype=dtype)
    edges = torch.zeros(2, 5, dtype=torch.long)
    kernel = pair_kernels.KERNELS["pairs_within"]
    assert pair_kernels.backend_for("pairs_within", pos, edges) is (
        kernel.compiled if NUMBA else kernel.torch
    )
    assert pair_kernels.backend_for("laplacian", pos, pos[:, 0]) is (
        ops._laplacian_compiled if NUMBA else ops._laplacian_torch
    )
    assert pair_kernels.backend_for("ppe_assembly", pos[:, 0]) is (
        ppe_system._assemble_compiled if NUMBA else ppe_system._assemble_torch
    )


@pytest.mark.parametrize(
    "tensor",
    [
        _fake("cuda"),
        _fake("cuda:1", torch.float64),
        torch.zeros(3, device="meta"),
        torch.zeros(3, dtype=torch.float16),
        torch.zeros(3, dtype=torch.bfloat16),
        torch.zeros(3, requires_grad=True),
    ],
    ids=["cuda-float32", "cuda-float64", "meta", "float16", "bfloat16", "requires-grad"],
)
def test_other_devices_dtypes_and_autograd_take_the_torch_body(tensor):
    for name, kernel in pair_kernels.KERNELS.items():
        assert pair_kernels.backend_for(name, tensor) is kernel.torch, name
    # one such tensor among CPU ones is enough
    assert pair_kernels.backend_for("mps_kernel", torch.zeros(3), tensor) is ops._kernel_torch


@needs_numba
def test_no_grad_integer_tensors_and_the_callers_own_switch():
    with torch.no_grad():  # positions that require grad, outside autograd: the compiled body
        assert (
            pair_kernels.backend_for("mps_kernel", torch.zeros(3, requires_grad=True)) is ops._kernel_compiled
        )
    edges = torch.zeros(2, 3, dtype=torch.int32)
    assert pair_kernels.backend_for("induced_edges", edges) is pair_kernels.induced_edges
    assert pair_kernels.backend_for("mps_kernel", torch.zeros(3), compiled=False) is ops._kernel_torch


def test_without_numba_every_kernel_takes_its_torch_body(monkeypatch):
    monkeypatch.setattr(pair_kernels, "_compiled", lambda: None)  # as when numba does not import
    for name, kernel in pair_kernels.KERNELS.items():
        assert pair_kernels.backend_for(name, torch.zeros(3)) is kernel.torch, name


def test_a_kernel_whose_numba_module_does_not_load_takes_its_torch_body(monkeypatch):
    kernel = pair_kernels.register(
        "test_missing_module", compiled=np.sum, torch=_torch_sum, module="lagfluid.no_such_module"
    )
    try:
        assert pair_kernels.backend_for("test_missing_module", torch.zeros(3)) is kernel.torch
    finally:
        del pair_kernels.KERNELS["test_missing_module"]


def _torch_sum(x):
    return x.sum()


def test_a_kernel_name_is_one_modules():
    with pytest.raises(ValueError, match=r"'laplacian' is already registered by lagfluid\.physics\."):
        pair_kernels.register("laplacian", compiled=np.sum, torch=_torch_sum)
    with pytest.raises(KeyError):
        pair_kernels.backend_for("no_such_kernel", torch.zeros(3))


# ------------------------------------------------------------------------ both bodies, by hand

CASES = {}


def case(name):
    def add(fn):
        CASES[name] = fn
        return fn

    return add


def both(name, *args, **kwargs):
    """``(compiled body's result, torch body's result)`` of kernel ``name`` on the same arguments."""
    kernel = pair_kernels.KERNELS[name]
    return kernel.compiled(*args, **kwargs), kernel.torch(*args, **kwargs)


def assert_same(got, want):
    """Equal values, dtypes and shapes, tensor by tensor (nested tuples)."""
    if isinstance(got, tuple | list):
        assert len(got) == len(want)
        for g, w in zip(got, want, strict=True):
            assert_same(g, w)
        return
    got, want = torch.as_tensor(got), torch.as_tensor(want)
    assert got.dtype == want.dtype and got.shape == want.shape, (got, want)
    assert torch.equal(got, want), (got, want)


@case("induced_edges")
def _induced_edges():
    edge_index = torch.tensor([[0, 2, 3, 1], [1, 0, 2, 3]])
    keep = torch.tensor([True, True, False, True])
    local = torch.tensor([0, 1, -1, 2])
    fast, slow = both("induced_edges", edge_index, keep, local)
    assert_same(fast, slow)
    assert_same(fast, (torch.tensor([[0, 1], [1, 2]]), torch.tensor([0, 3])))  # 0->1 and 1->3, renumbered


@case("select_below")
def _select_below():
    edge_index = torch.tensor([[1, 0, 2, 2], [0, 1, 1, 0]])
    dist = torch.tensor([0.5, 0.25, 0.75, 0.625])
    rel = torch.stack([dist, -dist, 2 * dist], dim=1)
    fast, slow = both("select_below", edge_index, rel, dist, 0.625)  # a pair at the radius is out
    assert_same(fast, slow)
    assert_same(fast, (edge_index[:, :2], rel[:2], dist[:2]))


def _line(dtype=torch.float32):
    """Four particles on the x axis at 0, 0.25, 0.75 and 1 (exact in binary)."""
    return torch.tensor([[0.0, 0, 0], [0.25, 0, 0], [0.75, 0, 0], [1.0, 0, 0]], dtype=dtype)


@case("pairs_within")
def _pairs_within():
    for dtype in (torch.float32, torch.float64):
        pos = _line(dtype)
        into_0 = torch.tensor([[1, 2, 3], [0, 0, 0]])  # at 0.25, 0.75, 1
        into_2 = torch.tensor([[1, 3], [2, 2]])  # at 0.5, 0.25
        mask = torch.tensor([True, True, False, True])  # particle 2 is no target
        fast, slow = both("pairs_within", pos, [into_0, into_2], 0.75, [None, mask])
        assert_same(fast, slow)
        edges, rel, dist = fast
        assert edges.tolist() == [[1], [0]]  # 0.75 is not within 0.75; particle 2 masked out
        assert rel.tolist() == [[0.25, 0.0, 0.0]] and dist.tolist() == [0.25]
        fast, slow = both("pairs_within", pos, [into_2], 0.75)
        assert_same(fast, slow)
        assert fast[0].tolist() == [[1, 3], [2, 2]] and fast[2].tolist() == [0.5, 0.25]


def _kernel_dist(dtype=torch.float32):
    """MPS weights at re = 0.5 worked out: w(0.25) = 1, w(0.125) = 3, 0 at r = re, r = 0 and beyond re."""
    return torch.tensor([0.25, 0.125, 0.5, 0.0, 1.0], dtype=dtype), [1.0, 3.0, 0.0, 0.0, 0.0]


@case("mps_kernel")
def _mps_kernel():
    for dtype in (torch.float32, torch.float64):
        dist, want = _kernel_dist(dtype)
        tiled = dist.repeat(1000)  # more pairs than the compiled body hands to the torch one
        fast, slow = both("mps_kernel", tiled, 0.5)
        assert_same(fast, slow)
        assert fast.tolist() == want * 1000


@case("number_density")
def _number_density():
    edge_index = torch.tensor([[1, 2, 0], [0, 0, 1]])  # sorted by target
    dist = torch.tensor([0.25, 0.125, 0.25])
    fast, slow = both("number_density", edge_index, dist, 0.5, 3, 3)
    assert_same(fast, slow)
    assert fast.tolist() == [1.0 + 3.0, 1.0, 0.0]


@case("min_pressure_gradient")
def _min_pressure_gradient():
    pos = _line()[:2]  # 0.25 apart: w = 1 at re = 0.5, rel / r^2 = +-4 along x
    edge_index = torch.tensor([[1, 0], [0, 1]])
    pressure = torch.tensor([0.0, 1.0])
    # d / n0 = 1: grad p_0 = (1 - min(0, 1)) * 4 * 1; grad p_1 = (0 - min(1, 0)) * (-4) = 0
    fast, slow = both("min_pressure_gradient", pos, edge_index, pressure, 0.5, 1.0, 1, True, 2, None, None)
    assert_same(fast, slow)
    assert fast.tolist() == [[4.0, 0.0, 0.0], [0.0, 0.0, 0.0]]


@case("laplacian")
def _laplacian():
    edge_index = torch.tensor([[1, 0], [0, 1]])
    dist = torch.tensor([0.25, 0.25])  # w = 1
    values = torch.tensor([0.0, 2.0])
    # 2 d / (lambda n0) = 2 * 1 / (2 * 1) = 1: lap_0 = 1 * (2 - 0), lap_1 = 1 * (0 - 2)
    fast, slow = both("laplacian", edge_index, dist, values, 0.5, 1.0, 2.0, 1, 2)
    assert_same(fast, slow)
    assert fast.tolist() == [2.0, -2.0]


@case("kernel_adjacency")
def _kernel_adjacency():
    i, j = torch.tensor([0, 0, 1]), torch.tensor([1, 2, 0])
    w = torch.tensor([1.0, 2.0, 3.0])
    fast, slow = both("kernel_adjacency", i, j, w, 3, 3)
    for part in ("crow_indices", "col_indices", "values"):
        assert_same(getattr(fast, part)(), getattr(slow, part)())
    assert fast.to_dense().tolist() == [[0.0, 1.0, 2.0], [3.0, 0.0, 0.0], [0.0, 0.0, 0.0]]


@case("ppe_assembly")
def _ppe_assembly():
    # particles 0 and 1 solved, 2 on the free surface; every pair once each way, sorted by target
    edge_index = torch.tensor([[1, 2, 0, 2, 0, 1], [0, 0, 1, 1, 2, 2]])
    coef = torch.ones(6)
    solve = torch.tensor([True, True, False])
    dirichlet = torch.tensor([False, False, True])
    args = (edge_index, coef, solve, dirichlet, 1.0, 2.0, "auto", False)
    fast, slow = both("ppe_assembly", *args)
    for part in ("crow_indices", "col_indices", "values"):
        assert_same(getattr(fast.matrix, part)(), getattr(slow.matrix, part)())
    assert_same(fast.isolated, slow.isolated)
    # A_ii = (1/rho) (c_ij + c_i2) = 2, A_01 = A_10 = -1; both rows see the free surface
    assert fast.matrix.to_dense().tolist() == [[2.0, -1.0], [-1.0, 2.0]]
    assert fast.isolated.tolist() == [False, False] and fast.n_isolated_components == 0


@case("component_labels")
def _component_labels():
    # rows 0-1 and 2-3 joined: two components
    crow, col = np.array([0, 1, 2, 3, 4]), np.array([1, 0, 3, 2])
    fast, slow = both("component_labels", crow, col, 4)
    for labels in (fast, slow):
        assert labels[0] == labels[1] != labels[2] == labels[3]


@case("cconv_block_entries")
def _cconv_block_entries():
    i, j = torch.tensor([0, 1]), torch.tensor([1, 0])
    cell = torch.arange(16).view(2, 8)  # pair 0: cells 0..7, pair 1: cells 8..15
    w = torch.arange(16, dtype=torch.float32).view(2, 8) / 16
    counts = torch.tensor([1, 1])
    fast, slow = both("cconv_block_entries", i, j, cell, w, counts, 4, 12, 2)
    assert_same(fast, slow)
    crow, cols, vals = fast
    # the block [4, 12): pair 0's cells 4..7 (input 1: columns 8 + 0..3), pair 1's 8..11 (input 0: 4..7)
    assert crow.tolist() == [0, 4, 8]
    assert cols.tolist() == [8, 9, 10, 11, 4, 5, 6, 7]
    assert vals.tolist() == (torch.cat([w[0, 4:8], w[1, 0:4]])).tolist()
    assert cconv_conv._NUMBA == pair_kernels.KERNELS["cconv_block_entries"].module


def _small_tank():
    """A 3 x 3 x 3 fluid block in a tank, moved off its lattice a little."""
    state = build_scene("dam", fluid_size=[3, 3, 3], tank_size=[7, 7])
    gen = torch.Generator().manual_seed(5)
    pos = state.pos.clone()
    pos[: state.n_fluid] += 0.004 * torch.rand(state.n_fluid, 3, generator=gen, dtype=pos.dtype)
    return pos, state.ptype, state.params.l0


def _built(pos, ptype, l0, wall_hops=1):
    neighbor_list = VerletNeighborList(3.1 * l0, 0.3 * l0, wall_hops=wall_hops)
    neighbor_list.update(pos, ptype)
    return neighbor_list


@case("verlet_search")
def _verlet_search():
    pos, ptype, l0 = _small_tank()
    nl = _built(pos, ptype, l0)
    fluid, walls = ptype == ParticleType.FLUID, ptype == ParticleType.WALL
    n_fluid = int(fluid.sum())
    fast, slow = both("verlet_search", nl, pos, fluid, walls, n_fluid)
    assert_same(fast[0], slow[0]) and fast[1] == slow[1]
    # the candidates into the fluid: every pair within cutoff + skin, as the brute-force search finds them
    into_fluid = neighbors.radius_graph(pos, nl.list_radius, receivers=fluid, backend="brute")
    assert_same(fast[0][:, : fast[1]], into_fluid)


@case("verlet_graph")
def _verlet_graph():
    pos, ptype, l0 = _small_tank()
    nl = _built(pos, ptype, l0, wall_hops=2)
    for radius in (3.1 * l0, 2.1 * l0):
        for with_walls in (False, True):
            fast, slow = both("verlet_graph", nl, pos, ptype, radius, with_walls)
            assert_same((fast.edge_index, fast.rel, fast.dist), (slow.edge_index, slow.rel, slow.dist))
        fluid = ptype == ParticleType.FLUID
        want = neighbors.radius_graph(pos, radius, receivers=fluid, backend="brute")
        assert_same(nl._graph_compiled(pos, ptype, radius, False).edge_index, want)


@case("verlet_active_walls")
def _verlet_active_walls():
    pos, ptype, l0 = _small_tank()
    nl = _built(pos, ptype, l0, wall_hops=1)
    fast, slow = both("verlet_active_walls", nl, pos)
    assert_same(fast, slow)
    # one hop: the walls with a fluid particle closer than the cutoff
    fluid, walls = ptype == ParticleType.FLUID, ptype == ParticleType.WALL
    sources = neighbors.radius_graph(pos, nl.cutoff, receivers=fluid, backend="brute")[0]
    want = torch.zeros_like(walls)
    want[sources[walls[sources]]] = True
    assert_same(fast, want)
    assert 0 < int(fast.sum()) < int(walls.sum())
    assert math.isfinite(nl.closest_static_pair())


# after every case above: parametrize reads CASES when the module is imported
def test_every_kernel_has_a_case_here():
    assert set(pair_kernels.KERNELS) == set(CASES)


@needs_numba
@pytest.mark.parametrize("name", sorted(CASES))
def test_both_bodies_give_the_worked_out_numbers(name):
    CASES[name]()
