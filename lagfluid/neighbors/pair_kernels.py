"""Kernels over particle pairs with a compiled (Numba, CPU) and a torch body, and where a backend is chosen.

Backends are chosen in one place. Every computation with a compiled and a torch body, here and in the
operators, the PPE assembly, FGN's and CConv's stages, is a :class:`Kernel` registered by name
(:func:`register`); an algorithm asks :func:`backend_for` for the body that serves its tensors and calls it,
without a branch of its own. The compiled body serves CPU tensors in float32 or float64 that need no
gradient, when Numba is installed (:func:`applies`); the torch body every other case (CUDA, autograd, no
Numba). A compiled body may hand input it does not take (edges not sorted by target, a handful of pairs)
to its torch body: both give the same numbers.

The pair filters here (:func:`pairs_within`, :func:`select_below`, :func:`induced_edges`, the cell list of
:func:`cell_search`): the Verlet list (:mod:`lagfluid.neighbors.verlet`) filters every candidate pair by its
current distance twice per MPS step, and as torch operations that pass materialises ``pos[src]``,
``pos[dst]``, ``rel``, ``rel * rel``, the mask and the ``nonzero`` index (each 1-10 M rows) before gathering
the kept rows again. The compiled bodies read each candidate once from cache-resident positions and write
only the kept pairs (measurements: ``benchmarks/results/neighbors_notes.md``). Neither PyG nor SciPy filters
an existing pair list.

The results are *bit-identical* to the torch bodies (:func:`lagfluid.neighbors.geometry.edge_vectors`
followed by ``dist < radius``): the same float operations in the same order (``sqrt((x*x + y*y) + z*z)``
in the positions' dtype, no fused multiply-add, no fast-math) and the radius rounded to that dtype as torch
rounds a Python scalar. The kept pairs keep their input order, so target-sorted input stays sorted.

The torch bodies remain for CUDA tensors, for positions that require grad, and where Numba is not
installed (:func:`available`).
"""

from __future__ import annotations

import functools
import importlib
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np
import torch
from torch import Tensor

from lagfluid.neighbors.geometry import edge_vectors, take_edges

log = logging.getLogger(__name__)


COMPILE_SECONDS = 18
"""Seconds the first run on a fresh install spends compiling the kernels a rollout calls. Measured: one step
of ``scene=dam_small threads=1`` with an empty ``NUMBA_CACHE_DIR`` took 17.9 s (MPS) and 17.2 s (FGN) more CPU
time than with the kernels cached (a 2-core machine; with 6 jobs on its cores the wall time was 53 s)."""

_announced: list[str] = []  # the kernel modules whose compilation was announced (once per process)


@functools.cache
def load(module: str) -> ModuleType | None:
    """A module of Numba kernels (imported once), or None when Numba is not importable.

    Numba is a dependency; the None keeps an install without it usable (the torch operations serve).
    The kernels compile on their first call and are cached on disk; when nothing is cached yet (a fresh
    install), one log line says so before the first call compiles them, instead of ~18 s of silence.
    """
    try:
        kernels = importlib.import_module(module)
    except ImportError as err:
        log.warning("numba unavailable (%s): %s falls back to slower torch operations", err, module)
        return None
    where = uncached_kernels(kernels)
    if where and not _announced:
        log.info("compiling the CPU kernels once, ~%d s; cached afterwards (%s)", COMPILE_SECONDS, where)
        _announced.append(module)
    return kernels


def uncached_kernels(kernels: ModuleType) -> str | None:
    """The cache folder of ``kernels`` when none of its kernels is cached there yet, else None.

    A kernel is a Numba dispatcher with ``cache=True``; its cache index is empty until a first call has
    compiled it (or the source changed since). A run calls only some kernels, so one cached kernel means
    the module was compiled here before. Kernels inlined into others (``inline="always"``) are never compiled
    alone and are not counted. None also where Numba's cache internals are not as expected (another Numba
    version): the notice is then left out, nothing else changes.
    """
    from numba.core.dispatcher import Dispatcher

    folder = None
    for kernel in vars(kernels).values():
        if not isinstance(kernel, Dispatcher) or kernel.targetoptions.get("inline") == "always":
            continue
        cache_file = getattr(getattr(kernel, "_cache", None), "_cache_file", None)
        if cache_file is None:  # cache=False: compiled in every process, nothing to announce once
            continue
        try:
            if cache_file._load_index():
                return None
            folder = str(kernel._cache._cache_path)
        except (AttributeError, OSError):
            return None
    return folder


def _compiled() -> ModuleType | None:
    """The pair-filter kernels, or None without Numba."""
    return load("lagfluid.neighbors._numba")


