"""Numba kernels behind :func:`baselines.cconv.conv.conv_geometry`'s blocks of kernel cells (CPU only).

Loaded lazily through :func:`lagfluid.neighbors.pair_kernels.load`; compiled on first use and cached on disk.
"""

import numpy as np
from numba import njit, prange


@njit(parallel=True, cache=True)
def block_counts(cell, lo, hi, per_pair):
    """``per_pair[e]``: the corners of pair e whose kernel cell lies in [lo, hi). cell: (E, 8)."""
    for e in prange(cell.shape[0]):
        found = 0
        for k in range(cell.shape[1]):
            if lo <= cell[e, k] < hi:
                found += 1
        per_pair[e] = found


@njit(parallel=True, cache=True)
def block_fill(j, cell, w, lo, hi, offsets, cols, vals):
    """Those corners in pair order: column ``j * (hi - lo) + cell - lo`` and weight, from ``offsets[e]``."""
    width = hi - lo
    for e in prange(cell.shape[0]):
        k_out = offsets[e]
        for k in range(cell.shape[1]):
            c = cell[e, k]
            if lo <= c < hi:
                cols[k_out] = j[e] * width + (c - lo)
                vals[k_out] = w[e, k]
                k_out += 1


def block_entries(i, j, cell, w, lo, hi, n_out):  # numpy arrays in, numpy arrays out
    """(crow (n_out + 1,), cols, vals) of the corners in [lo, hi), rows from the sorted outputs ``i``."""
    per_pair = np.empty(cell.shape[0], dtype=np.int64)
    block_counts(cell, lo, hi, per_pair)
    offsets = np.zeros(cell.shape[0] + 1, dtype=np.int64)
    np.cumsum(per_pair, out=offsets[1:])
    cols = np.empty(int(offsets[-1]), dtype=np.int64)
    vals = np.empty(int(offsets[-1]), dtype=w.dtype)
    block_fill(j, cell, w, lo, hi, offsets, cols, vals)
    # pairs sorted by output row: row r's entries start where its first pair's do
    crow = offsets[np.searchsorted(i, np.arange(n_out + 1), side="left")]
    return crow, cols, vals
