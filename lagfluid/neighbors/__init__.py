"""Neighbour search: which particles are within a radius of which, exactly, on any device.

One layer (docs/architecture.md#layers), below the physics and the models, with no import of them:

* :mod:`~lagfluid.neighbors.search`: :func:`radius_graph` (every ordered pair closer than ``r``),
  :func:`radius_graph_between` (pairs from one point set into another) and their
  backends (numba, scipy, torch_cluster, cell_list, brute), all returning the same edges;
* :mod:`~lagfluid.neighbors.verlet`: the Verlet list the solver steps with (candidates within ``cutoff +
  skin``, filtered at each set of positions) and its :class:`~lagfluid.neighbors.verlet.Graph`;
* :mod:`~lagfluid.neighbors.geometry`: the one distance formula, :func:`edge_vectors`, gathers along edges;
* :mod:`~lagfluid.neighbors.csr`: :func:`kernel_adjacency` (kernel weights as one CSR matrix) and the CSR
  row pointer of a target-sorted graph;
* :mod:`~lagfluid.neighbors.pair_kernels`: kernels with a compiled (Numba) and a torch body, and the one
  place a backend is chosen (:func:`~lagfluid.neighbors.pair_kernels.backend_for`); ``_numba`` and
  ``_csr_numba`` hold the compiled loops.

This package's names below are those of the former module ``lagfluid.neighbors``.
"""

from lagfluid.neighbors.csr import kernel_adjacency
from lagfluid.neighbors.geometry import edge_vectors
from lagfluid.neighbors.search import (
    BACKENDS,
    NeighborOverflowError,
    available_backends,
    radius_graph,
    radius_graph_between,
    restrict_radius,
)

__all__ = [
    "BACKENDS",
    "NeighborOverflowError",
    "available_backends",
    "edge_vectors",
    "kernel_adjacency",
    "radius_graph",
    "radius_graph_between",
    "restrict_radius",
]
