"""The compiled pair filters equal the torch path bit for bit; the Verlet list answers the same either way."""

import subprocess
import sys

import pytest
import torch

from lagfluid.neighbors import edge_vectors, pair_kernels
from lagfluid.neighbors.verlet import VerletNeighborList, _WallRows
from lagfluid.scenes import build_scene

pytestmark = pytest.mark.skipif(not pair_kernels.available(), reason="numba not installed")


def torch_filter(pos, edge_index, radius, target_mask=None):
    rel, dist = edge_vectors(pos, edge_index)
    keep = dist < radius
    if target_mask is not None:
        keep &= target_mask[edge_index[1]]
    return edge_index[:, keep], rel[keep], dist[keep]


def assert_identical(got, want):
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype and g.shape == w.shape
        assert torch.equal(g, w)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("dim", [3, 2])
def test_pairs_within_equals_edge_vectors_then_cut(dtype, dim):
    gen = torch.Generator().manual_seed(0)
    pos = torch.rand(3000, dim, generator=gen, dtype=dtype)
    edges = torch.randint(0, 3000, (2, 200_000), generator=gen)
    edges = edges[:, torch.argsort(edges[1], stable=True)]
    got = pair_kernels.pairs_within(pos, [edges], 0.2)
    assert_identical(got, torch_filter(pos, edges, 0.2))
    assert bool((got[0][1][1:] >= got[0][1][:-1]).all())  # input order kept: still sorted by target
    assert 0 < got[0].shape[1] < edges.shape[1]


def test_pairs_within_concatenates_lists_and_applies_target_masks():
    gen = torch.Generator().manual_seed(1)
    pos = torch.rand(500, 3, generator=gen)
    a, b = torch.randint(0, 500, (2, 20_000), generator=gen), torch.randint(0, 500, (2, 9_000), generator=gen)
    mask = torch.rand(500, generator=gen) < 0.3
    got = pair_kernels.pairs_within(pos, [a, b], 0.3, [None, mask])
    want_a, want_b = torch_filter(pos, a, 0.3), torch_filter(pos, b, 0.3, mask)
    want = (
        torch.cat([want_a[0], want_b[0]], dim=1),
        torch.cat([want_a[1], want_b[1]]),
        torch.cat([want_a[2], want_b[2]]),
    )
    assert_identical(got, want)
    assert bool(mask[got[0][1][want_a[0].shape[1] :]].all())


