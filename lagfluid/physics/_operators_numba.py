"""Numba kernels behind the CPU fast paths of :mod:`lagfluid.physics.operators` (imported lazily).

Each kernel walks the incoming edges of one target row at a time (the graph sorted by target), so the
sums need no scatter and follow the edge order exactly as ``index_add`` does; the per-edge arithmetic is
the torch path's, operation for operation. ``tests/test_operators.py`` checks them against it.
"""

from numba import njit, prange

_CHUNK = 1 << 16


@njit(parallel=True, cache=True)
def check_edges(dst, src, num_sources):
    """(places where ``dst`` decreases, sources outside [0, num_sources)): (0, 0) for a valid graph."""
    num = dst.shape[0]
    chunks = (num + _CHUNK - 1) // _CHUNK
    descents = 0
    outside = 0
    for c in prange(chunks):
        for e in range(c * _CHUNK, min(num, (c + 1) * _CHUNK)):
            if e > 0 and dst[e] < dst[e - 1]:
                descents += 1
            if src[e] < 0 or src[e] >= num_sources:
                outside += 1
    return descents, outside


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
