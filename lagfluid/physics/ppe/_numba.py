"""Numba kernels behind the CPU assembly of :func:`lagfluid.physics.ppe.assemble_ppe` (imported lazily).

One pass per solved row over its incoming edges (the graph is sorted by target, then source), written
straight into CSR arrays with the diagonal in place; and connected-component labels of the pattern. See
``assemble_ppe`` for the rules; ``tests/test_ppe.py`` checks these kernels against the torch assembly.
"""

import numpy as np
from numba import njit, prange


@njit(parallel=True, cache=True)
def count_rows(src, coef, role, edge_start, edge_stop, inv_rho, diag, coupled, counts):
    """Per solved row r: ``diag[r]``, ``coupled[r]``, and ``counts[r + 1]`` = stored entries (diagonal too).

    role: per particle 2 solved, 1 Dirichlet (free surface), 0 neither (dummy).
    """
    for r in prange(diag.shape[0]):
        total = coef.dtype.type(0.0)
        entries = 1  # the diagonal
        touches_surface = False
        for e in range(edge_start[r], edge_stop[r]):
            c = coef[e]
            if c > 0:
                kind = role[src[e]]
                if kind != 0:
                    total += c * inv_rho
                if kind == 1:
                    touches_surface = True
                elif kind == 2:
                    entries += 1
        diag[r] = total
        coupled[r] = touches_surface
        counts[r + 1] = entries


@njit(parallel=True, cache=True)
def fill_rows(src, coef, role, pos_of, edge_start, edge_stop, inv_rho, crow, col, val, diag_at):
    """Columns and values of each row (sorted by column), leaving the diagonal's value to the caller."""
    for r in prange(diag_at.shape[0]):
        k = crow[r]
        placed = False
        for e in range(edge_start[r], edge_stop[r]):
            c = coef[e]
            if c > 0 and role[src[e]] == 2:
                j = pos_of[src[e]]
                if not placed and j > r:
                    diag_at[r] = k
                    col[k] = r
                    k += 1
                    placed = True
                col[k] = j
                val[k] = -(c * inv_rho)
                k += 1
        if not placed:
            diag_at[r] = k
            col[k] = r


@njit(cache=True)
def component_labels(crow, col):
    """(K,) int64 connected-component label of every row of the pattern ``crow``/``col``.

    Labels 0, 1, ... in order of each component's first row, by depth-first search: what SciPy's
    ``connected_components`` returns for a symmetric pattern, without its conversions (which cost more
    than the search itself: see ``benchmarks/results/ppe.md``).
    """
    k = crow.shape[0] - 1
    labels = np.full(k, -1, dtype=np.int64)
    stack = np.empty(k, dtype=np.int64)
    count = 0
    for start in range(k):
        if labels[start] >= 0:
            continue
        labels[start] = count
        stack[0] = start
        top = 1
        while top > 0:
            top -= 1
            r = stack[top]
            for e in range(crow[r], crow[r + 1]):
                j = col[e]
                if labels[j] < 0:
                    labels[j] = count
                    stack[top] = j
                    top += 1
        count += 1
    return labels
