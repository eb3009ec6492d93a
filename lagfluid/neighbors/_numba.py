"""Numba kernels behind :mod:`lagfluid.neighbors.pair_kernels` (imported lazily: only CPU filters need Numba).

Compiled on first use and cached on disk (``cache=True``), so only a fresh install pays the compilation.
"""

import numpy as np
from numba import njit, prange

# Pairs per parallel work item: small enough to balance two to sixteen threads over a million pairs,
# large enough that the per-chunk bookkeeping is negligible.
_CHUNK = 1 << 15


@njit(cache=True, inline="always")
def _squared_distance(pos, s, d):  # (x*x + y*y) + z*z in pos.dtype, as lagfluid.neighbors.geometry.distance
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


@njit(cache=True, inline="always")
def _cell_run(cell, cell_start, dims, reach, i, cz, cy):
    """[start, stop) in ``order`` of cells (cz, cy, x within ``reach`` of particle i), contiguous along x."""
    row = ((cell[i, 0] * dims[1] + cz) * dims[2] + cy) * dims[3]
    lo = row + max(cell[i, 3] - reach, 0)
    hi = row + min(cell[i, 3] + reach + 1, dims[3])
    return cell_start[lo], cell_start[hi]


@njit(parallel=True, cache=True)
def cell_scan_sizes(cell, cell_start, dims, reach, recv, sizes):
    """``sizes[r + 1]``: the particles in the cells scanned around recv[r], a bound on its pair count.

    cell: (N, 4) int64 cell coordinates (graph id, cz, cy, cx); cell_start: (prod(dims) + 1,) where each
    cell's particles start in ``order`` (the particles sorted by cell key; dense table); recv: (R,) int64.
    """
    for r in prange(recv.shape[0]):
        i = recv[r]
        total = 0
        for cz in range(max(cell[i, 1] - reach, 0), min(cell[i, 1] + reach + 1, dims[1])):
            for cy in range(max(cell[i, 2] - reach, 0), min(cell[i, 2] + reach + 1, dims[2])):
                start, stop = _cell_run(cell, cell_start, dims, reach, i, cz, cy)
                total += stop - start
        sizes[r + 1] = total


@njit(cache=True, inline="always")
def _sort_nearly_sorted(a, lo, hi):
    """Sort ``a[lo:hi]`` in place: insertion sort while the input is nearly sorted, else a full sort.

    The sources of a receiver come out of the cell scan nearly sorted when particle numbers follow the cells
    (lattice scenes: see CellList.build); insertion sort is then ~3x cheaper than quicksort on ~85 sources.
    A budget of 8 moves per element bounds the cost on any other order (``neighbors_notes.md``).
    """
    budget = 8 * (hi - lo)
    for k in range(lo + 1, hi):
        v = a[k]
        m = k - 1
        while m >= lo and a[m] > v:
            a[m + 1] = a[m]
            m -= 1
        a[m + 1] = v
        budget -= k - 1 - m
        if budget < 0:
            a[lo:hi].sort()
            return


@njit(parallel=True, cache=True)
def cell_search_fill(pos, cell, order, cell_start, dims, reach, recv, bound2, slots, buf, counts):
    """Receiver r's sources j != recv[r] with d2 < bound2, sorted, into ``buf[slots[r]:]``; ``counts[r + 1]``.

    ``slots`` from :func:`cell_scan_sizes` (each receiver's room is its scan size), so one pass suffices.
    """
    for r in prange(recv.shape[0]):
        i = recv[r]
        k_out = slots[r]
        for cz in range(max(cell[i, 1] - reach, 0), min(cell[i, 1] + reach + 1, dims[1])):
            for cy in range(max(cell[i, 2] - reach, 0), min(cell[i, 2] + reach + 1, dims[2])):
                start, stop = _cell_run(cell, cell_start, dims, reach, i, cz, cy)
                for k in range(start, stop):
                    j = order[k]
                    if j != i and _squared_distance(pos, j, i) < bound2:
                        buf[k_out] = j
                        k_out += 1
        _sort_nearly_sorted(buf, slots[r], k_out)
        counts[r + 1] = k_out - slots[r]


@njit(parallel=True, cache=True)
def cell_search_compact(recv, slots, buf, offsets, out_i, out_j):
    """The pairs of :func:`cell_search_fill` packed: receiver r's at ``offsets[r]:offsets[r + 1]``."""
    for r in prange(recv.shape[0]):
        i, s, o = recv[r], slots[r], offsets[r]
        for k in range(offsets[r + 1] - o):
            out_i[o + k] = i
            out_j[o + k] = buf[s + k]


