"""A Verlet neighbour list over moving fluid and static boundary particles.

One step of the split-step scheme evaluates operators at three sets of positions (``x^n``, ``x*`` after
advection, ``x**`` after collision) and four radii (0.92, 2.1, 3.1 l0 and the networks' radii).
Searching at every position set would repeat the neighbour search three times per step. Instead we
keep *candidate* pairs within ``cutoff + skin`` and filter them by the true current distance; the list
is rebuilt only when some fluid particle has moved more than ``skin / 2`` since the last build, which
guarantees that every pair within ``cutoff`` is a candidate. The result is exact, not approximate. On
the CPU the filter is one compiled pass per candidate list (:mod:`lagfluid.neighbors.pair_kernels`,
bit-identical to the torch operations used on CUDA and for positions that require grad).

Receivers (graph targets) are the fluid particles and the wall particles within ``wall_hops`` hops of
the fluid, a hop being the cutoff (3.1 l0, the Laplacian radius): walls with fluid within 3.1 l0, then
walls within 3.1 l0 of those, at the current positions (so the set never depends on when the list was
rebuilt). Dummy particles and farther walls only ever appear as sources, so a scene's boundary costs work
only where the fluid is ("model only what the scene requires"). The pressure solve treats the farther
walls as p = 0. Why two hops: a wall within 3.1 l0 of the fluid pushes it, and its own pressure is
coupled through the Laplacian to the walls one radius further; two hops come within 0.01 % of solving
every wall (the authors, ``wall_hops=None``), one hop does not (``benchmarks/results/neighbors_notes.md``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from lagfluid.neighbors import pair_kernels
from lagfluid.neighbors.geometry import edge_vectors, take_edges
from lagfluid.neighbors.pair_kernels import backend_for
from lagfluid.neighbors.search import radius_graph
from lagfluid.state import ParticleType

log = logging.getLogger(__name__)


@dataclass
class Graph:
    """Edges within one radius at one set of positions.

    Attributes:
        edge_index: (2, E) int64, row 0 = source j, row 1 = target i, sorted by target.
        rel: (E, 3) ``x_j - x_i``.
        dist: (E,) ``|x_j - x_i|``.
        radius: the radius in metres (every edge has ``dist < radius``).
        first_counts: ``{n: k}``: the first ``k`` edges are those into particles ``0 .. n-1`` (what
            :meth:`into_first` found, or the builder knew); on CUDA each count read is a host synchronisation.
    """

    edge_index: Tensor
    rel: Tensor
    dist: Tensor
    radius: float
    first_counts: dict[int, int] = field(default_factory=dict, repr=False, compare=False)

    def within(self, radius: float) -> Graph:
        """Sub-graph with ``dist < radius`` (``radius`` must not exceed this graph's radius)."""
        if radius > self.radius * (1 + 1e-12):
            raise ValueError(f"cannot restrict a graph of radius {self.radius} to a larger radius {radius}")
        if radius >= self.radius:  # every edge already qualifies: no pass over the edges
            return self
        select_below = backend_for("select_below", self.rel, self.dist)
        return Graph(*select_below(self.edge_index, self.rel, self.dist, radius), radius)

    def select(self, keep: Tensor) -> Graph:
        """Sub-graph of the edges where the (E,) bool mask ``keep`` is True."""
        # nonzero + index_select rather than boolean indexing: faster on the CPU for (E, 3) arrays.
        index = torch.nonzero(keep).flatten()
        rel, dist = self.rel.index_select(0, index), self.dist.index_select(0, index)
        return Graph(take_edges(self.edge_index, index), rel, dist, self.radius)

    def into_first(self, n: int) -> Graph:
        """Sub-graph of the edges whose target is one of particles ``0 .. n-1`` (e.g. the fluid).

        Edges are sorted by target, so this is a slice (a view, no copy) rather than a mask.
        """
        k = self.first_counts.get(n)
        if k is None:
            k = int(torch.searchsorted(self.edge_index[1], n))  # a number, not a tensor: no upload
            self.first_counts[n] = k
        return Graph(self.edge_index[:, :k], self.rel[:k], self.dist[:k], self.radius, {n: k})

    @property
    def geometry(self) -> tuple[Tensor, Tensor]:
        """``(rel, dist)``, the ``geometry`` keyword of :mod:`lagfluid.physics.operators`."""
        return self.rel, self.dist


class VerletNeighborList:
    """Candidate pairs within ``cutoff + skin``; see the module docstring.

    Args:
        cutoff: the largest radius any stage will ask for, metres.
        skin: extra margin, metres; larger = fewer rebuilds, more candidate pairs to filter.
        backend: neighbour-search backend passed to :func:`lagfluid.neighbors.search.radius_graph`.
    """

    def __init__(self, cutoff: float, skin: float, backend: str = "auto", wall_hops: int | None = 2) -> None:
        if not (cutoff > 0 and skin >= 0):
            raise ValueError(f"need cutoff > 0 and skin >= 0, got cutoff={cutoff}, skin={skin}")
        if wall_hops is not None and wall_hops < 1:
            raise ValueError(f"wall_hops must be >= 1 or None (every wall), got {wall_hops}")
        self.wall_hops = wall_hops
        self.cutoff = float(cutoff)
        self.skin = float(skin)
        self.backend = backend
        self.candidates: Tensor | None = None
        self._fluid_prefix = 0  # candidates[:, :_fluid_prefix] are the pairs into fluid particles
        self._built_at: Tensor | None = None
        self._static: _WallRows | None = None
        self._fluid_rows: tuple[Tensor, int, int] | None = None  # (ptype, its _version, its FLUID count)
        self._boundary: pair_kernels.StaticBoundary | None = None  # the boundary's index (compiled search)
        self._layout: pair_kernels.WallLayout | None = None  # where the split search put the wall rows
        self.builds = 0
        self.boundary_builds = 0  # how often the static boundary was indexed (once per scene)

    @property
    def list_radius(self) -> float:
        """Radius of the candidate search, metres."""
        return self.cutoff + self.skin

    def reset(self) -> None:
        """Forget the candidate list (the next :meth:`update` searches again).

        The boundary's index is kept: every rebuild checks it against the boundary (remade if they differ).
        """
        self.candidates = None
        self._built_at = None
        self._static = None

    def needs_rebuild(self, pos: Tensor, n_fluid: int) -> bool:
        """True when a fluid particle has moved more than ``skin / 2`` since the last build.

        Also when the boundary is not where it was at the last build (the list and the cached distances
        between boundary particles assume a static boundary), or the dtype or device changed.
        """
        if self.candidates is None or self._built_at is None or self._built_at.shape[0] != n_fluid:
            return True
        boundary = self._static.boundary_at if self._static is not None else None
        if boundary is None or boundary.dtype != pos.dtype or boundary.device != pos.device:
            return True
        if boundary.shape != pos[n_fluid:].shape:
            return True
        # One read of the device for both tests (on CUDA each read is a host synchronisation).
        stale = (pos[n_fluid:] != boundary).any()
        if n_fluid:
            stale |= (pos[:n_fluid] - self._built_at).norm(dim=1).max() > 0.5 * self.skin
        return bool(stale)

    def _fluid_count(self, ptype: Tensor) -> int:
        """The FLUID rows of ``ptype`` (N,), counted once per ``ptype`` tensor (a read of the device)."""
        seen = self._fluid_rows
        if seen is None or seen[0] is not ptype or seen[1] != ptype._version:
            seen = (ptype, ptype._version, int((ptype == ParticleType.FLUID).sum()))
            self._fluid_rows = seen
        return seen[2]

    def update(self, pos: Tensor, ptype: Tensor) -> bool:
        """Rebuild the candidate list if needed; returns True when it searched.

        Args:
            pos: (N, 3) positions, fluid rows first (see :mod:`lagfluid.state`).
            ptype: (N,) particle types.
        """
        n_fluid = self._fluid_count(ptype)
        if not self.needs_rebuild(pos, n_fluid):
            return False
        fluid = ptype == ParticleType.FLUID
        walls = ptype == ParticleType.WALL
        # the compiled cell list serves the backends "auto" and "numba"; the others search by name
        search = backend_for("verlet_search", pos, compiled=self.backend in ("auto", "numba"))
        self._layout = None  # set by the split search: where its wall rows lie
        self.candidates, self._fluid_prefix = search(self, pos, fluid, walls, n_fluid)
        self._built_at = pos[:n_fluid].clone()
        into_walls = self.candidates[:, self._fluid_prefix :]
        if self._layout is not None:  # the static parts of the wall rows are known from the boundary's index
            self._static = _WallRows.from_split(pos, into_walls, self._boundary, self._layout, self.cutoff)
        else:
            self._static = _WallRows.build(pos, into_walls, n_fluid, self.cutoff)
        self.builds += 1
        log.debug("neighbour list rebuilt: %d candidate pairs", self.candidates.shape[1])
        return True

    def _search_compiled(self, pos: Tensor, fluid: Tensor, walls: Tensor, n_fluid: int) -> tuple[Tensor, int]:
        """:meth:`_search` by compiled cell lists (the torch body where the box is too wide for one).

        The boundary (rows from ``n_fluid``, static) is indexed once per scene (:class:`StaticBoundary`,
        rebuilt whenever its positions or wall flags differ from the cached ones), so a rebuild searches
        only the fluid (:func:`pair_kernels.verlet_candidates`); one cell list over every particle where the
        fluid rows are not first or the fluid's box is too wide.
        """
        if bool(fluid[:n_fluid].all()):  # the fluid is the first n_fluid rows (the split search's premise)
            static = self._boundary
            if static is None or not static.matches(pos, walls, n_fluid, self.list_radius):
                static = pair_kernels.StaticBoundary.build(pos, walls, n_fluid, self.list_radius)
                self._boundary = static
                self.boundary_builds += 1
            if static is not None:
                found = pair_kernels.verlet_candidates(pos, static, self.wall_hops)
                if found is not None:
                    candidates, prefix, self._layout = found
                    return candidates, prefix
        cells = pair_kernels.CellList.build(pos, self.list_radius)
        if cells is None:  # far-flung particles: too many cells for the dense cell table
            return self._search(pos, fluid, walls, n_fluid)
        candidates = self._search_with_cells(cells, fluid, walls)
        return candidates, int(torch.searchsorted(candidates[1], torch.tensor(n_fluid)))

    def _search_with_cells(self, cells: pair_kernels.CellList, fluid: Tensor, walls: Tensor) -> Tensor:
        """The candidates (2, E) from one compiled cell list over every particle (what :meth:`_search` finds).

        The compiled search where the split one (:func:`pair_kernels.verlet_candidates`) does not apply.

        The walls within ``wall_hops`` hops are found by any-neighbour queries over the walls, then the fluid
        and those walls are searched together (fluid rows first, so the edges come sorted by target exactly
        as :meth:`_search` concatenates them).

        Its speed on ``dam_medium`` / ``dam_large``: see ``benchmarks/results/neighbors_notes.md``.
        """
        if self.wall_hops is None:
            near_walls = walls.clone()
        else:
            wall_index = torch.nonzero(walls).flatten()
            near_walls = torch.zeros_like(fluid)
            near_walls[wall_index[cells.any_within(wall_index, fluid)]] = True
            frontier = near_walls.clone()
            for _ in range(self.wall_hops - 1):
                if not bool(frontier.any()):
                    break
                rest = torch.nonzero(walls & ~near_walls).flatten()  # the walls of the next hop among these
                reached = torch.zeros_like(fluid)
                reached[rest[cells.any_within(rest, frontier)]] = True
                frontier = reached
                near_walls |= frontier
        return cells.pairs(torch.nonzero(fluid | near_walls).flatten())

    def _search(self, pos: Tensor, fluid: Tensor, walls: Tensor, n_fluid: int) -> tuple[Tensor, int]:
        """The candidates (2, E) from :func:`radius_graph` searches (any backend, any device).

        Returns the candidates and how many of them are pairs into the fluid (their first columns).
        """
        r = self.list_radius
        into_fluid = radius_graph(pos, r, receivers=fluid, backend=self.backend)
        # Walls within `wall_hops` hops of the fluid receive edges too (their number density and pressure
        # matter); the rest of the boundary is never a target. Walls are static, so the hops beyond the
        # first only search around walls.
        if self.wall_hops is None:
            near_walls = walls.clone()
        else:
            near_walls = torch.zeros_like(fluid)
            near_walls[into_fluid[0][walls[into_fluid[0]]]] = True
            frontier = near_walls.clone()
            for _ in range(self.wall_hops - 1):
                if not bool(frontier.any()):
                    break
                around = radius_graph(pos, r, receivers=frontier, backend=self.backend)[0]
                frontier = torch.zeros_like(fluid)
                frontier[around[walls[around] & ~near_walls[around]]] = True
                near_walls |= frontier
        if not bool(near_walls.any()):
            return into_fluid, into_fluid.shape[1]
        into_walls = radius_graph(pos, r, receivers=near_walls, backend=self.backend)
        # Fluid rows come first, so concatenating keeps the edges sorted by target.
        return torch.cat([into_fluid, into_walls], dim=1), into_fluid.shape[1]

    def graph(self, pos: Tensor, ptype: Tensor, radius: float, fluid_targets_only: bool = False) -> Graph:
        """Every pair within ``radius`` at positions ``pos`` (N, 3), from the candidate list.

        Rebuilds the list first when the fluid has moved too far since the last build, so the answer is
        exact at any positions (``x^n``, ``x*``, ``x**`` of one step alike).

        Args:
            pos: (N, 3) positions, fluid rows first.
            ptype: (N,) particle types.
            radius: metres, at most ``cutoff``.
            fluid_targets_only: only edges into fluid particles (a prefix of the candidates, so the
                wall rows cost nothing when a stage does not need them).

        Raises:
            ValueError: ``radius`` exceeds the list's cutoff.
        """
        if radius > self.cutoff * (1 + 1e-12):
            raise ValueError(f"radius {radius} exceeds the neighbour list cutoff {self.cutoff}")
        self.update(pos, ptype)
        walls = self._static
        with_walls = not fluid_targets_only and walls is not None and walls.num_candidates > 0
        return backend_for("verlet_graph", pos)(self, pos, ptype, radius, with_walls)

    def _graph_compiled(self, pos: Tensor, ptype: Tensor, radius: float, with_walls: bool) -> Graph:
        """:meth:`graph` in one compiled pass per candidate list (:mod:`lagfluid.neighbors.pair_kernels`)."""
        into_fluid = self.candidates[:, : self._fluid_prefix]
        if not with_walls:
            return Graph(*pair_kernels.pairs_within(pos, [into_fluid], radius), radius)
        active = self._active_walls(pos) if self.wall_hops is not None else None
        edges, rel, dist = pair_kernels.pairs_within(
            pos, [into_fluid, self._static.candidates], radius, [None, active]
        )
        return Graph(edges, rel, dist, radius)

    def _graph_torch(self, pos: Tensor, ptype: Tensor, radius: float, with_walls: bool) -> Graph:
        """:meth:`graph` in torch operations; the boundary-source pairs keep their cached geometry."""
        into_fluid = self.candidates[:, : self._fluid_prefix]
        walls = self._static
        rel, dist = edge_vectors(pos, into_fluid)
        # nonzero + index_select rather than boolean indexing: faster on the CPU for (E, 3) arrays.
        keep = torch.nonzero(dist < radius).flatten()
        k = keep.numel()
        nf = self._fluid_count(ptype)  # the first k edges are those into the fluid
        if not with_walls:
            edge_index = take_edges(into_fluid, keep)
            return Graph(edge_index, rel.index_select(0, keep), dist.index_select(0, keep), radius, {nf: k})
        # Wall rows: only the pairs with a fluid source move; the boundary-boundary pairs (most of them)
        # keep the distances computed at the last build.
        w_rel, w_dist, from_fluid = walls.geometry(pos)
        within = w_dist < radius
        if self.wall_hops is not None:
            # Wall targets: exactly the walls within `wall_hops` hops (of length `cutoff`) of the fluid at
            # these positions. The list holds more (walls within reach at its last build), but a set that
            # depended on when the list was rebuilt would make wall pressures depend on history.
            active = self._hops_from(walls.dyn_dst, pos, from_fluid < self.cutoff)
            within &= active.index_select(0, walls.candidates[1])
        w_keep = torch.nonzero(within).flatten()
        # Wall targets come after every fluid target, so fluid rows then wall rows stay sorted by target.
        # Gathered straight into the two halves of one output rather than gathered then concatenated:
        # a concatenation pass costs a large share of this method (see benchmarks/results/neighbors_notes.md).
        e = k + w_keep.numel()
        edge_index = into_fluid.new_empty((2, e))
        take_edges(into_fluid, keep, out=edge_index[:, :k])
        take_edges(walls.candidates, w_keep, out=edge_index[:, k:])
        if rel.requires_grad:  # out= records no autograd history: concatenate (differentiable)
            out_rel = torch.cat([rel.index_select(0, keep), w_rel.index_select(0, w_keep)])
            out_dist = torch.cat([dist.index_select(0, keep), w_dist.index_select(0, w_keep)])
            return Graph(edge_index, out_rel, out_dist, radius, {nf: k})
        out_rel, out_dist = rel.new_empty((e, rel.shape[1])), dist.new_empty(e)
        torch.index_select(rel, 0, keep, out=out_rel[:k])
        torch.index_select(w_rel, 0, w_keep, out=out_rel[k:])
        torch.index_select(dist, 0, keep, out=out_dist[:k])
        torch.index_select(w_dist, 0, w_keep, out=out_dist[k:])
        return Graph(edge_index, out_rel, out_dist, radius, {nf: k})

    def wall_targets(self, pos: Tensor, ptype: Tensor) -> Tensor | None:
        """(N,) bool: the walls that are graph targets at ``pos`` (N, 3); None when every wall is one.

        The walls within ``wall_hops`` hops of the fluid at these positions, as :meth:`graph` selects them
        (rebuilding the list first when the fluid has moved too far, as :meth:`graph` does).
        """
        self.update(pos, ptype)
        if self.wall_hops is None:
            return None
        walls = self._static
        if walls is None or walls.num_candidates == 0:
            return torch.zeros(pos.shape[0], dtype=torch.bool, device=pos.device)
        return backend_for("verlet_active_walls", pos)(self, pos)

    def closest_static_pair(self) -> float:
        """The shortest pair between boundary particles into a wall target under the cutoff, m (inf if none).

        On a lattice boundary l0: a graph of a radius up to it has no edge between two boundary particles.
        """
        return self._static.closest_static if self._static is not None else math.inf

    def _active_walls(self, pos: Tensor) -> Tensor:
        """(N,) bool: the walls within ``wall_hops`` hops (of length ``cutoff``) of the fluid at ``pos``.

        The same set as the torch path of :meth:`graph` computes, from the fluid-source candidate pairs.
        """
        near, _, _ = pair_kernels.pairs_within(pos, [self._static.dyn_edges], self.cutoff)
        return self._hops_from(near[1], pos)

    def _active_walls_torch(self, pos: Tensor) -> Tensor:
        """:meth:`_active_walls` in torch operations, from the cached geometry of the wall rows."""
        walls = self._static
        return self._hops_from(walls.dyn_dst, pos, walls.geometry(pos)[2] < self.cutoff)

    def _hops_from(self, first: Tensor, pos: Tensor, where: Tensor | None = None) -> Tensor:
        """(N,) bool: the walls ``first`` (indices) and ``wall_hops - 1`` hops beyond them.

        ``first``: the walls within the cutoff of a fluid particle, or with ``where`` (same shape, bool)
        those of ``first`` where it is True; a hop is a static wall-to-wall pair closer than the cutoff.
        Scatters rather than boolean indexing: no data-dependent size, so no host synchronisation on CUDA
        (CUDA's ``scatter_reduce_`` has no deterministic form: ``torch.use_deterministic_algorithms``
        refuses it).
        """
        walls = self._static
        active = torch.zeros(pos.shape[0], dtype=torch.uint8, device=pos.device)
        if where is None:
            active[first] = 1
        else:
            active.scatter_reduce_(0, first, where.to(torch.uint8), "amax")
        for _ in range(self.wall_hops - 1):
            active.scatter_reduce_(0, walls.hop_dst, active.index_select(0, walls.hop_src), "amax")
        return active.bool()


@dataclass
class _WallRows:
    """The candidate pairs into wall targets, with the geometry of the static (boundary-source) ones cached.

    Boundary particles never move, so of the pairs into wall targets only those with a fluid source need
    their distance recomputed at new positions; the others (about 4 in 5) keep the values computed at the
    last build (the same formula on the same numbers: bit-identical to recomputing them).

    Attributes:
        candidates: (2, Ew) the candidate pairs into walls (sorted by target, then source).
        rel, dist: (Ew, 3), (Ew,) geometry buffers: exact for boundary sources, refreshed for fluid sources
            by :meth:`geometry`; None until its first call (the compiled CPU filter recomputes every pair
            in one pass and never asks, so the default path holds no ~16 bytes per wall pair for nothing).
        dyn: (Ed,) positions (in ``candidates``) of the pairs with a fluid source; ``dyn_edges`` their pairs,
            ``dyn_dst`` their targets.
        hop_src, hop_dst: boundary-to-wall pairs closer than the cutoff (static): the hops between walls.
        boundary_at: (N - n_fluid, 3) the boundary positions the cache holds.
        closest_static: the shortest boundary-to-wall pair under the cutoff, m (inf if none): no graph of a
            smaller radius has a boundary-source edge into a wall.
    """

    candidates: Tensor
    rel: Tensor | None
    dist: Tensor | None
    dyn: Tensor
    dyn_edges: Tensor
    dyn_dst: Tensor
    hop_src: Tensor
    hop_dst: Tensor
    boundary_at: Tensor
    closest_static: float

    @property
    def num_candidates(self) -> int:
        """Ew, the number of candidate pairs into walls."""
        return int(self.candidates.shape[1])

    @classmethod
    def build(cls, pos: Tensor, candidates: Tensor, n_fluid: int, cutoff: float) -> _WallRows:
        """Index the ``candidates`` (2, Ew) into walls at ``pos`` (N, 3): fluid-source pairs and wall hops."""
        from_fluid = candidates[0] < n_fluid
        dyn = torch.nonzero(from_fluid).flatten()
        dyn_edges = take_edges(candidates, dyn)
        static = take_edges(candidates, torch.nonzero(~from_fluid).flatten())  # boundary sources, in order
        hop_pairs, _, hop_dist = backend_for("pairs_within", pos)(pos, [static], cutoff)
        return cls(
            candidates,
            None,
            None,
            dyn,
            dyn_edges,
            dyn_edges[1],
            hop_pairs[0],
            hop_pairs[1],
            pos[n_fluid:].clone(),
            float(hop_dist.min()) if hop_dist.numel() else math.inf,
        )

    @classmethod
    def from_split(
        cls,
        pos: Tensor,
        candidates: Tensor,
        boundary: pair_kernels.StaticBoundary,
        layout: pair_kernels.WallLayout,
        cutoff: float,
    ) -> _WallRows:
        """:meth:`build` for the wall rows of the split search: the hops come from the boundary's index.

        The same fields as :meth:`build` finds by filtering the boundary-source pairs at every rebuild: those
        pairs are static, so their hops (closer than ``cutoff``) and each row's shortest one are made once per
        scene (:meth:`pair_kernels.StaticBoundary.hop_rows`) and only gathered here.
        """
        nf = boundary.n_fluid
        dyn = torch.from_numpy(layout.dynamic())
        dyn_edges = take_edges(candidates, dyn)
        ptr, src, closest = boundary.hop_rows(cutoff)
        counts = ptr[layout.rows + 1] - ptr[layout.rows]
        hop_src = src[pair_kernels._ranges(ptr[layout.rows], counts)] + nf
        hop_dst = np.repeat(layout.targets, counts) + nf
        shortest = float(closest[layout.rows].min()) if layout.rows.size else math.inf
        return cls(
            candidates,
            None,
            None,
            dyn,
            dyn_edges,
            dyn_edges[1],
            torch.from_numpy(hop_src),
            torch.from_numpy(hop_dst),
            pos[nf:].clone(),
            shortest,
        )

    def geometry(self, pos: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(rel, dist)`` of every pair into walls at ``pos`` and the distances of the fluid-source pairs.

        The returned ``rel`` and ``dist`` are the internal buffers (overwritten by the next call): take
        copies (``index_select``) of what is kept.
        """
        if self.rel is None or self.dist is None:  # first call: the boundary-source pairs, static from now on
            # detached: a static boundary takes no gradient, and the buffer is written in place below
            self.rel, self.dist = edge_vectors(pos.detach(), self.candidates)
        rel, dist = edge_vectors(pos, self.dyn_edges)
        self.rel.index_copy_(0, self.dyn, rel)
        self.dist.index_copy_(0, self.dyn, dist)
        return self.rel, self.dist, dist


pair_kernels.register(
    "verlet_search",
    compiled=VerletNeighborList._search_compiled,
    torch=VerletNeighborList._search,
)
pair_kernels.register(
    "verlet_graph", compiled=VerletNeighborList._graph_compiled, torch=VerletNeighborList._graph_torch
)
pair_kernels.register(
    "verlet_active_walls",
    compiled=VerletNeighborList._active_walls,
    torch=VerletNeighborList._active_walls_torch,
)
