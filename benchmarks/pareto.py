"""Pareto front of (cost, error) points: the simulators no other simulator beats on both at once.

A point is on the front when no other point is at least as cheap *and* at least as accurate while strictly
better in one of the two. Points with a non-finite coordinate (a run that stopped, a metric that does not
apply) are never on it. Used by ``benchmarks.tables`` for the speed/accuracy trade-off.
"""

from __future__ import annotations

import math
from collections.abc import Sequence


def dominates(a: tuple[float, float], b: tuple[float, float]) -> bool:
    """True when ``a`` is no worse than ``b`` in both coordinates and strictly better in one (minimising)."""
    return a[0] <= b[0] and a[1] <= b[1] and (a[0] < b[0] or a[1] < b[1])


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the non-dominated points, sorted by cost (then error), both coordinates minimised.

    Args:
        points: ``(cost, error)`` pairs, e.g. (wall seconds per simulated second, Chamfer distance).

    Returns:
        The indices into ``points`` of the front, cheapest first. Equal points are all kept (neither
        dominates the other); points with NaN or infinite coordinates are left out.
    """
    finite = [i for i, p in enumerate(points) if all(math.isfinite(float(v)) for v in p)]
    # O(n^2) is fine: a trade-off table has tens of rows, and the rule reads exactly as its definition.
    front = [i for i in finite if not any(dominates(points[j], points[i]) for j in finite if j != i)]
    return sorted(front, key=lambda i: (points[i][0], points[i][1]))