def test_pairs_within_handles_empty_lists_and_nothing_in_range():
    pos = torch.rand(10, 3)
    empty = torch.zeros((2, 0), dtype=torch.long)
    edges, rel, dist = pair_kernels.pairs_within(pos, [empty], 0.5)
    assert edges.shape == (2, 0) and rel.shape == (0, 3) and dist.shape == (0,)
    far = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    edges, _, _ = pair_kernels.pairs_within(far, [torch.tensor([[0, 1], [1, 0]])], 0.5)
    assert edges.shape == (2, 0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_cut_at_the_radius_is_torchs_to_the_last_bit(dtype):
    # Pairs at every representable distance within 40 ulp of the radius, both ways along x: the kernels
    # must keep exactly the pairs that torch's sqrt puts below the radius (they cut squared distances).
    radius = 3.1 * 0.0123
    r = torch.tensor(radius, dtype=dtype)
    int_type = torch.int32 if dtype == torch.float32 else torch.int64
    offsets = (r.view(int_type) + torch.arange(-40, 41, dtype=int_type)).view(dtype)
    pos = torch.zeros(1 + offsets.numel(), 3, dtype=dtype)
    pos[1:, 0] = offsets
    others = torch.arange(1, pos.shape[0])
    edges = torch.stack([others, torch.zeros_like(others)])
    edges = torch.cat([edges, edges.flip(0)], dim=1)
    got = pair_kernels.pairs_within(pos, [edges], radius)
    want = torch_filter(pos, edges, radius)
    assert_identical(got, want)
    assert 0 < got[0].shape[1] < edges.shape[1]  # the cut falls inside the window


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("radius", [0.92 * 0.05, 2.1 * 0.05, 3.1 * 0.0217, 1.0, 7.3e-4])
def test_squared_bound_reproduces_torchs_sqrt_comparison(dtype, radius):
    bound = pair_kernels._squared_bound(radius, dtype)
    int_type = torch.int32 if dtype == torch.float32 else torch.int64
    d2 = (torch.tensor(bound, dtype=dtype).view(int_type) + torch.arange(-300, 301, dtype=int_type)).view(
        dtype
    )
    assert torch.equal(d2 < bound, torch.sqrt(d2) < radius)


def test_select_below_equals_boolean_selection():
    gen = torch.Generator().manual_seed(2)
    pos = torch.rand(400, 3, generator=gen)
    edges = torch.randint(0, 400, (2, 30_000), generator=gen)
    edges, rel, dist = pair_kernels.pairs_within(pos, [edges], 0.4)
    got = pair_kernels.select_below(edges, rel, dist, 0.25)
    keep = dist < 0.25
    assert_identical(got, (edges[:, keep], rel[keep], dist[keep]))


def test_applies_only_where_the_kernels_are_exact_and_available(monkeypatch):
    pos = torch.rand(5, 3)
    assert pair_kernels.applies(pos)
    assert not pair_kernels.applies(pos.clone().requires_grad_(True))
    with torch.no_grad():
        assert pair_kernels.applies(pos.clone().requires_grad_(True))
    monkeypatch.setattr(pair_kernels, "_compiled", lambda: None)
    assert not pair_kernels.applies(pos)


@pytest.mark.parametrize("wall_hops", [1, 2, 3, None])
def test_verlet_list_gives_the_same_graphs_with_and_without_the_kernels(monkeypatch, wall_hops):
    state = build_scene("dam", fluid_size=[6, 6, 8], tank_size=[15, 8])
    compiled = VerletNeighborList(3.1 * 0.05, 0.3 * 0.05, wall_hops=wall_hops)
    plain = VerletNeighborList(3.1 * 0.05, 0.3 * 0.05, wall_hops=wall_hops)
    gen = torch.Generator().manual_seed(4)
    pos = state.pos.clone()
    real_applies = pair_kernels.applies
    for _ in range(4):  # moves beyond skin/2 now and then: rebuilds in between
        pos[: state.n_fluid] += 0.005 * torch.randn(state.n_fluid, 3, generator=gen, dtype=pos.dtype)
        for radius in (3.1 * 0.05, 2.1 * 0.05):
            for fluid_only in (False, True):
                monkeypatch.setattr(pair_kernels, "applies", real_applies)
                got = compiled.graph(pos, state.ptype, radius, fluid_only)
                monkeypatch.setattr(pair_kernels, "applies", lambda *t: False)
                want = plain.graph(pos, state.ptype, radius, fluid_only)
                assert_identical((got.edge_index, got.rel, got.dist), (want.edge_index, want.rel, want.dist))
                sub_want = want.within(0.92 * 0.05)
                monkeypatch.setattr(pair_kernels, "applies", real_applies)
                sub_got = got.within(0.92 * 0.05)
                assert_identical(
                    (sub_got.edge_index, sub_got.rel, sub_got.dist),
                    (sub_want.edge_index, sub_want.rel, sub_want.dist),
                )
            # the rebuild from one compiled cell list == the radius_graph searches, pair for pair
            assert torch.equal(compiled.candidates, plain.candidates)
            assert compiled._fluid_prefix == plain._fluid_prefix
    assert compiled.builds == plain.builds >= 2


def test_cell_list_rejects_non_finite_positions_by_name():
    pos = torch.rand(20, 3)
    pos[7, 1] = float("nan")
    with pytest.raises(ValueError, match="particle 7"):
        pair_kernels.CellList.build(pos, 0.3)
    state = build_scene("dam", fluid_size=[4, 4, 4], tank_size=[8, 8])
    bad = state.pos.clone()
    bad[3, 2] = float("inf")
    with pytest.raises(ValueError, match="particle 3"):
        VerletNeighborList(3.1 * 0.05, 0.3 * 0.05).graph(bad, state.ptype, 3.1 * 0.05)


@pytest.mark.parametrize("numbering", ["lattice", "random"])
def test_cell_search_pairs_are_sorted_and_exact_whatever_the_particle_numbering(numbering):
    """Lattice numbering takes the insertion sort's cheap path; a random one exhausts its budget."""
    from lagfluid.neighbors import radius_graph

    state = build_scene("dam", fluid_size=[10, 8, 6], tank_size=[14, 10])
    pos = state.pos + 1e-3 * torch.randn_like(state.pos)  # off the lattice: no distance ties at the cut
    if numbering == "random":
        pos = pos[torch.randperm(pos.shape[0], generator=torch.Generator().manual_seed(0))]
    radius = 2.73 * 0.05
    receivers = torch.arange(0, pos.shape[0], 3)
    got = pair_kernels.CellList.build(pos, radius).pairs(receivers)
    is_receiver = torch.zeros(pos.shape[0], dtype=torch.bool)
    is_receiver[receivers] = True
    want = radius_graph(pos, radius, receivers=is_receiver, backend="brute")
    assert got.shape[1] > 20 * receivers.numel()  # a full neighbourhood each
    assert torch.equal(got, want)  # sorted by target, then source, as every backend


def test_the_first_compiled_search_keeps_torchs_thread_count():
    # Numba's OpenMP pool, started inside a kernel's first parallel loop, set torch to every core: a
    # threads=1 run (a one-core job of a sweep) then ran on 2. A fresh process: the pool starts once.
    code = (
        "import torch; torch.set_num_threads(1)\n"
        "from lagfluid.neighbors import radius_graph\n"
        "radius_graph(torch.rand(3000, 3, generator=torch.Generator().manual_seed(0)), 0.08)\n"
        "print(torch.get_num_threads())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split()[-1] == "1"


# ---------------------------------------------------------------- the Verlet list's split search (issue 37)
L = 0.25  # a lattice spacing that binary floats hold exactly: lattice distances like 2 L are exact


def floor_tank(dtype, jitter=0.0, seed=0):
    """Fluid on an integer lattice above a floor of walls (z = -1 L) and dummies (z = -2 L), fluid rows first.

    Without jitter many pairs sit at exactly 2 L, the list radius of :func:`split_lists` below.
    """
    gen = torch.Generator().manual_seed(seed)
    grid = torch.stack(torch.meshgrid(*[torch.arange(-3.0, 5.0)] * 2, indexing="ij"), -1).reshape(-1, 2)
    fluid = torch.cat([torch.cat([grid, torch.full((64, 1), z)], 1) for z in (0.0, 1.0, 2.0)])
    floor = torch.cat([torch.cat([grid, torch.full((64, 1), z)], 1) for z in (-1.0, -2.0)])
    fluid = fluid + jitter * (torch.rand(fluid.shape, generator=gen, dtype=torch.float64) - 0.5)
    pos = (torch.cat([fluid, floor]) * L).to(dtype)
    ptype = torch.cat([torch.full((192,), 1), torch.full((64,), 2), torch.full((64,), 3)])
    return pos, ptype


def split_lists(wall_hops=2, backend="auto"):
    return VerletNeighborList(1.5 * L, 0.5 * L, backend=backend, wall_hops=wall_hops)  # list radius 2 L


def candidates(nl, pos, ptype):
    nl.reset()
    nl.update(pos, ptype)
    return nl.candidates, nl._fluid_prefix


def one_cell_list(nl, pos, ptype):
    """The candidates as the previous compiled search found them: one cell list over every particle."""
    fluid, walls = ptype == 1, ptype == 2
    cells = pair_kernels.CellList.build(pos, nl.list_radius)
    return nl._search_with_cells(cells, fluid, walls)


def states(dtype):
    yield "lattice", *floor_tank(dtype)  # pairs at exactly the list radius
    yield "jittered", *floor_tank(dtype, jitter=0.3)
    yield "random", *floor_tank(dtype, jitter=3.0, seed=1)  # fluid scattered, some in and below the floor
    dam = build_scene("dam", fluid_size=[6, 6, 8], tank_size=[15, 8], dtype=dtype)
    pos = dam.pos.clone()
    pos[: dam.n_fluid] += (
        0.3 * L * torch.randn(dam.n_fluid, 3, generator=torch.Generator().manual_seed(2)).to(dtype)
    )
    yield "dam", pos, dam.ptype


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("wall_hops", [1, 2, None])
def test_split_search_gives_the_candidates_of_brute_force_and_of_one_cell_list(dtype, wall_hops):
    for name, pos, ptype in states(dtype):
        fast = split_lists(wall_hops)
        got, prefix = candidates(fast, pos, ptype)
        assert fast.boundary_builds == 1, name  # the split search served (not the one-cell-list fallback)
        want, want_prefix = candidates(split_lists(wall_hops, backend="brute"), pos, ptype)
        assert torch.equal(got, want) and prefix == want_prefix, name
        assert torch.equal(got, one_cell_list(fast, pos, ptype)), name
        # the wall rows' index from the boundary's static hops == filtering the boundary-source pairs again
        want_rows = _WallRows.build(pos, got[:, prefix:], int((ptype == 1).sum()), fast.cutoff)
        for field in ("dyn", "dyn_edges", "dyn_dst", "hop_src", "hop_dst", "boundary_at"):
            assert torch.equal(getattr(fast._static, field), getattr(want_rows, field)), (name, field)
        assert fast._static.closest_static == want_rows.closest_static, name
    # the lattice has pairs at exactly the list radius: none of them is a candidate (the cut is strict)
    pos, ptype = floor_tank(dtype)
    got, _ = candidates(split_lists(wall_hops), pos, ptype)
    d2 = ((pos[got[0]] - pos[got[1]]).double() ** 2).sum(1)
    assert d2.max() < (2 * L) ** 2
    assert ((pos[:, None] - pos[None]).double().pow(2).sum(-1) == (2 * L) ** 2).any()


def test_static_boundary_is_indexed_once_and_again_when_the_walls_change():
    pos, ptype = floor_tank(torch.float64, jitter=0.3)
    fast, brute = split_lists(), split_lists(backend="brute")
    gen = torch.Generator().manual_seed(3)
    for _ in range(3):  # rebuilds as the fluid moves: the boundary's index is reused
        pos[:192] += 0.6 * L * torch.rand(192, 3, generator=gen, dtype=pos.dtype)
        fast.update(pos, ptype)
        brute.update(pos, ptype)
        assert torch.equal(fast.candidates, brute.candidates)
    assert fast.builds == 3 and fast.boundary_builds == 1
    moved = pos.clone()
    moved[192:256, 2] += 0.5 * L  # the walls move up (a new scene): the cached walls are stale
    fast.update(moved, ptype)
    brute.update(moved, ptype)
    assert fast.boundary_builds == 2 and torch.equal(fast.candidates, brute.candidates)
    retyped = ptype.clone()
    retyped[200:210] = 3  # ten walls become dummies, at the same positions: no longer targets
    fast.reset()
    brute.reset()
    fast.update(moved, retyped)
    brute.update(moved, retyped)
    assert fast.boundary_builds == 3 and torch.equal(fast.candidates, brute.candidates)


def test_split_search_without_boundary_or_fluid_and_with_fluid_rows_not_first():
    pos, ptype = floor_tank(torch.float32, jitter=0.3)
    for p, t in ((pos[:192], ptype[:192]), (pos[192:], ptype[192:])):
        got, prefix = candidates(split_lists(None), p, t)
        want, want_prefix = candidates(split_lists(None, backend="brute"), p, t)
        assert torch.equal(got, want) and prefix == want_prefix
    perm = torch.randperm(320, generator=torch.Generator().manual_seed(0))  # fluid rows mixed in
    fast = split_lists()
    got, _ = fast._search_compiled(pos[perm], ptype[perm] == 1, ptype[perm] == 2, 192)
    assert torch.equal(got, one_cell_list(fast, pos[perm], ptype[perm]))  # served by one cell list over all
    assert fast.boundary_builds == 0


@pytest.mark.parametrize("chunks", [1, 3, 7])
def test_fluid_rows_come_sorted_from_the_transpose_whatever_the_chunks(monkeypatch, chunks):
    """The fluid-fluid rows are sorted by a transpose over ascending runs of rows, one run per thread."""
    monkeypatch.setattr(pair_kernels, "numba_threads", lambda: chunks)
    pos, ptype = floor_tank(torch.float32, jitter=3.0, seed=5)  # numbering unrelated to the cells
    perm = torch.cat(
        [torch.randperm(192, generator=torch.Generator().manual_seed(1)), torch.arange(192, 320)]
    )
    pos = pos[perm]
    got, prefix = candidates(split_lists(), pos, ptype)
    want, want_prefix = candidates(split_lists(backend="brute"), pos, ptype)
    assert torch.equal(got, want) and prefix == want_prefix
