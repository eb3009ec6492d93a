"""Numba kernels behind the CPU fast paths of :mod:`lagfluid.physics.operators` (imported lazily).

Each kernel walks the incoming edges of one target row at a time (the graph sorted by target), so the
sums need no scatter and follow the edge order exactly as ``index_add`` does; the per-edge arithmetic is
the torch path's, operation for operation. ``tests/test_operators.py`` checks them against it.
"""

from numba import njit, prange

_CHUNK = 1 << 16


@njit(inline="always")
def _row_starts(dst, e, num_targets, row_ptr):
    """Write the starts of rows ``dst[e-1]+1 .. dst[e]`` (= e) into ``row_ptr``; each row once when sorted.

    A row with no edges starts where the next one does, as ``searchsorted(dst, rows, side="left")``.
    """
    prev = dst[e - 1] if e > 0 else -1
    d = dst[e]
    if prev < d < num_targets:
        for r in range(max(prev + 1, 0), d + 1):
            row_ptr[r] = e


@njit(inline="always")
def _row_tail(dst, num_targets, row_ptr):
    """The rows after the last edge's start at the end."""
    num = dst.shape[0]
    first = dst[num - 1] + 1 if num > 0 else 0
    for r in range(min(max(first, 0), num_targets + 1), num_targets + 1):
        row_ptr[r] = num


# The row pointer is filled in the pass that checks the edges: a separate np.searchsorted over the targets
# took ~2 ms a call at 40k particles, 4 calls a step (benchmarks/results/fgn_step_speed.md).
@njit(parallel=True, cache=True)
def check_edges(dst, src, num_sources, num_targets, row_ptr):
    """(places where ``dst`` decreases, indices outside their range): (0, 0) for a valid graph.

    On the way, the CSR row pointer (num_targets + 1,) of ``dst`` into ``row_ptr``: meaningful only for
    (0, 0) (then every row is written once).
    """
    num = dst.shape[0]
    chunks = (num + _CHUNK - 1) // _CHUNK
    descents = 0
    outside = 0
    for c in prange(chunks):
        for e in range(c * _CHUNK, min(num, (c + 1) * _CHUNK)):
            if e > 0 and dst[e] < dst[e - 1]:
                descents += 1
            if src[e] < 0 or src[e] >= num_sources or dst[e] < 0 or dst[e] >= num_targets:
                outside += 1
            else:
                _row_starts(dst, e, num_targets, row_ptr)
    _row_tail(dst, num_targets, row_ptr)
    return descents, outside


@njit(parallel=True, cache=True)
def check_pairs(dst, src, num_targets, num_sources, row_ptr):
    """(places where ``(dst, src)`` does not strictly increase, indices outside their range).

    (0, 0) for a graph sorted by target then source, each pair once, every index valid; then ``row_ptr``
    (num_targets + 1,) holds its CSR row pointer, filled on the way.
    """
    num = dst.shape[0]
    chunks = (num + _CHUNK - 1) // _CHUNK
    unordered = 0
    outside = 0
    for c in prange(chunks):
        for e in range(c * _CHUNK, min(num, (c + 1) * _CHUNK)):
            if e > 0 and (dst[e] < dst[e - 1] or (dst[e] == dst[e - 1] and src[e] <= src[e - 1])):
                unordered += 1
            if src[e] < 0 or src[e] >= num_sources or dst[e] < 0 or dst[e] >= num_targets:
                outside += 1
            else:
                _row_starts(dst, e, num_targets, row_ptr)
    _row_tail(dst, num_targets, row_ptr)
    return unordered, outside


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
