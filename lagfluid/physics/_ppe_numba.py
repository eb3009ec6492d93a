"""Numba kernels behind the CPU assembly of :func:`lagfluid.physics.ppe.assemble_ppe` (imported lazily).

One pass per solved row over its incoming edges (the graph is sorted by target, then source), written
straight into CSR arrays with the diagonal in place; and a breadth-first search for the rows that reach
a free-surface neighbour. See ``assemble_ppe`` for the rules; ``tests/test_ppe.py`` checks these kernels
against the torch assembly.
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
def reached_from(crow, col, seeds):
    """(K,) bool: rows connected (through the pattern ``crow``/``col``) to a row where ``seeds`` is True."""
    k = seeds.shape[0]
    reached = seeds.copy()
    stack = np.empty(k, dtype=np.int64)
    top = 0
    for r in range(k):
        if seeds[r]:
            stack[top] = r
            top += 1
    while top > 0:
        top -= 1
        r = stack[top]
        for e in range(crow[r], crow[r + 1]):
            j = col[e]
            if not reached[j]:
                reached[j] = True
                stack[top] = j
                top += 1
    return reached


@njit(cache=True)
def count_components(crow, col, members):
    """Number of connected components among the rows where ``members`` is True (a closed set)."""
    k = members.shape[0]
    seen = ~members
    stack = np.empty(k, dtype=np.int64)
    components = 0
    for start in range(k):
        if seen[start]:
            continue
        components += 1
        seen[start] = True
        stack[0] = start
        top = 1
        while top > 0:
            top -= 1
            r = stack[top]
            for e in range(crow[r], crow[r + 1]):
                j = col[e]
                if not seen[j]:
                    seen[j] = True
                    stack[top] = j
                    top += 1
    return components
