"""Boundary particles -> the surface points and normals a CConv network takes (paper A.5).

DeepLagrangianFluids samples its static geometry as points on the mesh surface with the outward normal;
the paper (A.5) turns its wall particles into "surface and corresponding normals". Here a boundary particle
is on the surface when its neighbours within ``1.5 l0`` are lopsided: the sum of the offsets to them,
``g_i = sum_j (x_j - x_i)``, is ``-5 l0 n`` on a flat lattice face (4 in-plane and 4 + 1 behind cancel
only sideways) and 0 one layer deeper (neighbours on both sides); ``|g_i| > 2.5 l0`` splits the two, edges
and corners score higher. The normal is ``n_i = -g_i / |g_i|`` (into the fluid). The point is moved
``offset`` l0 along it: fluid in an MPS tank rests one spacing in front of the wall particles' centres,
so the wall's own surface is half a spacing in front of them (``offset`` 0.5), where DeepLagrangianFluids'
data puts it (its fluid rests one particle radius, half a spacing, from the surface).
"""

from __future__ import annotations

import torch
from torch import Tensor

from lagfluid.zoo import radius_graph

__all__ = ["SURFACE_RADIUS", "SURFACE_THRESHOLD", "surface_points"]

SURFACE_RADIUS = 1.5
"""Neighbourhood of the surface test, l0: the nearest and the diagonal lattice neighbours."""
SURFACE_THRESHOLD = 2.5
"""``|g| / l0`` above which a boundary particle is on the surface (flat face: 5, one layer deeper: 0)."""


@torch.no_grad()
def surface_points(
    boundary_pos: Tensor, l0: float, offset: float = 0.5, batch: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """The surface of a set of boundary particles (module doc).

    Args:
        boundary_pos: (B, 3) positions of the static boundary particles (wall and dummy), m.
        l0: particle spacing, m.
        offset: how far the points are moved along their normals, in l0.
        batch: optional (B,) scene id of each particle (scenes of a batch do not see each other).

    Returns:
        points: (S, 3) surface points, m.
        normals: (S, 3) unit normals, pointing out of the solid.
        rows: (S,) rows of ``boundary_pos`` they come from.
    """
    if boundary_pos.shape[0] == 0:
        empty = boundary_pos.new_zeros(0, 3)
        return empty, empty, torch.zeros(0, dtype=torch.long, device=boundary_pos.device)
    edges = radius_graph(boundary_pos, SURFACE_RADIUS * l0, batch=batch)
    rel = boundary_pos[edges[0]] - boundary_pos[edges[1]]
    g = torch.zeros_like(boundary_pos).index_add_(0, edges[1], rel)
    size = g.norm(dim=1)
    rows = torch.nonzero(size > SURFACE_THRESHOLD * l0).flatten()
    normals = -g[rows] / size[rows, None]
    return boundary_pos[rows] + offset * l0 * normals, normals, rows
