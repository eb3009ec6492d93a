"""Kernel-weighted sparse adjacency: edges and their weights as one CSR matrix, and CSR row pointers.

FGN's kernel-weighted neighbour sums (number density, gradient, Laplacian, the networks' linear
aggregations) are all ``A @ X`` for some weights on a radius graph (:mod:`lagfluid.neighbors.search`);
:func:`kernel_adjacency` builds ``A``. The row pointer of a graph sorted by target comes from one compiled
pass that also checks the edges (:func:`sorted_rows`, ``_csr_numba``), for this module and for the
compiled operators of :mod:`lagfluid.physics.operators`.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import torch
from torch import Tensor

from lagfluid.neighbors import pair_kernels

NUMBA = "lagfluid.neighbors._csr_numba"
"""The compiled row-pointer kernels (checked in the same pass)."""


def kernel_adjacency(edge_index: Tensor, weight: Tensor, num_nodes: int | tuple[int, int]) -> Tensor:
    """Weighted adjacency as a sparse CSR matrix, so that ``A @ X = sum_j w_ij X_j``.

    FGN's kernel-weighted neighbour sums (number density, gradient, Laplacian, the networks' linear
    aggregations) are all ``A @ X`` for some weights; one CSR product replaces a gather of ``X[j]``
    (E x F) and an ``index_add``, and is far faster (see ``benchmarks/results/neighbors_notes.md``).

    Autograd (torch 2.13, checked by ``tests/test_neighbors.py``): ``A @ X`` is differentiable
    w.r.t. both the dense ``X`` and ``weight`` (the CSR values), including double backward; build
    ``A`` anew for every forward pass (its graph is consumed by ``backward``). ``A @ x`` for a (N,)
    vector works too.

    Args:
        edge_index: (2, E) int64, row 0 = source ``j`` (column), row 1 = target ``i`` (row); each
            pair at most once. Edges sorted by target then source (as :func:`radius_graph` returns
            them) are used as they are; otherwise they are sorted here.
        weight: (E,) floating edge weights ``w_ij``.
        num_nodes: N for a square (N, N) matrix, or (N_target, N_source).

    Returns:
        (N_target, N_source) ``torch.sparse_csr`` tensor with ``A[i, j] = w_ij``, on
        ``weight.device``, dtype of ``weight``.

    Raises:
        ValueError: mismatched shapes, indices out of range, or a repeated pair.
    """
    n_target, n_source = (num_nodes, num_nodes) if isinstance(num_nodes, int) else tuple(num_nodes)
    if edge_index.dim() != 2 or edge_index.shape[0] != 2:
        raise ValueError(f"edge_index must have shape (2, E), got {tuple(edge_index.shape)}")
    e = edge_index.shape[1]
    if weight.shape != (e,):
        raise ValueError(f"weight must have shape ({e},), got {tuple(weight.shape)}")
    if n_target < 0 or n_source < 0:
        raise ValueError(f"num_nodes must be >= 0, got {num_nodes!r}")
    j, i = edge_index[0].long(), edge_index[1].long()
    return pair_kernels.backend_for("kernel_adjacency", i, j)(i, j, weight, n_target, n_source)


def _adjacency_torch(i: Tensor, j: Tensor, weight: Tensor, n_target: int, n_source: int) -> Tensor:
    """:func:`kernel_adjacency` of the pairs ``(i, j)`` (E,) each: checked, sorted where they are not."""
    if i.numel():
        key = i * n_source + j
        # The range and order checks in one read of the device (on CUDA each read is a synchronisation).
        checks = [i.min(), i.max(), j.min(), j.max(), (key[1:] <= key[:-1]).any().long()]
        lo_i, hi_i, lo_j, hi_j, unordered = torch.stack(checks).tolist()
        for name, lo, hi, size in (("target", lo_i, hi_i, n_target), ("source", lo_j, hi_j, n_source)):
            if lo < 0 or hi >= size:
                raise ValueError(f"{name} index out of range [0, {size}): min {lo}, max {hi}")
        if unordered:
            order = torch.argsort(key)
            i, j, weight, key = i[order], j[order], weight[order], key[order]
            repeated = key[1:] == key[:-1]
            if bool(repeated.any()):
                k = int(torch.nonzero(repeated)[0, 0])
                raise ValueError(f"edge (j={int(j[k])}, i={int(i[k])}) appears more than once in edge_index")
    # i is sorted: row r starts at the first i >= r (no bincount, whose size on CUDA needs a read of max(i))
    rows = torch.arange(n_target + 1, dtype=i.dtype, device=i.device)
    crow = torch.searchsorted(i.contiguous(), rows)
    return _csr(crow, j, weight, n_target, n_source)


def _csr(crow: Tensor, col: Tensor, weight: Tensor, n_target: int, n_source: int) -> Tensor:
    with warnings.catch_warnings():
        # "Sparse CSR tensor support is in beta state": matmul and its autograd are what we use, tested.
        warnings.filterwarnings("ignore", message=".*Sparse CSR tensor support is in beta.*")
        return torch.sparse_csr_tensor(crow, col, weight, size=(n_target, n_source), check_invariants=False)


def _adjacency_compiled(i: Tensor, j: Tensor, weight: Tensor, n_target: int, n_source: int) -> Tensor:
    """:func:`kernel_adjacency` with the CSR row pointer from one compiled pass that also checks the pairs.

    Pairs that are not sorted by ``i`` then ``j``, each once, in range go to the torch body (which sorts
    them or reports the bad index), as does an empty graph. The torch checks and ``bincount`` take ~8 passes
    over the pairs (the step builds two such matrices of ~1.5M pairs at 40k particles: see
    ``benchmarks/results/fgn_speed.md``).
    """
    if i.numel() == 0:
        return _adjacency_torch(i, j, weight, n_target, n_source)
    kern = pair_kernels.load(NUMBA)
    dst, src = i.contiguous().numpy(), j.contiguous().numpy()
    pair_kernels.set_threads()
    row_ptr = np.empty(n_target + 1, dtype=np.int64)
    unordered, outside = kern.check_pairs(dst, src, n_target, n_source, row_ptr)
    if unordered or outside:
        return _adjacency_torch(i, j, weight, n_target, n_source)
    return _csr(torch.from_numpy(row_ptr), j, weight, n_target, n_source)


def sorted_rows(edge_index: Tensor, num_sources: int, num_nodes: int) -> tuple[Any, Any, Any] | None:
    """``(dst, src, row_ptr)`` numpy arrays of a CPU graph sorted by target, or None (unsorted, out of range).

    One compiled pass checks the (2, E) ``edge_index`` (targets non-decreasing, sources in
    ``[0, num_sources)``, targets in ``[0, num_nodes)``) and fills the (num_nodes + 1,) row pointer on the
    way.
    A compiled body's helper: Numba must be present.
    """
    kern = pair_kernels.load(NUMBA)
    dst, src = edge_index[1].contiguous().numpy(), edge_index[0].contiguous().numpy()
    pair_kernels.set_threads()
    row_ptr = np.empty(num_nodes + 1, dtype=np.int64)
    descents, outside = kern.check_edges(dst, src, num_sources, num_nodes, row_ptr)
    if descents or outside:
        return None  # unsorted, or indices out of range (the torch bodies report those)
    return dst, src, row_ptr


pair_kernels.register("kernel_adjacency", compiled=_adjacency_compiled, torch=_adjacency_torch, module=NUMBA)
