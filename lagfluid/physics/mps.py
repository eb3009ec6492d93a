"""Exact (ground-truth) stages of the MPS solver: viscosity + gravity, the collision rule, the PPE.

Koshizuka & Oka (1996) with the pressure solver of Lee et al. (2011), as in the FGN authors' code
("MPS step"). Each class implements one stage protocol of
:mod:`lagfluid.physics.scheme`; the learned stages of FGN implement the same protocols.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from lagfluid.device_constants import device_constant
from lagfluid.physics import operators as ops
from lagfluid.physics.ppe import PPESystem, assemble_ppe, ppe_source, solve_ppe
from lagfluid.physics.scheme import stage_cutoff
from lagfluid.physics.settings import SolverSettings
from lagfluid.physics.step_context import StepContext
from lagfluid.state import ParticleType, SceneParams


class ExactAdvection:
    """``a_i = nu lap(v)_i + g`` for fluid particles (Laplacian model over ``re_laplacian``).

    With ``nu = 0`` no neighbour work is done at all.
    """

    def radii(self, settings: SolverSettings, params: SceneParams) -> tuple[float, ...]:
        """Radii (l0) this stage searches: the Laplacian's, only when the fluid is viscous."""
        return (settings.re_laplacian,) if params.viscosity > 0 else ()

    def __call__(self, ctx: StepContext, pos: Tensor, vel: Tensor) -> Tensor:
        """Acceleration (N_fluid, 3) at ``(x^n, v^n)``."""
        nf, params = ctx.n_fluid, ctx.params
        acc = device_constant(params.gravity, pos.dtype, pos.device).expand(nf, 3).clone()
        if params.viscosity > 0:
            g = ctx.graph(pos, ctx.settings.re_laplacian, fluid_targets_only=True)
            with ctx.timer("advection", pos.device):
                lap = ops.laplacian(
                    pos,
                    g.edge_index,
                    vel,
                    ctx.radius(ctx.settings.re_laplacian),
                    ctx.constants.n0_lap,
                    ctx.constants.lam,
                    dim=params.dim,
                    num_nodes=nf,
                    geometry=g.geometry,
                )
                acc += params.viscosity * lap
        return acc


class CollisionRule:
    """Elastic-collision correction of approaching pairs closer than ``re_collision``.

    For fluid ``i`` and non-dummy ``j`` with ``r_ij = x_j - x_i``, ``|r_ij| < re_col`` and
    ``(v_i - v_j).r_ij > 0`` (approaching)::

        v_i -= (1 + e)/2 * [(v_i - v_j).r_ij / |r_ij|^2] r_ij

    summed over all such ``j`` using the velocities before the collision (the authors' rule).
    """

    def radii(self, settings: SolverSettings, params: SceneParams) -> tuple[float, ...]:
        """Radii (l0) this stage searches."""
        return (settings.re_collision,)

    def __call__(self, ctx: StepContext, pos: Tensor, vel: Tensor) -> Tensor:
        """Corrected fluid velocities (N_fluid, 3) at ``(x*, v*)``."""
        nf = ctx.n_fluid
        g = ctx.graph(pos, ctx.settings.re_collision, fluid_targets_only=True)
        with ctx.timer("collision", pos.device):
            src, dst = g.edge_index
            v_new = vel[:nf].clone()
            if src.numel() == 0:  # nothing is close enough: no collision work at all
                ctx.info["collisions"] = 0.0
                return v_new
            # Masks, not selections: no data-dependent sizes, so no host synchronisation on CUDA; a pair
            # that does not collide adds an exact zero (few pairs are this close: the pass is short).
            approach = ((vel.index_select(0, dst) - vel.index_select(0, src)) * g.rel).sum(dim=1)
            hit = (approach > 0) & (ctx.state.ptype.index_select(0, src) != ParticleType.DUMMY)
            factor = 0.5 * (1.0 + ctx.settings.restitution) * approach / g.dist.square()
            factor = torch.where(hit, factor, torch.zeros_like(factor))  # also where dist = 0 gave 0 / 0
            v_new.index_add_(0, dst, -factor.unsqueeze(1) * g.rel)
            ctx.info["collisions"] = hit.sum()
        return v_new


@dataclass(frozen=True)
class PressureSystem:
    """The MPS pressure Poisson system ``A p = b`` at one set of positions, with the fields it was built from.

    Attributes:
        system: ``A`` on the unknowns (:class:`~lagfluid.physics.ppe.PPESystem`, K unknowns).
        source: (N,) the source ``b`` of every particle (restrict it with ``system.gather``).
        number_density: (N,) ``n`` at ``re_density``.
        free_surface: (N,) bool, ``n < beta n0`` (Dirichlet ``p = 0``).
        solved: (N,) bool, the unknowns (fluid and wall particles off the free surface).
    """

    system: PPESystem
    source: Tensor
    number_density: Tensor
    free_surface: Tensor
    solved: Tensor


