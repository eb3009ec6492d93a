"""FGN's learned stages: its networks behind the stage protocols of :mod:`lagfluid.physics.scheme`.

Each stage asks the step's :class:`~lagfluid.physics.step_context.StepContext` for its radius graph (so graphs
are shared with the exact stages and never searched twice at one set of positions), keeps only the particles
that graph touches (a scene's ~80k static boundary particles mostly never enter), runs its network there and
returns what the exact stage would return. Only the networks differ between ``model=mps``, ``fgn`` and
``hybrid``; the update scheme around them is the same code. The networks' inputs come from
:mod:`lagfluid.models.fgn.inputs`, the functions training uses too.
"""

from __future__ import annotations

import torch
from torch import Tensor

from lagfluid.device_constants import device_constant
from lagfluid.models.fgn.inputs import advection_inputs, collision_inputs, pressure_inputs
from lagfluid.models.fgn.networks import AdvectionNet, CollisionNet, PressureNet
from lagfluid.neighbors import pair_kernels
from lagfluid.physics import operators as ops
from lagfluid.physics.settings import SolverSettings
from lagfluid.physics.step_context import StepContext
from lagfluid.state import SceneParams


def _net_dtype(net: torch.nn.Module) -> torch.dtype:
    return next(net.parameters()).dtype


def compact_nodes(edge_index: Tensor, first: int, num_nodes: int) -> tuple[Tensor, Tensor]:
    """Renumber a graph onto the particles it touches, keeping rows ``0 .. first-1`` (the fluid) in place.

    Args:
        edge_index: (2, E) over ``num_nodes`` particles, targets ``< first`` or not.
        first: particles ``0 .. first-1`` are kept (and keep their numbers) even when isolated.
        num_nodes: N, particles in the scene.

    Returns:
        ``nodes`` (M,) the scene rows kept (``0 .. first-1``, then every other particle the graph touches, in
        increasing order) and the (2, E) edge_index renumbered onto ``0 .. M-1``. Edge order is unchanged.
    """
    # A mask rather than torch.unique: no sort of the 2E indices.
    keep = torch.zeros(num_nodes, dtype=torch.bool, device=edge_index.device)
    keep[edge_index[0]] = True
    keep[edge_index[1]] = True
    keep[:first] = True
    nodes, sub, _ = induced_subgraph(edge_index, keep)  # 0 .. first-1, then the others in increasing order
    return nodes, sub


