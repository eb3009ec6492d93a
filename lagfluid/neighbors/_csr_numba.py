"""Numba kernels behind :mod:`lagfluid.neighbors.csr`: the CSR row pointer of a graph sorted by target.

Imported lazily (only the CPU's compiled bodies need Numba); compiled on first use and cached on disk. The row
pointer is filled in the pass that checks the edges: a separate ``np.searchsorted`` over the targets took
~2 ms a call at 40k particles, 4 calls a step (``benchmarks/results/fgn_step_speed.md``).
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