def pressure_system(ctx: StepContext, pos: Tensor, vel: Tensor, *, check: bool = False) -> PressureSystem:
    """Assemble the MPS pressure Poisson system at ``(pos, vel)``: the one place the PPE is built.

    The exact pressure stage solves it; the PPE residual metric (paper eq. 31,
    :func:`lagfluid.physics.reference.ppe_relative_residual`) scores a pressure field against it.

    * free surface: ``n_i < beta n0`` (number density at ``re_density``, :func:`~.operators.free_surface`);
      such particles are Dirichlet ``p = 0``; dummy particles carry no pressure and only complete the walls'
      neighbourhoods;
    * source (Lee et al. 2011): ``b_i = -gamma_div div(v)_i / dt + gamma_n (n_i - n0) / (dt^2 n0)``;
    * matrix: the Laplacian model at ``re_laplacian`` (see :mod:`lagfluid.physics.ppe`).

    Args:
        ctx: the step context (settings, constants, neighbour graphs, timer).
        pos: (N, 3) positions of every particle (the pressure stage's ``x**``).
        vel: (N, 3) velocities (``v**``).
        check: validate the assembly's inputs (:func:`~lagfluid.physics.ppe.assemble_ppe`); the graphs of
            the context's own neighbour list need none (symmetric, sorted, no self loops by construction),
            so the solver skips it.

    Returns:
        The :class:`PressureSystem`.
    """
    s, c, params = ctx.settings, ctx.constants, ctx.params
    n_all, ptype = pos.shape[0], ctx.state.ptype
    g_lap = ctx.graph(pos, s.re_laplacian)
    g_n = ctx.graph(pos, s.re_density)
    g_div = ctx.graph(pos, s.re_gradient)
    with ctx.timer("pressure_assembly", pos.device):
        n = ops.number_density(
            pos, g_n.edge_index, ctx.radius(s.re_density), num_nodes=n_all, geometry=g_n.geometry
        )
        surface = ops.free_surface(n, c.n0, s.surface_beta)
        solve_mask = ops.ppe_unknowns(ptype, surface)
        div = ops.divergence(
            pos,
            g_div.edge_index,
            vel,
            ctx.radius(s.re_gradient),
            c.n0,
            dim=params.dim,
            num_nodes=n_all,
            geometry=g_div.geometry,
        )
        b = ppe_source(div, n, c.n0, params.dt, **s.ppe_source_weights(params.dt))
        coef = ops.laplacian_weights(g_lap.dist, ctx.radius(s.re_laplacian), c.n0_lap, c.lam, dim=params.dim)
        # Free-surface particles are Dirichlet p = 0; dummy particles are in neither mask, so the assembly
        # ignores them (they only complete the walls' number density).
        system = assemble_ppe(
            g_lap.edge_index,
            coef,
            solve_mask,
            params.density,
            dirichlet_mask=surface & (ptype != ParticleType.DUMMY),
            check=check,
        )
    return PressureSystem(system, b, n, surface, solve_mask)


class ExactPressure:
    """Pressure from the MPS pressure Poisson equation on the non-free-surface fluid and wall particles.

    The system is :func:`pressure_system`'s; it is solved by preconditioned CG, warm-started from the
    previous step's pressure.
    """

    def radii(self, settings: SolverSettings, params: SceneParams) -> tuple[float, ...]:
        """Radii (l0) this stage searches."""
        return (settings.re_laplacian, settings.re_density, settings.re_gradient)

    def __call__(self, ctx: StepContext, pos: Tensor, vel: Tensor) -> Tensor:
        """Pressure (N,) of every particle at ``(x**, v**)``."""
        s = ctx.settings
        ps = pressure_system(ctx, pos, vel)
        system, b, surface = ps.system, ps.source, ps.free_surface
        with ctx.timer("pressure_solve", pos.device):
            x0 = system.gather(ctx.state.pressure) if s.ppe_warm_start else None
            p, info = solve_ppe(
                system,
                system.gather(b),
                x0=x0,
                tol=s.ppe_tol,
                tol_mode=s.ppe_tol_mode,
                maxiter=s.ppe_maxiter,
                method=s.ppe_method,
            )
            pressure = system.scatter(torch.as_tensor(p, device=pos.device).to(pos.dtype))
        ctx.record(number_density=ps.number_density, free_surface=surface, ppe_solved=ps.solved)
        ctx.info.update(
            ppe_iterations=float(info.iterations),
            ppe_residual=float(info.residual),
            ppe_converged=float(info.converged),
            ppe_unknowns=float(system.num_unknowns),
            surface_particles=surface[: ctx.n_fluid].sum(),
        )
        return pressure


def exact_cutoff(settings: SolverSettings, params: SceneParams) -> float:
    """Neighbour cutoff (in l0) of the MPS solver: :func:`~.scheme.stage_cutoff` of the exact stages."""
    return stage_cutoff(settings, params, ExactAdvection(), CollisionRule(), ExactPressure())
