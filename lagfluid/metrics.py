"""Physics metrics of a particle field, with the same definitions for every simulator.

Definitions (README "Metrics"), evaluated on the fluid particles that are *not* on the free surface
(``n_i >= beta n0``), because at the surface a deficient number density is geometry, not compression:

* density error of a frame: ``mean_i |n_i / n0 - 1|`` with ``n_i`` the MPS number density at
  ``re_density`` (2.1 l0) and ``n0`` the ideal-lattice value;
* velocity divergence of a frame: ``mean_i |div(v)_i|`` in 1/s, the MPS divergence at ``re_gradient``.

Over a run, "mean" is the mean of the per-frame values and "max" their maximum.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from lagfluid.neighbors import edge_vectors, radius_graph
from lagfluid.physics import operators as ops
from lagfluid.state import ParticleType


@dataclass(frozen=True)
class FieldMetrics:
    """Per-frame metrics; see the module docstring for the definitions."""

    density_error: float
    velocity_divergence: float
    interior_particles: int


def field_metrics(
    pos: Tensor,
    vel: Tensor,
    ptype: Tensor,
    n0: float,
    re_density: float,
    re_gradient: float,
    surface_beta: float = 0.97,
    dim: int = 3,
    backend: str = "auto",
) -> FieldMetrics:
    """Density error and velocity divergence of one frame.

    Args:
        pos: (N, 3) positions of all particles (fluid first).
        vel: (N, 3) velocities (boundary rows zero).
        ptype: (N,) particle types.
        n0: reference number density at ``re_density``.
        re_density: number-density radius, metres.
        re_gradient: divergence radius, metres.
        surface_beta: free-surface threshold.
        dim: spatial dimension of the operators.
        backend: neighbour-search backend.
    """
    fluid = ptype == ParticleType.FLUID
    radius = max(re_density, re_gradient)
    edge_index = radius_graph(pos, radius, receivers=fluid, backend=backend)
    _, dist = edge_vectors(pos, edge_index)
    n = ops.number_density(pos, edge_index[:, dist < re_density], re_density, num_nodes=pos.shape[0])
    div = ops.divergence(
        pos, edge_index[:, dist < re_gradient], vel, re_gradient, n0, dim=dim, num_nodes=pos.shape[0]
    )
    interior = fluid & (n >= surface_beta * n0)
    if not bool(interior.any()):
        return FieldMetrics(0.0, 0.0, 0)
    return FieldMetrics(
        density_error=float((n[interior] / n0 - 1.0).abs().mean()),
        velocity_divergence=float(div[interior].abs().mean()),
        interior_particles=int(interior.sum()),
    )


def summarize(values: list[float]) -> dict[str, float]:
    """``{"mean": ..., "max": ...}`` of per-frame values (NaN when empty)."""
    if not values:
        return {"mean": float("nan"), "max": float("nan")}
    t = torch.tensor(values, dtype=torch.float64)
    return {"mean": float(t.mean()), "max": float(t.max())}