def available() -> bool:
    """True when the compiled kernels can run (Numba importable)."""
    return _compiled() is not None


_COMPILED_FLOATS = (torch.float32, torch.float64)  # the floating dtypes the Numba kernels are written for


def applies(*tensors: Tensor) -> bool:
    """True when compiled kernels should serve these tensors (the one test :func:`backend_for` makes).

    Numba present; every tensor on the CPU, none needing grad, the floating ones float32 or float64
    (integer and bool tensors: any dtype).
    """
    return (
        all(
            t.device.type == "cpu"
            and not (t.requires_grad and torch.is_grad_enabled())
            and (t.dtype in _COMPILED_FLOATS or not t.dtype.is_floating_point)
            for t in tensors
        )
        and available()
    )


@dataclass(frozen=True)
class Kernel:
    """One computation with two bodies that give the same numbers, bit for bit.

    Attributes:
        name: its key in :data:`KERNELS`.
        compiled: the Numba body (CPU, no autograd); it may hand input it does not take to ``torch``.
        torch: the torch body (any device, autograd, no Numba needed).
        module: the Numba module the compiled body loads (None: this module's pair kernels), which must
            load for the compiled body to serve.
    """

    name: str
    compiled: Callable[..., Any]
    torch: Callable[..., Any]
    module: str | None = None


KERNELS: dict[str, Kernel] = {}
"""Every registered kernel by name (:func:`register`)."""


def register(
    name: str, *, compiled: Callable[..., Any], torch: Callable[..., Any], module: str | None = None
) -> Kernel:
    """Register the two bodies of kernel ``name`` (see :class:`Kernel`); :func:`backend_for` picks one.

    Raises:
        ValueError: ``name`` is already the kernel of another module.
    """
    known = KERNELS.get(name)
    if known is not None and known.torch.__module__ != torch.__module__:
        raise ValueError(f"kernel {name!r} is already registered by {known.torch.__module__}")
    KERNELS[name] = kernel = Kernel(name, compiled, torch, module)
    return kernel


def backend_for(name: str, *tensors: Tensor, compiled: bool = True) -> Callable[..., Any]:
    """The body of kernel ``name`` that serves ``tensors``: the one place where a backend is chosen.

    The compiled body where :func:`applies` to ``tensors`` and its Numba module loads, else the torch body;
    always the torch body with ``compiled=False`` (a caller's own backend option, e.g. a search backend).
    """
    kernel = KERNELS[name]
    if compiled and applies(*tensors) and (kernel.module is None or load(kernel.module) is not None):
        return kernel.compiled
    return kernel.torch


def set_threads() -> None:
    """Give Numba's parallel loops as many threads as torch (``torch.set_num_threads`` is the one knob).

    Numba's OpenMP pool is started here, before a kernel's first parallel loop: started inside that loop it
    set torch's intra-op threads to every core (``threads=1`` ran on 2 after the first neighbour search).
    """
    import numba
    from numba.np.ufunc import parallel

    threads = torch.get_num_threads()
    parallel._launch_threads()  # a no-op once started
    torch.set_num_threads(threads)
    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))


def _kernels() -> ModuleType:
    """The kernel module, with as many threads as torch."""
    kernels = _compiled()
    if kernels is None:
        raise RuntimeError("the compiled pair kernels need numba: pip install numba")
    set_threads()
    return kernels


def numba_threads() -> int:
    """The threads Numba's parallel loops use (as many as torch's, :func:`set_threads`)."""
    import numba

    return int(numba.get_num_threads())


