"""The inputs of FGN's networks, built by one function per network for training and inference alike.

Training (:mod:`lagfluid.models.fgn.trainables`, batches of dataset items) and inference
(:mod:`lagfluid.models.fgn.learned_stages`, one scene inside the split-step scheme) find their graphs
differently, but both hand the graph and the per-particle and per-scene fields to these functions, so what a
network sees cannot differ between the two. Each returns the network's positional arguments, in the network's
float type ``dtype``; ``net(*args)`` is the standardised output, ``net.predict(*args)`` the physical one.

``batch`` (N,) says which graph (sample) each node belongs to and picks that graph's row of a per-graph
field; ``None`` means one graph, whose per-graph fields are broadcast to every node.
"""

from __future__ import annotations

import torch
from torch import Tensor

from lagfluid.neighbors import kernel_adjacency
from lagfluid.physics import operators as ops


def _per_node(value: Tensor, batch: Tensor | None, num_nodes: int) -> Tensor:
    """(B, ...) per-graph values -> (N, ...) per node."""
    if batch is None:
        return value.expand(num_nodes, *value.shape[1:])
    return value.index_select(0, batch)


def kernel_matrix(
    edge_index: Tensor, dist: Tensor, radius: float, num_nodes: int, dtype: torch.dtype
) -> Tensor:
    """(N, N) CSR adjacency of MPS kernel weights ``w(r_ij)`` at ``radius`` (m), rows = targets.

    ``edge_index`` (2, E) source -> target, ``dist`` (E,) pair distances.
    """
    return kernel_adjacency(edge_index, ops.kernel(dist, radius).to(dtype), num_nodes)


def advection_inputs(
    vel: Tensor,
    is_fluid: Tensor,
    gravity: Tensor,
    viscosity: Tensor,
    edge_index: Tensor,
    dist: Tensor,
    radius: float,
    dtype: torch.dtype,
    batch: Tensor | None = None,
) -> tuple[Tensor, ...]:
    """Arguments of :class:`~lagfluid.models.fgn.networks.AdvectionNet`.

    Args:
        vel: (N, 3) velocities v^n of the nodes (0 on the boundary).
        is_fluid: (N,) bool.
        gravity: (B, 3) body force of each graph, m/s^2.
        viscosity: (B,) kinematic viscosity of each graph, m^2/s.
        edge_index: (2, E) the kernel graph into the fluid nodes (source -> target).
        dist: (E,) its pair distances.
        radius: the kernel radius, m.
        dtype: the network's float type.
        batch: (N,) graph of each node, or None for one graph.

    Returns:
        ``(vel (N, 3), is_fluid (N,), gravity (N, 3), viscosity (N,), adj (N, N) CSR)``.
    """
    n = vel.shape[0]
    adj = kernel_matrix(edge_index, dist, radius, n, dtype)
    return (
        vel.to(dtype),
        is_fluid,
        _per_node(gravity.to(dtype), batch, n),
        _per_node(viscosity.to(dtype), batch, n),
        adj,
    )


def collision_inputs(
    vel: Tensor, rel: Tensor, dist: Tensor, edge_index: Tensor, dtype: torch.dtype
) -> tuple[Tensor, ...]:
    """Arguments of :class:`~lagfluid.models.fgn.networks.CollisionNet`.

    Args:
        vel: (N, 3) velocities v* of the nodes.
        rel: (E, 3) ``x_j - x_i`` of the pairs closer than the collision radius.
        dist: (E,) their norms.
        edge_index: (2, E) source j -> target i over the N nodes.
        dtype: the network's float type.

    Returns:
        ``(vel (N, 3), rel (E, 3), dist (E,), edge_index (2, E))``.
    """
    return vel.to(dtype), rel.to(dtype), dist.to(dtype), edge_index


def pressure_inputs(
    vel: Tensor,
    density: Tensor,
    n0: Tensor | float,
    is_fluid: Tensor,
    edge_index: Tensor,
    dist: Tensor,
    radius: float,
    dtype: torch.dtype,
    batch: Tensor | None = None,
) -> tuple[Tensor, ...]:
    """Arguments of :class:`~lagfluid.models.fgn.networks.PressureNet` on the PPE unknowns.

    Args:
        vel: (M, 3) velocities v** of the unknowns (non-free-surface fluid and wall particles).
        density: (M,) number density n at x**.
        n0: (B,) reference number density of each graph, or one float for one graph.
        is_fluid: (M,) bool.
        edge_index: (2, E) the kernel graph among the unknowns (source -> target).
        dist: (E,) its pair distances.
        radius: the kernel radius, m.
        dtype: the network's float type.
        batch: (M,) graph of each node, or None for one graph.

    Returns:
        ``(vel (M, 3), n / n0 (M,), is_fluid (M,), adj (M, M) CSR)``.
    """
    m = vel.shape[0]
    adj = kernel_matrix(edge_index, dist, radius, m, dtype)
    ratio = density / (n0 if batch is None else n0.index_select(0, batch))
    return vel.to(dtype), ratio.to(dtype), is_fluid, adj
