"""The MPS pressure Poisson equation (PPE): assembly on the solved set and conjugate-gradient solves.

This is the "project pressure" stage of the ground-truth solver (the authors' code, MPS step items
4-6). The caller computes neighbours, free-surface flags and the source term; this package turns them
into a sparse symmetric positive definite system and solves it. One job per module:

* :mod:`~lagfluid.physics.ppe.system`: :class:`PPESystem` and :func:`assemble_ppe` (which neighbours
  count, the remedy for isolated clusters);
* :mod:`~lagfluid.physics.ppe.source`: :func:`ppe_source`, the mixed divergence + density source;
* :mod:`~lagfluid.physics.ppe.solve`: :func:`solve_ppe` (the CG backends), :class:`PPEInfo`,
  :func:`ppe_residual`;
* :mod:`~lagfluid.physics.ppe._numba`: the compiled CPU backend of the assembly (imported lazily).

The system the solver solves and the one the residual metric scores are built by one function,
:func:`lagfluid.physics.mps.pressure_system`.
"""

from lagfluid.physics.ppe.solve import PPEInfo, ppe_residual, pyamg_available, solve_ppe
from lagfluid.physics.ppe.source import ppe_source
from lagfluid.physics.ppe.system import PPESystem, assemble_ppe

__all__ = [
    "PPEInfo",
    "PPESystem",
    "assemble_ppe",
    "ppe_residual",
    "ppe_source",
    "pyamg_available",
    "solve_ppe",
]
