"""Numba kernels behind :mod:`lagfluid.pair_kernels` (imported lazily: only CPU filtering needs Numba).

Compiled on first use and cached on disk (``cache=True``), so only a fresh install pays the compilation.
"""

import numpy as np
from numba import njit, prange

# Pairs per parallel work item: small enough to balance two to sixteen threads over a million pairs,
# large enough that the per-chunk bookkeeping is negligible.
_CHUNK = 1 << 15


@njit(cache=True, inline="always")
def _squared_distance(pos, s, d):  # (x*x + y*y) + z*z in pos.dtype, as lagfluid.neighbors._distance
    diff = pos[s, 0] - pos[d, 0]
    acc = diff * diff
    for k in range(1, pos.shape[1]):
        diff = pos[s, k] - pos[d, k]
        acc = acc + diff * diff
    return acc


@njit(parallel=True, cache=True)
def count_within(pos, src, dst, bound2, target_mask, use_mask):
    num = src.shape[0]
    chunks = (num + _CHUNK - 1) // _CHUNK
    counts = np.zeros(chunks + 1, dtype=np.int64)
    for c in prange(chunks):
        kept = 0
        for e in range(c * _CHUNK, min(num, (c + 1) * _CHUNK)):
            if use_mask and not target_mask[dst[e]]:
                continue
            if _squared_distance(pos, src[e], dst[e]) < bound2:
                kept += 1
        counts[c + 1] = kept
    return np.cumsum(counts)


@njit(parallel=True, cache=True)
def fill_within(pos, src, dst, bound2, target_mask, use_mask, offsets, out_src, out_dst, rel, dist2):
    num = src.shape[0]
    dim = pos.shape[1]
    for c in prange(offsets.shape[0] - 1):
        k = offsets[c]
        for e in range(c * _CHUNK, min(num, (c + 1) * _CHUNK)):
            s, d = src[e], dst[e]
            if use_mask and not target_mask[d]:
                continue
            r2 = _squared_distance(pos, s, d)
            if r2 < bound2:
                out_src[k] = s
                out_dst[k] = d
                for j in range(dim):
                    rel[k, j] = pos[s, j] - pos[d, j]
                dist2[k] = r2
                k += 1


@njit(parallel=True, cache=True)
def count_below(values, bound):
    num = values.shape[0]
    chunks = (num + _CHUNK - 1) // _CHUNK
    counts = np.zeros(chunks + 1, dtype=np.int64)
    for c in prange(chunks):
        kept = 0
        for e in range(c * _CHUNK, min(num, (c + 1) * _CHUNK)):
            if values[e] < bound:
                kept += 1
        counts[c + 1] = kept
    return np.cumsum(counts)


@njit(parallel=True, cache=True)
def fill_below(values, bound, offsets, src, dst, rel, out_src, out_dst, out_rel, out_dist):
    num = values.shape[0]
    dim = rel.shape[1]
    for c in prange(offsets.shape[0] - 1):
        k = offsets[c]
        for e in range(c * _CHUNK, min(num, (c + 1) * _CHUNK)):
            if values[e] < bound:
                out_src[k] = src[e]
                out_dst[k] = dst[e]
                for j in range(dim):
                    out_rel[k, j] = rel[e, j]
                out_dist[k] = values[e]
                k += 1
