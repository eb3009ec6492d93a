"""Radius graphs over particles: every ordered pair closer than ``r``, exactly, on any device.

Every operator of the split-step scheme is a sum over the neighbours ``j`` of a particle ``i`` within
some radius ``r_e`` (a multiple of ``l0``). This module finds those pairs once, exactly, on any
device (:mod:`lagfluid.neighbors.csr` turns kernel weights on them into a CSR matrix, so that the
neighbour sums become one sparse matrix product).

Conventions (shared with PyG, ``flow="source_to_target"``):

* ``edge_index[0] = j`` is the source (the neighbour), ``edge_index[1] = i`` the target (the centre),
  so ``rel = pos[j] - pos[i]`` is ``x_j - x_i``.
* A pair is an edge when ``|x_j - x_i| < r`` (strict), measured by one formula in the input dtype
  (:func:`lagfluid.neighbors.geometry.distance`), whichever backend found the candidates. Every backend
  searches a slightly larger radius and then applies that formula, so all backends return *exactly* the
  same edges. (The CPU filter of the Verlet list, :mod:`lagfluid.neighbors.pair_kernels`, reaches the same
  cut from squared distances at the exact threshold of torch's ``sqrt``.)
* Edges are sorted by target, then source: ready for CSR, and deterministic, so backends can be
  compared edge for edge.
* The search never truncates silently: with ``max_num_neighbors`` it raises
  :class:`NeighborOverflowError`; without it, every neighbour is returned.

Backends: ``"numba"`` (compiled parallel cell list, CPU default;
:func:`lagfluid.neighbors.pair_kernels.cell_search`), ``"scipy"`` (k-d tree, the CPU default without
Numba), ``"torch_cluster"`` (optional compiled extension, CUDA default when installed), ``"cell_list"``
(pure torch cell list, any device), ``"brute"`` (chunked all-pairs, the reference for tests). The
compiled cell list is the CPU default because it is the fastest there (see
``benchmarks/results/neighbors_notes.md``).
"""

from __future__ import annotations

import functools
import importlib
import itertools
import logging
import math
from types import ModuleType

import numpy as np
import torch
from torch import Tensor

from lagfluid.neighbors import pair_kernels
from lagfluid.neighbors.geometry import distance

__all__ = ["BACKENDS", "NeighborOverflowError", "available_backends", "radius_graph", "restrict_radius"]

log = logging.getLogger(__name__)

BACKENDS: tuple[str, ...] = ("numba", "scipy", "torch_cluster", "cell_list", "brute")
"""Every backend name :func:`radius_graph` knows (``"auto"`` picks one per device)."""

# Candidate pairs handled at once by the cell list and the brute-force search. Each candidate costs
# about six int64/float temporaries, so 2**21 candidates keep the peak near 100 MB on any device.
_CHUNK_PAIRS = 1 << 21

# torch_cluster.radius keeps at most ``max_num_neighbors`` neighbours per query point. Without a user
# cap we start here (the degree at 3.1 l0 is ~122, at 4 l0 ~268) and redo saturated centres exactly.
_TORCH_CLUSTER_DEFAULT_CAP = 256

# Particles per cell of edge r above which the cell list splits cells into 2 (3) per radius.
_CELL_SPLIT = (8.0, 27.0)


class NeighborOverflowError(ValueError):
    """A particle has more neighbours than ``max_num_neighbors`` allows.

    Attributes:
        node: index of the first particle over the cap.
        count: its number of neighbours (incoming edges, its self loop included when ``loop=True``).
        cap: the ``max_num_neighbors`` that was exceeded.
        num_over: how many particles exceed the cap.
    """

    def __init__(self, node: int, count: int, cap: int, num_over: int, radius: float) -> None:
        self.node, self.count, self.cap, self.num_over = node, count, cap, num_over
        super().__init__(
            f"particle {node} has {count} neighbours within r={radius:g}, more than "
            f"max_num_neighbors={cap} ({num_over} particle(s) over the cap); raise the cap or check "
            "the scene for clustered particles (the search never truncates silently)"
        )


