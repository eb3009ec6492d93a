"""Numba kernels behind the CPU fast paths of :mod:`lagfluid.physics.operators` (imported lazily).

Each kernel walks the incoming edges of one target row at a time (the graph sorted by target), so the
sums need no scatter and follow the edge order exactly as ``index_add`` does; the per-edge arithmetic is
the torch path's, operation for operation. ``tests/test_operators.py`` checks them against it. The row
pointers they walk come from :func:`lagfluid.neighbors.csr.sorted_rows`.
"""

from numba import njit, prange


@njit(parallel=True, cache=True)
def laplacian_rows(src, dist, values, row_ptr, re, r_min, scale, out):
    """The MPS Laplacian of ``values`` (N, C) into every row i of ``out`` (num_rows, C).

    ``out[i] = sum_e ((1/r_e) re - 1) scale (values[src_e] - values[i])`` over row i's edges, the weight 0
    outside ``r_min < r < re``.
    """
    one = dist.dtype.type(1.0)
    zero = dist.dtype.type(0.0)
    for i in prange(out.shape[0]):
        for k in range(out.shape[1]):
            out[i, k] = 0.0
        for e in range(row_ptr[i], row_ptr[i + 1]):
            d = dist[e]
            w = (one / d) * re - one
            if not (d > r_min and d < re):
                w = zero
            c = w * scale
            j = src[e]
            for k in range(out.shape[1]):
                out[i, k] += (values[j, k] - values[i, k]) * c


@njit(parallel=True, cache=True)
def min_gradient_rows(
    src, rel, dist, pressure, source_ok, use_mask, row_ptr, re, r_min, scale, with_self, out
):
    """The minimum-pressure gradient into every row i of ``out`` (num_rows, D).

    ``out[i] = scale sum_e (rel_e w_e / max(r_e, r_min)^2) (p_j - p_min,i)`` over row i's edges whose source
    ``j`` has ``source_ok[j]`` (all with ``use_mask`` False), ``p_min,i`` the minimum of those ``p_j`` (and
    of ``p_i`` with ``with_self``, or where no edge arrives), ``w_e = re / r_e - 1`` inside
    ``r_min < r < re``, else 0. A NaN pressure propagates, as torch's ``amin`` does.
    """
    one = dist.dtype.type(1.0)
    zero = dist.dtype.type(0.0)
    for i in prange(out.shape[0]):
        for k in range(out.shape[1]):
            out[i, k] = 0.0
        p_min = pressure[i]
        seen = with_self
        for e in range(row_ptr[i], row_ptr[i + 1]):
            j = src[e]
            if use_mask and not source_ok[j]:
                continue
            p = pressure[j]
            if not seen:
                p_min = p
                seen = True
            elif p_min == p_min and (p < p_min or p != p):  # once NaN, the minimum stays NaN
                p_min = p
        for e in range(row_ptr[i], row_ptr[i + 1]):
            j = src[e]
            if use_mask and not source_ok[j]:
                continue
            d = dist[e]
            w = (one / d) * re - one
            if not (d > r_min and d < re):
                w = zero
            dc = d if d > r_min else r_min
            c = w / (dc * dc)
            dp = pressure[j] - p_min
            for k in range(out.shape[1]):
                out[i, k] += (rel[e, k] * c) * dp
        for k in range(out.shape[1]):
            out[i, k] = out[i, k] * scale


@njit(parallel=True, cache=True)
def density_rows(dist, row_ptr, re, r_min, out):
    """The number density ``out[i] = sum_e w(r_e)`` over row i's edges.

    ``w = re / r - 1`` inside ``r_min < r < re``, else 0 (the torch path's arithmetic and edge order).
    """
    one = dist.dtype.type(1.0)
    zero = dist.dtype.type(0.0)
    for i in prange(out.shape[0]):
        acc = zero
        for e in range(row_ptr[i], row_ptr[i + 1]):
            d = dist[e]
            w = (one / d) * re - one
            if not (d > r_min and d < re):
                w = zero
            acc += w
        out[i] = acc


@njit(parallel=True, cache=True)
def kernel_weights(dist, re, r_min, out):
    """``out[e] = re / r_e - 1`` inside ``r_min < r_e < re``, else 0 (the torch path's arithmetic)."""
    one = dist.dtype.type(1.0)
    zero = dist.dtype.type(0.0)
    for e in prange(dist.shape[0]):
        d = dist[e]
        w = (one / d) * re - one
        out[e] = w if (d > r_min and d < re) else zero