def induced_subgraph(edge_index: Tensor, keep: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The sub-graph among the nodes ``keep`` (N,) bool, renumbered onto them.

    Returns:
        ``nodes`` (M,) the kept rows in increasing order, the (2, K) edges between them renumbered onto
        ``0 .. M-1`` (order kept) and their (K,) positions in ``edge_index`` (to take per-edge values).
    """
    nodes = torch.nonzero(keep).flatten()
    local = torch.full((keep.shape[0],), -1, dtype=torch.long, device=keep.device)
    local[nodes] = torch.arange(nodes.numel(), device=keep.device)
    return nodes, *pair_kernels.backend_for("induced_edges", edge_index)(edge_index, keep, local)


class LearnedAdvection:
    """Advection by :class:`~lagfluid.models.fgn.networks.AdvectionNet` on the fluid and its neighbours."""

    def __init__(self, net: AdvectionNet) -> None:
        self.net = net.eval()

    def radii(self, settings: SolverSettings, params: SceneParams) -> tuple[float, ...]:
        """Radii (l0) this stage searches."""
        return (self.net.radius,)

    def __call__(self, ctx: StepContext, pos: Tensor, vel: Tensor) -> Tensor:
        """Acceleration (N_fluid, 3) at ``(x^n, v^n)``."""
        nf, params = ctx.n_fluid, ctx.params
        g = ctx.graph(pos, self.net.radius, fluid_targets_only=True)
        with ctx.timer("advection", pos.device):
            nodes, edge_index = compact_nodes(g.edge_index, nf, pos.shape[0])
            dtype = _net_dtype(self.net)
            inputs = advection_inputs(
                vel.index_select(0, nodes),
                nodes < nf,
                device_constant(params.gravity, dtype, pos.device).unsqueeze(0),
                device_constant([params.viscosity], dtype, pos.device),
                edge_index,
                g.dist,
                ctx.radius(self.net.radius),
                dtype,
            )
            acc = self.net.predict(*inputs)
        return acc[:nf].to(pos.dtype)


class LearnedCollision:
    """Collision correction by :class:`~lagfluid.models.fgn.networks.CollisionNet` (pairs in its radius)."""

    def __init__(self, net: CollisionNet) -> None:
        self.net = net.eval()

    def radii(self, settings: SolverSettings, params: SceneParams) -> tuple[float, ...]:
        """Radii (l0) this stage searches."""
        return (self.net.radius,)

    def __call__(self, ctx: StepContext, pos: Tensor, vel: Tensor) -> Tensor:
        """Corrected fluid velocities (N_fluid, 3) at ``(x*, v*)``."""
        nf = ctx.n_fluid
        # Edges into fluid and nearby walls, as the authors' graph: a source's summed incoming edges are an
        # input of the edge update, and a wall's come from the fluid pressing on it.
        g = ctx.graph(pos, self.net.radius)
        with ctx.timer("collision", pos.device):
            ctx.info["collision_pairs"] = float(g.edge_index.shape[1])
            if g.edge_index.shape[1] == 0:  # nothing within the radius: no network call at all
                return vel[:nf].clone()
            nodes, edge_index = compact_nodes(g.edge_index, nf, pos.shape[0])
            inputs = collision_inputs(
                vel.index_select(0, nodes), g.rel, g.dist, edge_index, _net_dtype(self.net)
            )
            dv = self.net.predict(*inputs)
        return vel[:nf] + dv[:nf].to(vel.dtype)


class LearnedPressure:
    """Pressure by :class:`~lagfluid.models.fgn.networks.PressureNet` on the non-free-surface particles.

    The nodes are the PPE's unknowns: fluid and wall particles with ``n >= beta n0`` (number density at
    ``re_density``); free-surface and dummy particles have ``p = 0``, as in the exact stage.
    """

    def __init__(self, net: PressureNet) -> None:
        self.net = net.eval()

    def radii(self, settings: SolverSettings, params: SceneParams) -> tuple[float, ...]:
        """Radii (l0) this stage searches: its graph and the number density (free surface, input)."""
        return (self.net.radius, settings.re_density)

    def __call__(self, ctx: StepContext, pos: Tensor, vel: Tensor) -> Tensor:
        """Pressure (N,) of every particle at ``(x**, v**)``."""
        s, c = ctx.settings, ctx.constants
        n_all, ptype, nf = pos.shape[0], ctx.state.ptype, ctx.n_fluid
        g_n = ctx.graph(pos, s.re_density)
        g_p = ctx.graph(pos, self.net.radius)
        with ctx.timer("pressure_net", pos.device):
            n = ops.number_density(
                pos, g_n.edge_index, ctx.radius(s.re_density), num_nodes=n_all, geometry=g_n.geometry
            )
            surface = ops.free_surface(n, c.n0, s.surface_beta)
            solved = ops.ppe_unknowns(ptype, surface)
            idx, edge_index, positions = induced_subgraph(g_p.edge_index, solved)
            m = idx.numel()
            inputs = pressure_inputs(
                vel.index_select(0, idx),
                n.index_select(0, idx),
                c.n0,
                idx < nf,
                edge_index,
                g_p.dist.index_select(0, positions),
                ctx.radius(self.net.radius),
                _net_dtype(self.net),
            )
            p = self.net.predict(*inputs)
            pressure = torch.zeros(n_all, dtype=pos.dtype, device=pos.device)
            pressure[idx] = p.to(pos.dtype)
        ctx.record(number_density=n, free_surface=surface, ppe_solved=solved)
        ctx.info.update(pressure_nodes=float(m), surface_particles=surface[:nf].sum())
        return pressure