# ---------------------------------------------------------------------------------------------- helpers
@functools.cache
def _import_torch_cluster() -> ModuleType | None:
    """The ``torch_cluster`` module, or None when it is not installed (imported once, lazily).

    It is optional because it compiles from source (slowly) on machines without a matching wheel.
    """
    try:
        return importlib.import_module("torch_cluster")
    except (ImportError, OSError) as err:  # OSError: a wheel built against another torch ABI
        log.debug("torch_cluster unavailable: %s", err)
        return None


def available_backends() -> tuple[str, ...]:
    """Backends usable in this environment, in the order of :data:`BACKENDS`."""
    missing = {"torch_cluster": _import_torch_cluster() is None, "numba": not pair_kernels.available()}
    return tuple(b for b in BACKENDS if not missing.get(b, False))


def _candidate_radius(r: float, dtype: torch.dtype) -> float:
    """Search radius that surely contains every pair with ``distance(...) < r`` in ``dtype``.

    ``distance`` in float32 differs from the exact distance by a few ulp, and ``r`` itself is rounded
    to ``dtype`` in ``dist < r``; 1e-4 relative covers both with a wide margin (it adds ~3e-4 of the
    candidates), and 16 eps covers half precision.
    """
    return r * (1.0 + max(1e-4, 16.0 * torch.finfo(dtype).eps))


def _exact_pairs(pos: Tensor, i: Tensor, j: Tensor, r: float) -> tuple[Tensor, Tensor]:
    """Keep the candidate pairs with ``i != j`` and ``distance(pos[j] - pos[i]) < r``."""
    keep = (i != j) & (distance(pos[j] - pos[i]) < r)
    return i[keep], j[keep]


def _sort_pairs(i: Tensor, j: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """Sort pairs by ``i`` then ``j`` (both (E,) int64, values in [0, n))."""
    if i.numel() == 0:
        return i, j
    shift = n <= 2**31
    key = (i << 32) | j if shift else i * n + j
    if key.device.type == "cpu":
        # numpy's SIMD sort beats torch.sort on the CPU (see benchmarks/results/neighbors_notes.md).
        key = torch.from_numpy(np.sort(key.numpy()))
    else:
        key = torch.sort(key).values
    if shift:
        return key >> 32, key & 0xFFFFFFFF
    return torch.div(key, n, rounding_mode="floor"), key % n


# ---------------------------------------------------------------------------------------------- validation
def _check_radius(r: object, name: str = "r") -> float:
    if isinstance(r, bool):
        raise ValueError(f"{name} must be a positive finite number, got {r!r}")
    try:
        value = float(r)  # type: ignore[arg-type]
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(f"{name} must be a positive finite number, got {r!r}") from None
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} must be a positive finite number, got {r!r}")
    return value


