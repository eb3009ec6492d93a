"""GNS's graph and its inputs, built by one function for training and for rollouts.

Nodes are every fluid particle and the boundary particles within the connectivity radius ``R`` of a fluid
particle (the boundary a fluid particle can see; farther boundary particles are not modelled). Edges are
every ordered pair closer than ``R`` whose receiver is a fluid particle, all of them (no neighbour cap).
Boundary nodes never move and carry no loss, and enter the graph only as neighbours of the fluid (model only
what the scene requires: ``docs/architecture.md#conventions``, convention 15): they send messages and
receive none (their latents still pass through every block's node MLP). Receiving too would cost 84 % more
edges (357k instead of 194k on a ``data=cpu`` frame, 6,250 fluid particles) for latents no loss sees
directly.

Node inputs (paper A.5, DeepMind's ``learning_to_simulate``): the ``H`` previous velocities, standardised
(boundary: 0 m/s); the distance to each lower and upper domain bound over ``R``, clipped to [-1, 1]; the
particle type (0 fluid, 1 boundary). Edge inputs: ``(x_sender - x_receiver) / R`` and its norm. Relative
positions only: the inputs are translation invariant (the bounds move with the particles) and every
aggregation is a sum over edges, so the network is permutation invariant and batches block-diagonally.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from lagfluid.zoo import radius_graph

from .network import GNSNet


@dataclass(frozen=True)
class GNSGraph:
    """The GNS graph of a (batch of) particle set(s), in node rows.

    Attributes:
        nodes: (N,) rows of the particle arrays that are nodes: the fluid rows first, in their order,
            then the boundary rows within reach, in theirs.
        n_fluid: number of fluid nodes (the first rows of ``nodes``).
        edge_index: (2, E) node indices (row 0 sender, row 1 receiver).
    """

    nodes: Tensor
    n_fluid: int
    edge_index: Tensor


def build_graph(pos: Tensor, fluid: Tensor, radius: float, batch: Tensor | None = None) -> GNSGraph:
    """Nodes and edges of the GNS graph (module doc) of positions ``pos`` (P, 3): one radius search.

    Args:
        pos: (P, 3) positions of all particles (fluid and boundary).
        fluid: (P,) bool, the fluid particles.
        radius: connectivity radius ``R`` in m.
        batch: optional (P,) sample id (no edge joins two samples).
    """
    into_fluid = radius_graph(pos, radius, batch=batch, receivers=fluid)
    reach = torch.zeros_like(fluid)
    reach[into_fluid[0]] = True
    fluid_rows = torch.nonzero(fluid).flatten()
    nodes = torch.cat([fluid_rows, torch.nonzero(reach & ~fluid).flatten()])
    node_of = torch.full((pos.shape[0],), -1, dtype=torch.long, device=pos.device)
    node_of[nodes] = torch.arange(nodes.numel(), device=pos.device)
    return GNSGraph(nodes, int(fluid_rows.numel()), node_of[into_fluid])


def fluid_acceleration(
    net: GNSNet,
    pos: Tensor,
    velocities: Tensor,
    graph: GNSGraph,
    bounds: Tensor | None,
    radius: float,
) -> Tensor:
    """The standardised acceleration (Nf, 3) of the fluid nodes (arguments as :func:`graph_inputs`)."""
    nodes, edges = graph_inputs(net, pos, velocities, graph, bounds, radius)
    return net(nodes, graph.edge_index, edges)[: graph.n_fluid]


def bounds_features(pos: Tensor, bounds: Tensor | None, radius: float) -> Tensor:
    """(N, 6) distances to the lower and upper bound per axis over ``radius``, clipped to [-1, 1].

    Args:
        pos: (N, 3) positions.
        bounds: (2, 3) domain box, or (N, 2, 3) one per node (a batch of scenes); None: no bound in reach
            (every feature 1).
        radius: ``R`` in m.
    """
    if bounds is None:
        return torch.ones(pos.shape[0], 6, dtype=pos.dtype, device=pos.device)
    lower, upper = bounds[..., 0, :], bounds[..., 1, :]
    return torch.cat([(pos - lower) / radius, (upper - pos) / radius], dim=1).clamp(-1.0, 1.0)


def graph_inputs(
    net: GNSNet,
    pos: Tensor,
    velocities: Tensor,
    graph: GNSGraph,
    bounds: Tensor | None,
    radius: float,
) -> tuple[Tensor, Tensor]:
    """Node inputs (N, F) and edge inputs (E, 4) of the graph.

    Args:
        net: the network (its velocity statistics and type encoding).
        pos: (P, 3) positions of all particles.
        velocities: (Nf, H, 3) the fluid nodes' previous velocities in m/s, oldest first.
        graph: from :func:`build_graph`.
        bounds: (2, 3) domain box, (P, 2, 3) one per particle, or None.
        radius: ``R`` in m.
    """
    x = pos.index_select(0, graph.nodes)
    n, nf = graph.nodes.numel(), graph.n_fluid
    vel = torch.zeros(n, velocities.shape[1], 3, dtype=pos.dtype, device=pos.device)
    vel[:nf] = velocities
    node_bounds = bounds if bounds is None or bounds.dim() == 2 else bounds.index_select(0, graph.nodes)
    boundary = torch.arange(n, device=pos.device) >= nf
    nodes = torch.cat(
        [
            net.velocity(vel).flatten(1),
            bounds_features(x, node_bounds, radius),
            net.type_features(boundary).to(pos.dtype),
        ],
        dim=1,
    )
    src, dst = graph.edge_index
    rel = (x.index_select(0, src) - x.index_select(0, dst)) / radius
    return nodes, torch.cat([rel, rel.norm(dim=1, keepdim=True)], dim=1)