@njit(parallel=True, cache=True)
def cell_any_within(pos, cell, order, cell_start, dims, reach, queries, is_target, bound2, out):
    """``out[q]``: a particle i with ``is_target[i]``, i != queries[q], lies within the cut of queries[q]."""
    for q in prange(queries.shape[0]):
        j = queries[q]
        hit = False
        for cz in range(max(cell[j, 1] - reach, 0), min(cell[j, 1] + reach + 1, dims[1])):
            for cy in range(max(cell[j, 2] - reach, 0), min(cell[j, 2] + reach + 1, dims[2])):
                start, stop = _cell_run(cell, cell_start, dims, reach, j, cz, cy)
                for k in range(start, stop):
                    i = order[k]
                    if is_target[i] and i != j and _squared_distance(pos, i, j) < bound2:
                        hit = True
                        break
                if hit:
                    break
            if hit:
                break
        out[q] = hit


@njit(parallel=True, cache=True)
def count_induced(src, dst, keep):
    num = src.shape[0]
    chunks = (num + _CHUNK - 1) // _CHUNK
    counts = np.zeros(chunks + 1, dtype=np.int64)
    for c in prange(chunks):
        kept = 0
        for e in range(c * _CHUNK, min(num, (c + 1) * _CHUNK)):
            if keep[src[e]] and keep[dst[e]]:
                kept += 1
        counts[c + 1] = kept
    return np.cumsum(counts)


@njit(parallel=True, cache=True)
def fill_induced(src, dst, keep, local, offsets, out_src, out_dst, out_pos):
    num = src.shape[0]
    for c in prange(offsets.shape[0] - 1):
        k = offsets[c]
        for e in range(c * _CHUNK, min(num, (c + 1) * _CHUNK)):
            if keep[src[e]] and keep[dst[e]]:
                out_src[k] = local[src[e]]
                out_dst[k] = local[dst[e]]
                out_pos[k] = e
                k += 1


# ------------------------------------------------------------------------- the Verlet list's split search
# Queries from one particle set (the fluid) into the cell list of another (the fluid's own, or the static
# boundary's), the sources read from positions stored in cell order (contiguous), then the Verlet list's
# candidate rows assembled from the parts (fluid-fluid, fluid-boundary, its transpose, the static rows).


@njit(cache=True, inline="always")
def _query_run(qcell, r, cell_start, dims, reach, cz, cy):
    """[start, stop) in cell order of cells (cz, cy, x within ``reach`` of query r); empty off the grid."""
    x_lo = max(qcell[r, 3] - reach, 0)
    x_hi = min(qcell[r, 3] + reach + 1, dims[3])
    if x_lo >= x_hi:
        return 0, 0
    row = ((qcell[r, 0] * dims[1] + cz) * dims[2] + cy) * dims[3]
    return cell_start[row + x_lo], cell_start[row + x_hi]


@njit(parallel=True, cache=True)
def query_scan_sizes(qcell, cell_start, dims, reach, sizes):
    """``sizes[r + 1]``: the particles in the cells scanned around query r (qcell: (Q, 4) in the grid)."""
    for r in prange(qcell.shape[0]):
        total = 0
        for cz in range(max(qcell[r, 1] - reach, 0), min(qcell[r, 1] + reach + 1, dims[1])):
            for cy in range(max(qcell[r, 2] - reach, 0), min(qcell[r, 2] + reach + 1, dims[2])):
                start, stop = _query_run(qcell, r, cell_start, dims, reach, cz, cy)
                total += stop - start
        sizes[r + 1] = total


@njit(parallel=True, cache=True)
def query_fill(qpos, qcell, visit, skip, spos, order, cell_start, dims, reach, bound2, slots, buf, counts,
               sort):  # fmt: skip
    """Query r's sources ``order[k]`` != skip[r] with d2 < bound2 into ``buf[slots[r]:]``, sorted if ``sort``.

    Queries are visited in the order ``visit`` (their cell order: neighbouring queries read the same cells);
    ``spos``: the sources' positions in cell order (``spos[k]`` is source ``order[k]``), read contiguously.
    The distance is ``spos[k] - qpos[r]`` squared and summed as ``_squared_distance`` (source minus target).
    """
    dim = qpos.shape[1]
    for v in prange(visit.shape[0]):
        r = visit[v]
        k_out = slots[r]
        for cz in range(max(qcell[r, 1] - reach, 0), min(qcell[r, 1] + reach + 1, dims[1])):
            for cy in range(max(qcell[r, 2] - reach, 0), min(qcell[r, 2] + reach + 1, dims[2])):
                start, stop = _query_run(qcell, r, cell_start, dims, reach, cz, cy)
                for k in range(start, stop):
                    diff = spos[k, 0] - qpos[r, 0]
                    acc = diff * diff
                    for d in range(1, dim):
                        diff = spos[k, d] - qpos[r, d]
                        acc = acc + diff * diff
                    if acc < bound2 and order[k] != skip[r]:
                        buf[k_out] = order[k]
                        k_out += 1
        if sort:
            _sort_nearly_sorted(buf, slots[r], k_out)
        counts[r] = k_out - slots[r]