def _check_inputs(
    pos: object,
    r: object,
    batch: Tensor | None,
    receivers: Tensor | None,
    backend: str,
    max_num_neighbors: int | None,
) -> tuple[float, str]:
    """Validate the arguments of :func:`radius_graph`; returns (radius, resolved backend)."""
    if not isinstance(pos, Tensor):
        raise ValueError(f"pos must be a torch.Tensor of shape (N, 3) or (N, 2), got {type(pos).__name__}")
    if pos.dim() != 2 or pos.shape[1] not in (2, 3):
        raise ValueError(f"pos must have shape (N, 3) or (N, 2), got {tuple(pos.shape)}")
    if not pos.is_floating_point():
        raise ValueError(f"pos must be floating point, got dtype {pos.dtype}")
    radius = _check_radius(r)
    n = pos.shape[0]
    if n:
        finite = torch.isfinite(pos).all(dim=1)
        if not bool(finite.all()):
            bad = int(torch.nonzero(~finite)[0, 0])
            raise ValueError(f"pos of particle {bad} is not finite: {pos[bad].tolist()}")
    for name, t in (("batch", batch), ("receivers", receivers)):
        if t is None:
            continue
        if not isinstance(t, Tensor) or t.dim() != 1 or t.shape[0] != n:
            shape = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"{name} must be a 1-D tensor of length N={n}, got {shape}")
        if t.device != pos.device:
            raise ValueError(f"{name} is on {t.device} but pos is on {pos.device}")
    if batch is not None and (batch.is_floating_point() or batch.is_complex() or batch.dtype == torch.bool):
        raise ValueError(f"batch must be an integer tensor of graph ids, got dtype {batch.dtype}")
    if receivers is not None and receivers.dtype != torch.bool:
        raise ValueError(f"receivers must be a bool mask, got dtype {receivers.dtype}")
    if max_num_neighbors is not None and (
        isinstance(max_num_neighbors, bool) or not isinstance(max_num_neighbors, int) or max_num_neighbors < 0
    ):
        raise ValueError(f"max_num_neighbors must be None or an int >= 0, got {max_num_neighbors!r}")
    return radius, _resolve_backend(backend, pos.device)


def _resolve_backend(backend: str, device: torch.device) -> str:
    if backend == "auto":
        if device.type == "cpu":
            return "numba" if "numba" in available_backends() else "scipy"
        return "torch_cluster" if _import_torch_cluster() is not None else "cell_list"
    if backend not in BACKENDS:
        raise ValueError(
            f"unknown neighbour-search backend {backend!r}; available: "
            f"{', '.join(('auto', *available_backends()))}"
        )
    if backend == "numba" and (device.type != "cpu" or "numba" not in available_backends()):
        raise ValueError(
            f"backend 'numba' runs on the CPU with numba installed (positions on {device}); available: "
            f"{', '.join(('auto', *available_backends()))}"
        )
    if backend == "torch_cluster" and _import_torch_cluster() is None:
        raise ValueError(
            "backend 'torch_cluster' is not available (torch_cluster is not installed; "
            "`pip install lagfluid[cluster]`); available: "
            f"{', '.join(('auto', *available_backends()))}"
        )
    return backend


# ---------------------------------------------------------------------------------------------- backends
# Each backend returns the exact pairs (i target, j source) with i a receiver, i != j, same graph and
# distance < r, in any order; radius_graph adds self loops, sorts and checks the cap.