def _as_numpy(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


def pairs_within(
    pos: Tensor,
    edge_lists: Sequence[Tensor],
    radius: float,
    target_masks: Sequence[Tensor | None] | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """The candidate pairs closer than ``radius``, with their geometry, in input order.

    Equal, bit for bit, to ``rel, dist = edge_vectors(pos, edge_index)`` followed by keeping
    ``dist < radius`` (and ``target_mask[edge_index[1]]`` where a mask is given), for each candidate list
    in turn, the results concatenated (written in place: no concatenation pass).

    Args:
        pos: (N, D) CPU positions, float32 or float64.
        edge_lists: candidate lists, each (2, E_k) int64, row 0 = source ``j``, row 1 = target ``i``.
        radius: metres.
        target_masks: per list, None or an (N,) bool mask; pairs into targets where it is False are dropped.

    Returns:
        edge_index: (2, K) the kept pairs; rel: (K, D) ``pos[j] - pos[i]``; dist: (K,) ``|rel|``.
    """
    kern = _kernels()
    p = _as_numpy(pos)
    bound2 = p.dtype.type(_squared_bound(float(radius), pos.dtype))
    masks = list(target_masks) if target_masks is not None else [None] * len(edge_lists)
    parts, total = [], 0
    for edges, target_mask in zip(edge_lists, masks, strict=True):
        src, dst = _as_numpy(edges[0]), _as_numpy(edges[1])
        use_mask = target_mask is not None
        mask = _as_numpy(target_mask) if use_mask else np.ones(1, dtype=np.bool_)
        offsets = kern.count_within(p, src, dst, bound2, mask, use_mask)
        parts.append((src, dst, mask, use_mask, offsets, total))
        total += int(offsets[-1])
    out = np.empty((2, total), dtype=np.int64)
    rel = np.empty((total, p.shape[1]), dtype=p.dtype)
    dist = np.empty(total, dtype=p.dtype)
    for src, dst, mask, use_mask, offsets, start in parts:
        stop = start + int(offsets[-1])
        kern.fill_within(
            p, src, dst, bound2, mask, use_mask, offsets,
            out[0, start:stop], out[1, start:stop], rel[start:stop], dist[start:stop],
        )  # fmt: skip
    # the kernels keep squared distances; the square root is torch's (see _squared_bound)
    return torch.from_numpy(out), torch.from_numpy(rel), torch.from_numpy(dist).sqrt_()


@functools.lru_cache(maxsize=256)
def _squared_bound(radius: float, dtype: torch.dtype) -> float:
    """The squared distance ``b`` with ``d2 < b``  <=>  ``torch.sqrt(d2) < radius`` for every ``d2`` in dtype.

    Why: torch's vectorised CPU ``sqrt`` is not always correctly rounded (AVX-512 build: 0.7 % of float32
    values differ from IEEE ``sqrt`` in the last bit), yet the cut must be torch's ``sqrt(d2) < radius``
    to the bit, as in every other search. So the kernels compare squared distances with the exact
    threshold, found here by asking torch about every ``d2`` within 64 ulp of ``radius^2`` (beyond that no
    sqrt is wrong by enough to cross ``radius``); the kept ``d2`` then get torch's ``sqrt``.

    Raises:
        RuntimeError: torch's sqrt is not monotonic there (never seen; the caller cannot be exact then).
    """
    int_type = {torch.float32: torch.int32, torch.float64: torch.int64}[dtype]
    r = torch.tensor(radius, dtype=dtype)
    steps = torch.arange(-64, 65, dtype=int_type)
    window = ((r * r).view(int_type) + steps).view(dtype)  # consecutive floats around r^2 (all positive)
    inside = torch.sqrt(window) < radius
    first_out = int(torch.argmin(inside.to(torch.uint8)))
    if not (inside[0] and not inside[-1] and bool(inside[:first_out].all()) and not inside[first_out:].any()):
        raise RuntimeError(f"torch.sqrt is not monotonic near radius {radius} ({dtype}): cannot cut exactly")
    return float(window[first_out])


def select_below(
    edge_index: Tensor, rel: Tensor, dist: Tensor, radius: float
) -> tuple[Tensor, Tensor, Tensor]:
    """The edges of a graph with ``dist < radius`` (order kept): ``(edge_index, rel, dist)`` restricted.

    Args:
        edge_index: (2, E) int64 on the CPU.
        rel: (E, D) edge vectors.
        dist: (E,) edge lengths.
        radius: metres.
    """
    kern = _kernels()
    d = _as_numpy(dist)
    bound = d.dtype.type(radius)
    offsets = kern.count_below(d, bound)
    kept = int(offsets[-1])
    out = np.empty((2, kept), dtype=np.int64)
    out_rel = np.empty((kept, rel.shape[1]), dtype=d.dtype)
    out_dist = np.empty(kept, dtype=d.dtype)
    src, dst = _as_numpy(edge_index[0]), _as_numpy(edge_index[1])
    kern.fill_below(d, bound, offsets, src, dst, _as_numpy(rel), out[0], out[1], out_rel, out_dist)
    return torch.from_numpy(out), torch.from_numpy(out_rel), torch.from_numpy(out_dist)


def _select_below_torch(
    edge_index: Tensor, rel: Tensor, dist: Tensor, radius: float
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`select_below` in torch operations: the edges with ``dist < radius``.

    nonzero + index_select rather than boolean indexing: faster on the CPU for (E, 3) arrays.
    """
    index = torch.nonzero(dist < radius).flatten()
    return take_edges(edge_index, index), rel.index_select(0, index), dist.index_select(0, index)


def _pairs_within_torch(
    pos: Tensor,
    edge_lists: Sequence[Tensor],
    radius: float,
    target_masks: Sequence[Tensor | None] | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`pairs_within` in torch operations (any device, differentiable).

    Per candidate list ``(2, E_k)``: its geometry at ``pos`` (N, D), the pairs with ``dist < radius`` (and
    ``target_mask[i]`` where a mask is given), in input order; the lists' results concatenated.
    """
    masks = list(target_masks) if target_masks is not None else [None] * len(edge_lists)
    parts = []
    for edges, target_mask in zip(edge_lists, masks, strict=True):
        rel, dist = edge_vectors(pos, edges)
        keep = dist < radius
        if target_mask is not None:
            keep &= target_mask.index_select(0, edges[1])
        index = torch.nonzero(keep).flatten()
        parts.append((take_edges(edges, index), rel.index_select(0, index), dist.index_select(0, index)))
    if len(parts) == 1:
        return parts[0]
    edges, rel, dist = zip(*parts, strict=True)
    return torch.cat(edges, dim=1), torch.cat(rel), torch.cat(dist)


register("select_below", compiled=select_below, torch=_select_below_torch)
register("pairs_within", compiled=pairs_within, torch=_pairs_within_torch)


def induced_edges(edge_index: Tensor, keep: Tensor, local: Tensor) -> tuple[Tensor, Tensor]:
    """The edges between kept nodes, renumbered, and where they were (order kept): one compiled pass.

    Args:
        edge_index: (2, E) int64 on the CPU.
        keep: (N,) bool, the nodes kept.
        local: (N,) int64, each kept node's new number.

    Returns:
        ``(edge_index (2, K) renumbered by local, positions (K,) of those edges in edge_index)``.
    """
    kern = _kernels()
    src, dst, k = _as_numpy(edge_index[0]), _as_numpy(edge_index[1]), _as_numpy(keep)
    offsets = kern.count_induced(src, dst, k)
    kept = int(offsets[-1])
    out = np.empty((2, kept), dtype=np.int64)
    positions = np.empty(kept, dtype=np.int64)
    kern.fill_induced(src, dst, k, _as_numpy(local), offsets, out[0], out[1], positions)
    return torch.from_numpy(out), torch.from_numpy(positions)


def _induced_edges_torch(edge_index: Tensor, keep: Tensor, local: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`induced_edges` in torch operations (~6 passes over the edges), on any device."""
    positions = torch.nonzero(keep.index_select(0, edge_index[0]) & keep.index_select(0, edge_index[1]))
    positions = positions.flatten()
    sub = local.index_select(0, edge_index.index_select(1, positions).flatten()).view(2, -1)
    return sub, positions


register("induced_edges", compiled=induced_edges, torch=_induced_edges_torch)


# The cell list keeps a dense table of cells: above this many cells per particle (a far-flung particle
# stretching the box) the caller falls back to the k-d tree.
_MAX_CELLS_PER_PARTICLE = 64
# Cells per search radius: edge r/2 scans (5/2)^3 = 15.6 r^3 around a receiver instead of 27 r^3.
_CELLS_PER_RADIUS = 2


class CellList:
    """Particles binned into cubes of edge ``radius / 2`` (+1e-6) for compiled radius queries (CPU).

    Each query scans the 5^3 cells around a particle in parallel and cuts at the exact squared threshold
    of torch's ``sqrt`` (:func:`_squared_bound`), so its pairs are those of every other backend of
    :func:`lagfluid.neighbors.search.radius_graph`. Build with :meth:`build` (None when the particles' box
    holds too many cells for the dense cell table: far-flung particles; use another search then).
    """

    def __init__(self, pos: np.ndarray, cell: np.ndarray, order: np.ndarray, cell_start: np.ndarray,
                 dims: np.ndarray, bound2: np.generic, lo: np.ndarray, edge: float) -> None:  # fmt: skip
        self._args = (pos, cell, order, cell_start, dims, _CELLS_PER_RADIUS)
        self._bound2 = bound2
        self.lo, self.edge = lo, edge  # the grid: particle x is in cell floor((x - lo) / edge)
        self._sorted_pos: np.ndarray | None = None

    @property
    def sorted_pos(self) -> np.ndarray:
        """(N, D) the positions in cell order (row k: particle ``order[k]``), made once: contiguous reads."""
        if self._sorted_pos is None:
            self._sorted_pos = np.ascontiguousarray(self._args[0][self._args[2]])
        return self._sorted_pos

    def cells_of(self, coords: np.ndarray) -> np.ndarray:
        """(Q, 4) int64 cells (graph 0) of the (Q, D) float64 points ``coords`` in this grid (or off it)."""
        cell = np.zeros((coords.shape[0], 4), dtype=np.int64)
        d = coords.shape[1]
        for axis in range(d):
            cell[:, 4 - d + axis] = np.floor((coords[:, axis] - self.lo[axis]) / self.edge).astype(np.int64)
        return cell

    def query_rows(
        self, qpos: np.ndarray, qcell: np.ndarray, visit: np.ndarray, skip: np.ndarray, sort: bool = True
    ) -> QueryRows:
        """Each query's sources within the radius in this list, in one distance pass (no compaction).

        Args:
            qpos: (Q, D) query positions, this list's dtype.
            qcell: (Q, 4) their cells in this grid (:meth:`cells_of`, or this list's own cells).
            visit: (Q,) int64 the order the queries are visited in (any permutation; cell order reads best).
            skip: (Q,) int64 the particle of this list each query never pairs with (itself), or -1.
            sort: each row's sources ascending (else in cell order).
        """
        kern = _kernels()
        pos, _, order, cell_start, dims, reach = self._args
        sizes = np.zeros(qpos.shape[0] + 1, dtype=np.int64)
        kern.query_scan_sizes(qcell, cell_start, dims, reach, sizes)
        slots = np.cumsum(sizes)
        buf = np.empty(int(slots[-1]), dtype=np.int32 if pos.shape[0] < 2**31 else np.int64)
        counts = np.zeros(qpos.shape[0], dtype=np.int64)
        kern.query_fill(
            qpos, qcell, visit, skip, self.sorted_pos, order, cell_start, dims, reach, self._bound2,
            slots[:-1], buf, counts, sort,
        )  # fmt: skip
        return QueryRows(slots[:-1], buf, counts)

    @classmethod
    def build(cls, pos: Tensor, radius: float, batch: Tensor | None = None) -> CellList | None:
        """Bin ``pos`` (N, D), D in {2, 3}, for queries at ``radius``; ``batch``: optional dense graph ids."""
        p = _as_numpy(pos)
        n, d = p.shape
        coords = p.astype(np.float64)
        finite = np.isfinite(coords).all(axis=1)
        if not finite.all():  # the cell indices below would be garbage (the kernels do not bound-check)
            bad = int(np.flatnonzero(~finite)[0])
            raise ValueError(f"positions must be finite: particle {bad} is at {p[bad].tolist()}")
        lo = coords.min(axis=0) if n else np.zeros(d)
        edge = float(radius) * (1.0 + 1e-6) / _CELLS_PER_RADIUS  # a pair within radius is <= 2 cells apart
        cell = np.zeros((n, 4), dtype=np.int64)
        dims = np.ones(4, dtype=np.int64)
        # The last axis varies fastest in the cell key, as in the scenes' particle numbering (lattices from
        # meshgrid(indexing="ij")): key order then follows particle order, and each receiver's sources come
        # out of the scan nearly sorted (cheaper to sort: _sort_nearly_sorted).
        for axis in range(d):
            col = 4 - d + axis
            cell[:, col] = np.floor((coords[:, axis] - lo[axis]) / edge).astype(np.int64)
            dims[col] = int(cell[:, col].max()) + 1 if n else 1
        if batch is not None:
            cell[:, 0] = _as_numpy(batch).astype(np.int64)
            dims[0] = int(cell[:, 0].max()) + 1 if n else 1
        total = float(np.prod(dims.astype(np.float64)))
        if total > _MAX_CELLS_PER_PARTICLE * max(n, 1024):
            return None
        keys = ((cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]) * dims[3] + cell[:, 3]
        order = np.argsort(keys, kind="stable")
        cell_start = np.zeros(int(total) + 1, dtype=np.int64)
        np.cumsum(np.bincount(keys, minlength=int(total)), out=cell_start[1:])
        bound2 = p.dtype.type(_squared_bound(float(radius), pos.dtype))
        return cls(p, cell, order, cell_start, dims, bound2, lo, edge)

    def pairs(self, receivers: Tensor) -> Tensor:
        """(2, E) int64 edge index [j; i]: every j != i (same graph) within the radius of each receiver i.

        ``receivers``: (R,) int64 ascending; the edges come sorted by target, then source.
        """
        kern = _kernels()
        recv = _as_numpy(receivers).astype(np.int64)
        pos, cell, _, cell_start, dims, reach = self._args
        # One distance pass: each receiver gets room for every particle of its scanned cells (~3.5x its
        # pairs), then the kept pairs are packed; cheaper than counting first (neighbors_notes.md).
        sizes = np.zeros(recv.shape[0] + 1, dtype=np.int64)
        kern.cell_scan_sizes(cell, cell_start, dims, reach, recv, sizes)
        slots = np.cumsum(sizes)
        buf = np.empty(int(slots[-1]), dtype=np.int32 if pos.shape[0] < 2**31 else np.int64)
        counts = np.zeros(recv.shape[0] + 1, dtype=np.int64)
        kern.cell_search_fill(*self._args, recv, self._bound2, slots, buf, counts)
        offsets = np.cumsum(counts)
        out = np.empty((2, int(offsets[-1])), dtype=np.int64)
        kern.cell_search_compact(recv, slots, buf, offsets, out[1], out[0])
        return torch.from_numpy(out)

    def any_within(self, queries: Tensor, targets: Tensor) -> Tensor:
        """(Q,) bool: whether some other particle with ``targets`` True lies within the radius of each query.

        Args:
            queries: (Q,) int64 particle indices.
            targets: (N,) bool.
        """
        kern = _kernels()
        q = _as_numpy(queries).astype(np.int64)
        out = np.zeros(q.shape[0], dtype=np.bool_)
        kern.cell_any_within(*self._args, q, _as_numpy(targets), self._bound2, out)
        return torch.from_numpy(out)


def cell_search(pos: Tensor, radius: float, batch: Tensor | None, receivers: Tensor) -> Tensor | None:
    """Every pair (i receiver, j any particle, i != j, same graph) with torch's ``|x_j - x_i| < radius``.

    The ``numba`` backend of :func:`lagfluid.neighbors.search.radius_graph` (see :class:`CellList`).

    Args:
        pos: (N, D) CPU positions, D in {2, 3}.
        radius: metres.
        batch: optional (N,) dense graph ids 0..B-1.
        receivers: (R,) int64 receiver indices, ascending.

    Returns:
        (2, E) int64 edge index [j; i] sorted by target, then source; None when the particles' box holds too
        many cells for a dense cell table.
    """
    cells = CellList.build(pos, radius, batch)
    return None if cells is None else cells.pairs(receivers)


def cross_search(sources: Tensor, targets: Tensor, radius: float) -> Tensor | None:
    """Every pair (j source, i target) with torch's ``|s_j - t_i| < radius``: one point set into another.

    The ``numba`` backend of :func:`lagfluid.neighbors.search.radius_graph_between`: a cell list over the
    sources only, queried at the targets (in their cell order), so no target-target pair is ever scanned.
    The same cut (:func:`_squared_bound`) and squared distance as :func:`cell_search` (the difference's
    sign aside, which its square does not see), hence the same pairs.

    Args:
        sources: (S, D) CPU positions, D in {2, 3}, finite.
        targets: (T, D) finite positions of the same dtype.
        radius: metres.

    Returns:
        (2, E) int64 edge index [j; i] (j a source row, i a target row) sorted by target, then source; None
        when the sources' box holds too many cells for a dense cell table.
    """
    cells = CellList.build(sources, radius)
    if cells is None:
        return None
    q = _as_numpy(targets)
    qcell = cells.cells_of(q.astype(np.float64))
    dims = cells._args[4]
    inside = np.clip(qcell, 0, dims - 1)  # a query off the grid scans nothing; any order visits it
    visit = np.argsort(((inside[:, 1] * dims[2] + inside[:, 2]) * dims[3]) + inside[:, 3], kind="stable")
    rows = cells.query_rows(q, qcell, visit, np.full(q.shape[0], -1, dtype=np.int64))
    starts = np.zeros(q.shape[0] + 1, dtype=np.int64)
    np.cumsum(rows.counts, out=starts[1:])
    out = np.empty((2, int(starts[-1])), dtype=np.int64)
    _kernels().fluid_rows(rows.slots, rows.buf, rows.counts, 0, starts[:-1], out[1], out[0])
    return torch.from_numpy(out)


# ------------------------------------------------------------------------- the Verlet list's split search
@dataclass(frozen=True)
class QueryRows:
    """Each query's sources, sorted, uncompacted: query r's are ``buf[slots[r]:slots[r] + counts[r]]``."""

    slots: np.ndarray
    buf: np.ndarray
    counts: np.ndarray


@dataclass
class StaticBoundary:
    """The boundary rows (N - n_fluid of them, after the fluid) indexed once per scene: walls never move.

    Holds the boundary's cell list and every wall's candidate boundary sources (the wall-wall and
    wall-dummy pairs within the radius), as CSR rows over the walls, so a rebuild of the Verlet list only
    searches the fluid (:func:`verlet_candidates`). Valid only for the very boundary it was built from:
    :meth:`matches` compares positions and wall flags exactly (one read of the boundary per rebuild).

    Attributes:
        n_fluid: the rows before the boundary.
        boundary: (B, D) the boundary positions it was built from; walls: (B,) bool, which are walls.
        radius: the search radius, m.
        cells: the boundary's cell list (local indices 0..B-1).
        wall_local: (W,) int64 local index of each wall, ascending; wall_row: (B,) its row, -1 for non-walls.
        ptr, src: (W + 1,) int64 and (E_wb,) the walls' boundary sources (local), sorted, as CSR rows.
    """

    n_fluid: int
    boundary: np.ndarray
    walls: np.ndarray
    radius: float
    cells: CellList
    wall_local: np.ndarray
    wall_row: np.ndarray
    ptr: np.ndarray
    src: np.ndarray
    _hops: tuple[float, np.ndarray, np.ndarray, np.ndarray] | None = None

    def hop_rows(self, cutoff: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The walls' static sources closer than ``cutoff`` (the hops between walls), made once per cutoff.

        Returns:
            ptr (W + 1,) int64 and src (local, int64) as CSR rows over the walls, in the rows' order, and
            (W,) float64 each row's shortest such distance (inf for none), as the compiled filter computes it.
        """
        if self._hops is None or self._hops[0] != cutoff:
            counts = np.diff(self.ptr)
            edges = np.stack([self.src.astype(np.int64), np.repeat(self.wall_local, counts)])
            kept, _, dist = pairs_within(torch.from_numpy(self.boundary), [torch.from_numpy(edges)], cutoff)
            rows = torch.from_numpy(self.wall_row)[kept[1]]
            ptr = np.zeros(self.ptr.shape[0], dtype=np.int64)
            np.cumsum(np.bincount(rows.numpy(), minlength=ptr.shape[0] - 1), out=ptr[1:])
            closest = torch.full((ptr.shape[0] - 1,), math.inf, dtype=torch.float64)
            closest.scatter_reduce_(0, rows, dist.double(), "amin")
            self._hops = (cutoff, ptr, kept[0].numpy(), closest.numpy())
        return self._hops[1], self._hops[2], self._hops[3]

    @classmethod
    def build(cls, pos: Tensor, walls: Tensor, n_fluid: int, radius: float) -> StaticBoundary | None:
        """Index the boundary rows ``pos[n_fluid:]`` (N, D) with wall flags ``walls[n_fluid:]`` (N,) bool.

        None when the boundary's box holds too many cells for a dense cell table (then search another way).
        """
        boundary = _as_numpy(pos[n_fluid:]).copy()
        is_wall = _as_numpy(walls[n_fluid:]).copy()
        cells = CellList.build(torch.from_numpy(boundary), radius)
        if cells is None:
            return None
        wall_local = np.flatnonzero(is_wall).astype(np.int64)
        wall_row = np.full(boundary.shape[0], -1, dtype=np.int64)
        wall_row[wall_local] = np.arange(wall_local.shape[0])
        own = cells._args[1]
        visit = np.arange(wall_local.shape[0], dtype=np.int64)
        wall_pos = np.ascontiguousarray(boundary[wall_local])
        rows = cells.query_rows(wall_pos, own[wall_local], visit, wall_local)
        ptr = np.zeros(wall_local.shape[0] + 1, dtype=np.int64)
        np.cumsum(rows.counts, out=ptr[1:])
        src = np.empty(int(ptr[-1]), dtype=rows.buf.dtype)
        _kernels().compact_rows(rows.slots, rows.counts, rows.buf, ptr, src)
        return cls(n_fluid, boundary, is_wall, float(radius), cells, wall_local, wall_row, ptr, src)

    def matches(self, pos: Tensor, walls: Tensor, n_fluid: int, radius: float) -> bool:
        """True when ``pos[n_fluid:]`` and ``walls[n_fluid:]`` are exactly this boundary, at this radius."""
        if n_fluid != self.n_fluid or radius != self.radius:
            return False
        if pos.shape[0] - n_fluid != self.boundary.shape[0]:
            return False
        if _as_numpy(pos[:1]).dtype != self.boundary.dtype:
            return False
        same_pos = np.array_equal(_as_numpy(pos[n_fluid:]), self.boundary)
        return bool(same_pos and np.array_equal(_as_numpy(walls[n_fluid:]), self.walls))


@dataclass(frozen=True)
class WallLayout:
    """Where the wall rows of :func:`verlet_candidates` lie in its candidates after the fluid rows.

    Attributes:
        targets: (T,) int64 the wall targets (local boundary indices, ascending); rows: their static rows.
        from_fluid: (T,) int64 how many fluid sources each has (the first pairs of its row).
        starts: (T,) int64 where each row starts, counted from the first wall row.
    """

    targets: np.ndarray
    rows: np.ndarray
    from_fluid: np.ndarray
    starts: np.ndarray

    def dynamic(self) -> np.ndarray:
        """(E_d,) int64 where (from the first wall row) the pairs with a fluid source lie, ascending."""
        return _ranges(self.starts, self.from_fluid)


def _ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """``concatenate([arange(s, s + c) for s, c in zip(starts, counts)])`` without a Python loop."""
    total = int(counts.sum())
    shift = np.repeat(starts - (np.cumsum(counts) - counts), counts)
    return shift + np.arange(total, dtype=np.int64)


def verlet_candidates(
    pos: Tensor, static: StaticBoundary, wall_hops: int | None
) -> tuple[Tensor, int, WallLayout] | None:
    """The Verlet list's candidates (2, E) at ``pos`` (N, D), searching only the fluid (rows < n_fluid).

    The same pairs in the same order as one cell list over every particle with receivers the fluid and the
    walls within ``wall_hops`` hops of it (``VerletNeighborList._search_with_cells``): rows by target, the
    fluid first, each row's sources ascending. Each fluid row is its fluid sources (a search of the fluid's
    cell list) then its boundary sources (a search of the static boundary's); a wall row is its fluid sources
    (those rows transposed) then its static boundary sources (``static``). The cut is the same squared bound,
    the distance the same operations with the difference negated (its square is the same number).

    Returns:
        (candidates, how many of them are pairs into the fluid, where the wall rows lie), or None when the
        fluid's box holds too many cells for a dense cell table.
    """
    kern = _kernels()
    nf, nb = static.n_fluid, static.boundary.shape[0]
    fcells = CellList.build(pos[:nf], static.radius)
    if fcells is None:
        return None
    fpos, fcell, visit = fcells._args[0], fcells._args[1], fcells._args[2]  # visit: the fluid in cell order
    # unsorted: the fluid-fluid relation is symmetric, so its rows come sorted by a transpose (below)
    ff = fcells.query_rows(fpos, fcell, visit, np.arange(nf, dtype=np.int64), sort=False)
    fcell_b = static.cells.cells_of(fpos.astype(np.float64))
    fb = static.cells.query_rows(fpos, fcell_b, visit, np.full(nf, -1, dtype=np.int64))
    from_fluid = kern.column_counts(fb.slots, fb.counts, fb.buf, nb)  # (B,) fluid sources per boundary row
    if wall_hops is None:
        near = static.walls.copy()
    else:  # walls with fluid within the radius, then walls within the radius of those (static rows)
        near = (from_fluid > 0) & static.walls
        frontier = near.copy()
        for _ in range(wall_hops - 1):
            if not frontier.any():
                break
            reached = np.zeros(nb, dtype=np.bool_)
            kern.near_wall_hop(static.wall_local, static.ptr, static.src, near, frontier, reached)
            frontier = reached
            near |= frontier
    targets = np.flatnonzero(near).astype(np.int64)  # local boundary indices, ascending
    rows = static.wall_row[targets]
    wf_counts = from_fluid[targets]
    w_sizes = wf_counts + (static.ptr[rows + 1] - static.ptr[rows])
    f_off = np.zeros(nf + 1, dtype=np.int64)
    np.cumsum(ff.counts + fb.counts, out=f_off[1:])
    prefix = int(f_off[-1])
    w_off = np.empty(targets.shape[0] + 1, dtype=np.int64)
    w_off[0] = prefix
    np.cumsum(w_sizes, out=w_off[1:])
    w_off[1:] += prefix
    out = np.empty((2, int(w_off[-1])), dtype=np.int64)
    chunks = max(1, min(numba_threads(), nf))
    hist = np.zeros((chunks, nf), dtype=np.int64)
    kern.symmetric_histogram(ff.slots, ff.counts, ff.buf, chunks, hist)
    cursor = np.cumsum(hist, axis=0) - hist + f_off[:-1]  # where chunk c's entries of row i start
    kern.symmetric_transpose(ff.slots, ff.counts, ff.buf, chunks, cursor, out[1], out[0])
    kern.fluid_rows(fb.slots, fb.buf, fb.counts, nf, f_off[:-1] + ff.counts, out[1], out[0])
    cursor = np.full(nb, -1, dtype=np.int64)
    cursor[targets] = w_off[:-1]
    kern.wall_rows_from_fluid(fb.slots, fb.buf, fb.counts, nf, cursor, out[1], out[0])
    kern.wall_rows_static(targets, rows, static.ptr, static.src, nf, w_off[:-1] + wf_counts, out[1], out[0])
    return torch.from_numpy(out), prefix, WallLayout(targets, rows, wf_counts, w_off[:-1] - prefix)