@njit(cache=True)
def column_counts(slots, counts, buf, size):
    """How often each value 0..size-1 occurs among the query rows ``buf[slots[r]:slots[r] + counts[r]]``."""
    out = np.zeros(size, dtype=np.int64)
    for r in range(slots.shape[0]):
        for k in range(slots[r], slots[r] + counts[r]):
            out[buf[k]] += 1
    return out


@njit(parallel=True, cache=True)
def near_wall_hop(wall_local, ptr, src, near, frontier, reached):
    """``reached[b]``: wall b (not yet ``near``) has a ``frontier`` particle among its static sources."""
    for w in prange(wall_local.shape[0]):
        b = wall_local[w]
        if near[b]:
            continue
        for k in range(ptr[w], ptr[w + 1]):
            if frontier[src[k]]:
                reached[b] = True
                break


@njit(parallel=True, cache=True)
def symmetric_histogram(slots, counts, buf, chunks, hist):
    """``hist[c, i]``: how many rows j of chunk c (rows split into ``chunks`` ascending runs) hold i."""
    n = slots.shape[0]
    per = (n + chunks - 1) // chunks
    for c in prange(chunks):
        for j in range(c * per, min(n, (c + 1) * per)):
            for k in range(slots[j], slots[j] + counts[j]):
                hist[c, buf[k]] += 1


@njit(parallel=True, cache=True)
def symmetric_transpose(slots, counts, buf, chunks, cursor, out_i, out_j):
    """The rows of a symmetric relation, each sorted, without a sort: j goes into row i for every i of row j.

    Rows j are visited in ascending order (chunk c after chunk c - 1, each from ``cursor[c, i]``, where the
    entries of row i from the chunks before end), so each row i receives its j ascending. Symmetric: i is in
    row j exactly when j is in row i (the same squared distance, negated difference): row i gets its sources.
    """
    n = slots.shape[0]
    per = (n + chunks - 1) // chunks
    for c in prange(chunks):
        for j in range(c * per, min(n, (c + 1) * per)):
            for k in range(slots[j], slots[j] + counts[j]):
                i = buf[k]
                at = cursor[c, i]
                out_i[at] = i
                out_j[at] = j
                cursor[c, i] = at + 1


@njit(parallel=True, cache=True)
def fluid_rows(fb_slots, fb_buf, fb_counts, n_fluid, starts, out_i, out_j):
    """Fluid target i's boundary sources (local + n_fluid), sorted, from ``starts[i]`` (after its fluid)."""
    for i in prange(fb_slots.shape[0]):
        o = starts[i]
        for k in range(fb_counts[i]):
            out_i[o + k] = i
            out_j[o + k] = fb_buf[fb_slots[i] + k] + n_fluid


@njit(cache=True)
def wall_rows_from_fluid(fb_slots, fb_buf, fb_counts, n_fluid, cursor, out_i, out_j):
    """The fluid sources of each wall target, ascending: the fluid-boundary rows transposed, in fluid order.

    ``cursor[b]``: where wall target b's row is written next (-1: b is not a target); advanced in place.
    """
    for i in range(fb_slots.shape[0]):
        for k in range(fb_slots[i], fb_slots[i] + fb_counts[i]):
            b = fb_buf[k]
            c = cursor[b]
            if c >= 0:
                out_i[c] = b + n_fluid
                out_j[c] = i
                cursor[b] = c + 1


@njit(parallel=True, cache=True)
def wall_rows_static(targets, rows, ptr, src, n_fluid, starts, out_i, out_j):
    """Wall target ``targets[t]`` (local)'s static boundary sources (row ``rows[t]``) from ``starts[t]``."""
    for t in prange(targets.shape[0]):
        w, o, b = rows[t], starts[t], targets[t] + n_fluid
        for k in range(ptr[w + 1] - ptr[w]):
            out_i[o + k] = b
            out_j[o + k] = src[ptr[w] + k] + n_fluid


@njit(parallel=True, cache=True)
def compact_rows(slots, counts, buf, ptr, out):
    """Rows ``buf[slots[r]:slots[r] + counts[r]]`` packed into ``out[ptr[r]:ptr[r + 1]]``."""
    for r in prange(slots.shape[0]):
        for k in range(counts[r]):
            out[ptr[r] + k] = buf[slots[r] + k]
