"""Edge geometry: the one distance formula of every search and filter, and the gathers along edges.

A pair is an edge when ``|x_j - x_i| < r`` by :func:`distance` (``sqrt(x*x + y*y (+ z*z))`` in the input
dtype, one elementwise sequence), whoever computes it: every backend of
:func:`lagfluid.neighbors.search.radius_graph`, :func:`edge_vectors` and the torch bodies of
:mod:`lagfluid.neighbors.pair_kernels` (whose compiled bodies reach the same cut from squared distances at
the exact threshold of torch's ``sqrt``).
"""

from __future__ import annotations

import torch
from torch import Tensor


def squared_distance(rel: Tensor) -> Tensor:
    """``x*x + y*y (+ z*z)`` over the last axis, in this fixed order (see :func:`distance`)."""
    d2 = rel[..., 0] * rel[..., 0]
    for k in range(1, rel.shape[-1]):
        d2 = d2 + rel[..., k] * rel[..., k]
    return d2


def distance(rel: Tensor) -> Tensor:
    """Euclidean norm over the last axis, ``sqrt(x*x + y*y (+ z*z))``.

    Every backend decides ``|x_j - x_i| < r`` with this exact sequence of elementwise operations (no
    reduction kernel whose summation order could depend on layout or device), so a pair that sits
    within rounding of ``r`` is classified identically everywhere.

    Args:
        rel: (..., D) differences, D in {2, 3}.

    Returns:
        (...) distances, same dtype.
    """
    return torch.sqrt(squared_distance(rel))


def edge_vectors(pos: Tensor, edge_index: Tensor) -> tuple[Tensor, Tensor]:
    """Relative positions and distances along the edges.

    The distance is computed exactly as :func:`radius_graph` decides ``< r``, so
    ``restrict_radius(edge_index, dist, r)`` on a graph searched at radius ``r`` keeps every edge.
    Differentiable w.r.t. ``pos``; the gradient of a zero distance (a self loop) is 0, not NaN.

    Args:
        pos: (N, D) positions.
        edge_index: (2, E) int64, row 0 = source ``j``, row 1 = target ``i``.

    Returns:
        rel: (E, D) ``pos[j] - pos[i]``.
        dist: (E,) ``|pos[j] - pos[i]|``.
    """
    # index_select, not pos[idx]: faster for (E, 3) gathers on the CPU, identical values
    # (see benchmarks/results/neighbors_notes.md).
    if not (pos.requires_grad and torch.is_grad_enabled()):
        # In place and on the squared components as one (E, D) array: the same operations in the same
        # order as distance (x*x + y*y, then + z*z), so bit-identical, but faster than strided
        # per-column products (see benchmarks/results/neighbors_notes.md).
        rel = pos.index_select(0, edge_index[0])
        rel.sub_(pos.index_select(0, edge_index[1]))
        sq = rel * rel
        d2 = sq[:, 0] + sq[:, 1] if rel.shape[1] > 1 else sq[:, 0].clone()
        for k in range(2, rel.shape[1]):
            d2 += sq[:, k]
        return rel, d2.sqrt_()
    rel = pos.index_select(0, edge_index[0]) - pos.index_select(0, edge_index[1])
    # sqrt'(0) = inf would turn the gradient of self loops into NaN; where() keeps the forward values
    # bit-identical for every positive distance.
    sq = squared_distance(rel)
    positive = sq > 0
    dist = torch.where(positive, torch.sqrt(torch.where(positive, sq, torch.ones_like(sq))), 0.0)
    return rel, dist


def take_edges(edge_index: Tensor, index: Tensor, out: Tensor | None = None) -> Tensor:
    """``edge_index[:, index]``: the (2, K) columns ``index`` (K,) of a (2, E) edge index.

    One 1-D gather per row, optionally into ``out`` (2, K) (a column slice of a larger edge index): on the
    CPU ``index_select`` along dim 1 of a (2, E) tensor is slower (``benchmarks/results/neighbors_notes.md``).
    """
    if out is None:
        out = edge_index.new_empty((2, index.numel()))
    for row in range(2):
        if out[row].is_contiguous():
            torch.index_select(edge_index[row], 0, index, out=out[row])
        else:
            out[row].copy_(edge_index[row].index_select(0, index))
    return out