def _search_brute(pos: Tensor, r: float, batch: Tensor | None, recv: Tensor) -> tuple[Tensor, Tensor]:
    """All pairs, ``chunk`` centres at a time: O(M N) time, O(_CHUNK_PAIRS) memory."""
    n = pos.shape[0]
    cols = pos.t().contiguous()  # (D, N): one coordinate per row, for broadcasting
    chunk = max(1, _CHUNK_PAIRS // max(n, 1))
    out_i, out_j = [], []
    for start in range(0, recv.numel(), chunk):
        centre = recv[start : start + chunk]
        # Same operation sequence as distance(pos[j] - pos[i]), so the results are bit-identical.
        rel = torch.stack([cols[k][None, :] - cols[k][centre, None] for k in range(pos.shape[1])], dim=-1)
        mask = distance(rel) < r
        mask[torch.arange(centre.numel(), device=pos.device), centre] = False
        if batch is not None:
            mask &= batch[centre, None] == batch[None, :]
        row, col = torch.nonzero(mask, as_tuple=True)
        out_i.append(centre[row])
        out_j.append(col)
    return torch.cat(out_i), torch.cat(out_j)


def _search_scipy(
    pos: Tensor, r: float, batch: Tensor | None, recv_mask: Tensor | None
) -> tuple[Tensor, Tensor]:
    """k-d tree search on the CPU (any input device; the result goes back to ``pos.device``).

    ``cKDTree.query_pairs(output_type="ndarray")`` lists each unordered pair once and returns one
    array without Python objects; it is the fastest of SciPy's queries (see
    ``benchmarks/results/neighbors_notes.md``). So pairs among receivers come from query_pairs (half the
    distance work, then mirrored); only receiver <- non-receiver pairs need sparse_distance_matrix
    between two trees, and that touches only the boundary layer next to the receivers. Non-receiver
    centres are never searched.
    """
    from scipy.spatial import cKDTree  # scipy is a dependency, imported here to keep import time low

    device = pos.device
    pos_cpu = pos.detach().cpu()
    r_c = _candidate_radius(r, pos.dtype)
    pts = pos_cpu.double().numpy()
    if batch is not None:
        # One extra coordinate 2 r_c * graph id: pairs from different graphs are >= 2 r_c apart, pairs
        # within one graph keep their distance (the extra difference is exactly 0). Exact batching.
        pts = np.concatenate([pts, (batch.cpu().double().numpy() * (2.0 * r_c))[:, None]], axis=1)
    if recv_mask is None:
        recv, others = None, None
        recv_tree = cKDTree(pts)
    else:
        mask = recv_mask.cpu().numpy()
        recv, others = np.flatnonzero(mask), np.flatnonzero(~mask)
        recv_tree = cKDTree(pts[recv])

    pairs = torch.from_numpy(recv_tree.query_pairs(r_c, output_type="ndarray"))
    if recv is not None:
        pairs = torch.from_numpy(recv)[pairs]
    # The distance is symmetric bit for bit (rel only changes sign), so filter once, then mirror.
    a, b = _exact_pairs(pos_cpu, pairs[:, 0], pairs[:, 1], r)
    parts_i, parts_j = [a, b], [b, a]
    if others is not None and others.size:
        cross = recv_tree.sparse_distance_matrix(cKDTree(pts[others]), r_c, output_type="ndarray")
        ci = torch.from_numpy(recv[cross["i"]])
        cj = torch.from_numpy(others[cross["j"]])
        ci, cj = _exact_pairs(pos_cpu, ci, cj, r)
        parts_i.append(ci)
        parts_j.append(cj)
    return torch.cat(parts_i).to(device), torch.cat(parts_j).to(device)


def _compress_axis(c: Tensor, n: int) -> Tensor:
    """Renumber integer cell coordinates so that gaps wider than ``n + 1`` cells shrink to ``n + 1``.

    Cells at most ``n`` apart keep their distance, farther ones stay farther than ``n``: the cells a
    particle visits are unchanged, only the empty space between clusters disappears.
    """
    uniq, inverse = torch.unique(c, return_inverse=True)
    step = torch.diff(uniq).clamp(max=n + 1)
    rank = torch.cat([step.new_zeros(1), torch.cumsum(step, 0)])
    return rank[inverse]


def _cell_rows(dim: int, n: int) -> Tensor:
    """Rows of neighbour cells to visit when cells are ``r / n`` wide, as (R, dim + 1) int64.

    A row is ``(a, zlo, zhi)`` (2-D) or ``(a, b, zlo, zhi)`` (3-D): the cells at offset ``a`` (and ``b``)
    across and ``zlo..zhi`` along the last axis. Cells along the last axis are consecutive in key
    order, so one row is one contiguous run of the particles sorted by key: two binary searches
    instead of one per cell. Rows and cells that cannot hold a point closer than ``r`` (their closest
    corner is ``(|offset| - 1) r / n`` away per axis) are left out.
    """
    rows = []
    span = range(-n, n + 1)
    for across in itertools.product(span, repeat=dim - 1):
        gap = sum(max(abs(o) - 1, 0) ** 2 for o in across)
        along = [o for o in span if gap + max(abs(o) - 1, 0) ** 2 < n * n]
        if along:
            rows.append([*across, min(along), max(along)])
    return torch.tensor(rows, dtype=torch.long)


def _search_cell_list(
    pos: Tensor, r: float, batch: Tensor | None, recv: Tensor, cells_per_radius: int | None = None
) -> tuple[Tensor, Tensor]:
    """Cell list (spatial hashing) in pure torch: runs on any device, no Python loop over particles.

    Particles are binned into cubic cells of edge ``r_c / n`` (``r_c`` slightly above ``r``) and sorted
    by cell key, last axis fastest. Every pair within ``r`` lies within ``n`` cells per axis; those
    cells form at most (2n+1)^(D-1) contiguous runs of the sorted particles (see :func:`_cell_rows`),
    found by binary search. Candidate pairs are then expanded and filtered in chunks of at most
    ``_CHUNK_PAIRS`` (memory-bounded). Candidates per edge: 6.4 (n=1), 3.7 (n=2), 2.8 (n=3); smaller
    cells cost more binary searches, so ``n`` grows with the particles per cell.

    Args:
        pos: (N, D) positions.
        r: radius.
        batch: (N,) dense graph ids or None.
        recv: (M,) receiver indices, ascending.
        cells_per_radius: ``n``; by default 1 when a cell of edge ``r`` holds few particles, up to 3.
    """
    device, n_pts, dim = pos.device, pos.shape[0], pos.shape[1]
    pos = pos.detach()
    r_c = _candidate_radius(r, pos.dtype)
    # float64 cell coordinates: binning errors of float32 positions cannot move a particle by a cell.
    p64 = pos.double()
    lo_corner = p64.min(dim=0).values
    n_graphs = int(batch.max()) + 1 if batch is not None else 1
    if cells_per_radius is None:
        # Smaller cells mean fewer candidates but more binary searches; what decides is how many
        # particles share a cell of edge r_c with a typical particle (sum of squared occupancies / N).
        coarse = torch.floor((p64 - lo_corner) / r_c).long()
        spread = coarse[:, 0] * 73856093  # spatial hash; a rare collision only nudges the estimate
        for k in range(1, dim):
            spread = spread ^ (coarse[:, k] * (19349663 if k == 1 else 83492791))
        occupancy = torch.unique(spread, return_counts=True)[1].double()
        per_cell = float((occupancy * occupancy).sum()) / n_pts
        cells_per_radius = 1 if per_cell < _CELL_SPLIT[0] else 2 if per_cell < _CELL_SPLIT[1] else 3
    n = cells_per_radius
    h = r_c / n
    # Margin of n cells on every side so that every visited cell has coordinates in [0, extent).
    cell = torch.floor((p64 - lo_corner) / h).long() + n
    extent = cell.max(dim=0).values + n + 1
    if math.prod(extent.tolist()) * n_graphs >= 2**62:
        # Far-flung particles (e.g. one that escaped): drop empty gaps so the keys fit into int64.
        cell = torch.stack([_compress_axis(cell[:, k], n) for k in range(dim)], dim=1) + n
        extent = cell.max(dim=0).values + n + 1
        if math.prod(extent.tolist()) * n_graphs >= 2**62:
            raise ValueError(
                f"cell_list: {n_pts} particles span too many cells of size {h:g} for int64 keys; "
                "use backend='scipy' or 'brute'"
            )
    strides = torch.ones(dim, dtype=torch.long, device=device)
    for k in range(dim - 2, -1, -1):
        strides[k] = strides[k + 1] * extent[k + 1]
    key = (cell * strides).sum(dim=1)
    if batch is not None:
        key = key + batch * int(torch.prod(extent))
    order = torch.argsort(key)
    sorted_key = key[order]
    sorted_pos = pos[order]  # gathers of sources below then read nearby memory

    rows = _cell_rows(dim, n).to(device)
    across = (rows[:, : dim - 1] * strides[: dim - 1]).sum(dim=1)
    first = torch.searchsorted(sorted_key, key[recv, None] + (across + rows[:, -2])[None, :])  # (M, R)
    last = torch.searchsorted(sorted_key, key[recv, None] + (across + rows[:, -1])[None, :], right=True)
    cand_count = last - first
    n_rows = rows.shape[0]
    per_centre = torch.cumsum(cand_count.sum(dim=1), 0)  # (M,) cumulative candidates
    centre_pos = pos[recv]

    out_i, out_j = [], []
    m, done, lo = recv.numel(), 0, 0
    while lo < m:
        # Largest run of centres whose candidates fit into one chunk (at least one centre).
        hi = int(torch.searchsorted(per_centre, done + _CHUNK_PAIRS, right=True))
        hi = min(max(hi, lo + 1), m)
        total = int(per_centre[hi - 1]) - done
        cnt = cand_count[lo:hi].reshape(-1)
        seg = torch.repeat_interleave(torch.arange(cnt.numel(), device=device), cnt, output_size=total)
        # Index of each candidate in key order: its run's first index + its rank within the run.
        src = (
            torch.arange(total, device=device)
            + (first[lo:hi].reshape(-1) - (torch.cumsum(cnt, 0) - cnt))[seg]
        )
        centre = lo + torch.div(seg, n_rows, rounding_mode="floor")
        # Same operations as _exact_pairs: bit-identical distances (sorted_pos[k] is pos[order[k]]).
        keep = distance(sorted_pos[src] - centre_pos[centre]) < r
        src, centre = src[keep], centre[keep]
        i, j = recv[centre], order[src]
        keep = i != j
        out_i.append(i[keep])
        out_j.append(j[keep])
        done += total
        lo = hi
    log.debug("cell_list: n=%d, %d candidates for %d centres", n, done, m)
    return torch.cat(out_i), torch.cat(out_j)


def _search_torch_cluster(
    pos: Tensor, r: float, batch: Tensor | None, recv: Tensor, max_num_neighbors: int | None
) -> tuple[Tensor, Tensor]:
    """``torch_cluster.radius`` with its per-centre cap made safe.

    torch_cluster keeps at most ``max_num_neighbors`` neighbours per centre and drops the rest
    silently. We call it with a cap and treat every centre that *reached* the cap as possibly
    truncated: those centres are searched again, exactly, with the cell list. The answer is therefore
    complete whatever the cap; the cap only decides how much work goes to the fallback.
    """
    tc = _import_torch_cluster()
    assert tc is not None  # _resolve_backend checked it
    pos = pos.detach()
    n = pos.shape[0]
    perm = None
    if batch is not None and bool((batch[1:] < batch[:-1]).any()):
        # torch_cluster needs each graph's particles contiguous (it builds ptr from a sorted batch).
        perm = torch.argsort(batch, stable=True)
        inv = torch.empty_like(perm)
        inv[perm] = torch.arange(n, device=pos.device)
        x, bx, recv_p = pos[perm], batch[perm], torch.sort(inv[recv]).values
    else:
        x, bx, recv_p = pos, batch, recv
    # +2: the centre itself and a pair just beyond r may be among the candidates.
    cap = max_num_neighbors + 2 if max_num_neighbors is not None else _TORCH_CLUSTER_DEFAULT_CAP
    cap = min(cap, n)
    by = bx[recv_p] if bx is not None else None
    row, col = tc.radius(x, x[recv_p], _candidate_radius(r, pos.dtype), bx, by, max_num_neighbors=cap)
    # torch_cluster.radius returns [index into y (centres), index into x (sources)].
    i, j = recv_p[row], col
    if perm is not None:
        i, j = perm[i], perm[j]
    i, j = _exact_pairs(pos, i, j, r)
    saturated = torch.bincount(row, minlength=recv_p.numel()) >= cap
    if cap < n and bool(saturated.any()):
        redo = recv_p[saturated]
        if perm is not None:
            redo = perm[redo]
        log.debug("torch_cluster: %d centre(s) reached cap %d; searching them exactly", redo.numel(), cap)
        redo_mask = torch.zeros(n, dtype=torch.bool, device=pos.device)
        redo_mask[redo] = True
        keep = ~redo_mask[i]
        ri, rj = _search_cell_list(pos, r, batch, torch.sort(redo).values)
        i, j = torch.cat([i[keep], ri]), torch.cat([j[keep], rj])
    return i, j


# ---------------------------------------------------------------------------------------------- public API
def radius_graph(
    pos: Tensor,
    r: float,
    *,
    batch: Tensor | None = None,
    receivers: Tensor | None = None,
    loop: bool = False,
    backend: str = "auto",
    max_num_neighbors: int | None = None,
) -> Tensor:
    """Every ordered pair of particles closer than ``r``.

    Args:
        pos: (N, 3) or (N, 2) positions, floating point, finite; distances are computed in this
            dtype. Not differentiated through (indices only).
        r: radius in metres; a pair is an edge when ``|x_j - x_i| < r`` (strict).
        batch: optional (N,) integer graph id per particle (sorted or not): no edge joins particles
            of different graphs, even when the graphs overlap in space.
        receivers: optional (N,) bool mask; only these particles are targets ``i`` (centres), every
            particle can be a source ``j``. Static boundary particles enter graphs this way, only as
            neighbours of fluid particles; non-receivers cost no search work.
        loop: add the self loop ``(i, i)`` of every receiver.
        backend: ``"auto"`` (CPU: numba, or scipy without Numba; CUDA: torch_cluster if installed,
            else cell_list), ``"numba"``, ``"scipy"``, ``"torch_cluster"``, ``"cell_list"`` or ``"brute"``.
            All return identical edges.
        max_num_neighbors: optional cap on the incoming edges of a node (its self loop included when
            ``loop``); exceeding it raises, nothing is truncated.

    Returns:
        (2, E) int64 ``edge_index`` on ``pos.device``: row 0 = source ``j``, row 1 = target ``i``,
        sorted by target then source.

    Raises:
        ValueError: invalid ``pos`` (shape, dtype, NaN/inf), ``r``, ``batch``, ``receivers``,
            ``max_num_neighbors`` or an unknown/unavailable ``backend``.
        NeighborOverflowError: a node has more than ``max_num_neighbors`` neighbours.
    """
    radius, backend = _check_inputs(pos, r, batch, receivers, backend, max_num_neighbors)
    n, device = pos.shape[0], pos.device
    recv = torch.arange(n, device=device) if receivers is None else torch.nonzero(receivers).flatten()
    if recv.numel() == 0:
        return torch.empty(2, 0, dtype=torch.long, device=device)
    if batch is not None:
        # Dense ids 0..B-1 (keys of the cell list stay small; torch_cluster wants them).
        batch = torch.unique(batch, return_inverse=True)[1]

    found = None
    if backend == "numba":
        found = pair_kernels.cell_search(pos.detach(), radius, batch, recv)
        if found is None:  # a domain too wide for the cell keys (far-flung particles): the k-d tree
            backend = "scipy"
    if found is not None:
        if not loop and max_num_neighbors is None:
            return found  # exact, and already sorted by target, then source
        j, i = found[0], found[1]
    elif backend == "brute":
        i, j = _search_brute(pos.detach(), radius, batch, recv)
    elif backend == "scipy":
        i, j = _search_scipy(pos, radius, batch, receivers)
    elif backend == "cell_list":
        i, j = _search_cell_list(pos, radius, batch, recv)
    else:
        i, j = _search_torch_cluster(pos, radius, batch, recv, max_num_neighbors)
    if loop:
        i, j = torch.cat([i, recv]), torch.cat([j, recv])
    if found is None or loop:
        i, j = _sort_pairs(i, j, n)

    if max_num_neighbors is not None and i.numel():
        count = torch.bincount(i, minlength=n)
        over = count > max_num_neighbors
        if bool(over.any()):
            node = int(torch.nonzero(over)[0, 0])
            raise NeighborOverflowError(node, int(count[node]), max_num_neighbors, int(over.sum()), radius)
    log.debug("radius_graph[%s]: N=%d, r=%g, E=%d", backend, n, radius, i.numel())
    return torch.stack([j, i])


def radius_graph_between(
    sources: Tensor,
    targets: Tensor,
    r: float,
    *,
    source_batch: Tensor | None = None,
    target_batch: Tensor | None = None,
    backend: str = "auto",
) -> Tensor:
    """Every pair (source ``j``, target ``i``) closer than ``r``: a graph from one point set into another.

    What :func:`radius_graph` finds over the two sets stacked (sources first) with the targets as receivers,
    less the target-target pairs. On the CPU with Numba and no batches, only the sources are binned and the
    targets query them (:func:`pair_kernels.cross_search`): no target-target pair is scanned (CConv's
    boundary-to-fluid pairs, where the stacked search scanned every fluid pair to drop it).

    Args:
        sources: (S, 3) or (S, 2) positions.
        targets: (T, 3) or (T, 2) positions, the sources' width, dtype and device.
        r: radius in metres (strict: ``|s_j - t_i| < r``).
        source_batch: optional (S,) graph ids of the sources (with ``target_batch``, or neither).
        target_batch: optional (T,) graph ids of the targets: no pair joins two graphs.
        backend: as :func:`radius_graph`.

    Returns:
        (2, E) int64 [j; i], ``j`` a row of ``sources`` and ``i`` a row of ``targets``, sorted by target then
        source.

    Raises:
        ValueError: as :func:`radius_graph`; sets of different widths, dtypes or devices; one batch only.
    """
    if (source_batch is None) != (target_batch is None):
        raise ValueError("radius_graph_between: give both source_batch and target_batch, or neither")
    for name, t in (("sources", sources), ("targets", targets)):
        if not isinstance(t, Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if sources.dim() != 2 or targets.dim() != 2 or sources.shape[1] != targets.shape[1]:
        raise ValueError(
            "sources and targets must be (S, D) and (T, D), "
            f"got {tuple(sources.shape)} and {tuple(targets.shape)}"
        )
    if sources.dtype != targets.dtype or sources.device != targets.device:
        raise ValueError(
            f"sources ({sources.dtype}, {sources.device}) and targets ({targets.dtype}, {targets.device}) "
            "must share a dtype and a device"
        )
    n_s = sources.shape[0]
    both = torch.cat([sources, targets])
    batch = None if source_batch is None else torch.cat([source_batch, target_batch])
    radius, resolved = _check_inputs(both, r, batch, None, backend, None)
    if resolved == "numba" and batch is None and n_s and targets.shape[0]:
        found = pair_kernels.cross_search(sources.detach(), targets.detach(), radius)
        if found is not None:
            return found
    receivers = torch.zeros(both.shape[0], dtype=torch.bool, device=both.device)
    receivers[n_s:] = True
    edges = radius_graph(both, radius, batch=batch, receivers=receivers, backend=backend)
    edges = edges[:, edges[0] < n_s]  # targets are not sources of each other
    return torch.stack([edges[0], edges[1] - n_s])


def restrict_radius(edge_index: Tensor, dist: Tensor, r: float) -> tuple[Tensor, Tensor]:
    """Sub-graph of the edges shorter than ``r``.

    Search once per step at the largest radius, then restrict to each smaller radius: the solver
    never repeats the neighbour search. The edge order (sorted by target) is kept.

    Args:
        edge_index: (2, E) int64.
        dist: (E,) edge lengths, from :func:`edge_vectors`.
        r: the smaller radius, metres.

    Returns:
        edge_index: (2, E') the edges with ``dist < r``.
        mask: (E,) bool, True for the kept edges (use it to restrict ``rel``, weights, ...).
    """
    radius = _check_radius(r)
    if dist.shape != (edge_index.shape[-1],):
        raise ValueError(f"dist must have shape ({edge_index.shape[-1]},), got {tuple(dist.shape)}")
    mask = dist < radius
    return edge_index[:, mask], mask
