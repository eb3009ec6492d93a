"""One-step references of the exact MPS solver, to score a simulator's stages against (paper section 4).

A learned (or any other) stage is scored at the state where it acts by the exact computation there: the
PPE residual of its pressure (paper eq. 31) in the system the MPS pressure stage would solve
(:func:`lagfluid.physics.mps.pressure_system`, the one place it is assembled), evaluated with the MPS
solver's own constants and neighbour list. The field metrics themselves (:mod:`lagfluid.metrics`) know no
simulator.
"""

from __future__ import annotations

from torch import Tensor

from lagfluid.errors import MetricInputError
from lagfluid.neighbors.verlet import VerletNeighborList
from lagfluid.physics.mps import exact_cutoff, pressure_system
from lagfluid.physics.ppe import PPESystem, ppe_residual
from lagfluid.physics.settings import MPSConstants, SolverSettings, scene_constants
from lagfluid.physics.step_context import StepContext, neighbor_list
from lagfluid.physics.timing import StageTimer
from lagfluid.state import ParticleState

__all__ = ["exact_context", "exact_ppe", "mps_constants", "mps_neighbor_list", "ppe_relative_residual"]


def mps_constants(state: ParticleState, settings: SolverSettings) -> MPSConstants:
    """``n0``, ``n0_lap``, ``lambda`` as the MPS solver takes them (``settings.n0_from``) for this scene."""
    return scene_constants(state, settings)


def mps_neighbor_list(state: ParticleState, settings: SolverSettings) -> VerletNeighborList:
    """A Verlet list with the MPS solver's cutoff, skin, backend and wall hops (so the same wall targets)."""
    return neighbor_list(settings, exact_cutoff(settings, state.params), state.params.l0)


def exact_context(
    state: ParticleState,
    settings: SolverSettings,
    constants: MPSConstants,
    neighbors: VerletNeighborList | None = None,
) -> StepContext:
    """A step context at ``state`` with the MPS solver's neighbour list, to evaluate exact stages there.

    Args:
        state: positions, velocities and types where the stages are evaluated.
        settings: solver settings (radii, wall hops, skin, backend).
        constants: MPS constants of the scene.
        neighbors: a neighbour list to reuse across calls (it rebuilds itself when needed and its graphs are
            exact at any positions); a fresh one at the MPS solver's cutoff when None.
    """
    if neighbors is None:
        neighbors = mps_neighbor_list(state, settings)
    return StepContext(state, settings, constants, neighbors, StageTimer())


def exact_ppe(ctx: StepContext) -> tuple[PPESystem, Tensor]:
    """The MPS pressure Poisson system ``A p = b`` at ``ctx.state``, as the exact pressure stage builds it.

    :func:`lagfluid.physics.mps.pressure_system` at ``(ctx.state.pos, ctx.state.vel)``, its inputs checked
    (the state may come from any simulator).

    Args:
        ctx: context at the pressure stage's input ``(x**, v**)`` (see :func:`exact_context`).

    Returns:
        The assembled system and the source ``b`` (N,) of every particle.
    """
    built = pressure_system(ctx, ctx.state.pos, ctx.state.vel, check=True)
    return built.system, built.source


def ppe_relative_residual(ctx: StepContext, pressure: Tensor) -> float:
    """Relative residual of a pressure field in the discretised PPE, paper eq. 31.

    ``tol = ||A p - b||_2 / ||b||_2`` with ``A``, ``b`` the exact MPS system at ``ctx.state``
    (:func:`exact_ppe`) and ``p`` the given pressure restricted to its unknowns (the pressure stage's
    output before the negative-pressure clamp). 0 for the exact solution, 1 for ``p = 0``, ``|a|`` for
    ``(1 + a) p_exact``. When ``b = 0`` the absolute ``||A p||`` is returned (as
    :func:`lagfluid.physics.ppe.ppe_residual`).

    Args:
        ctx: context at the pressure stage's input ``(x**, v**)``.
        pressure: (N,) pressure of every particle.

    Raises:
        MetricInputError: when ``pressure`` is not one value per particle.
    """
    n_all = ctx.state.pos.shape[0]
    if not isinstance(pressure, Tensor) or pressure.shape != (n_all,):
        raise MetricInputError(
            f"pressure must be an ({n_all},) tensor, one value per particle, "
            f"got {getattr(pressure, 'shape', None)}"
        )
    system, b = exact_ppe(ctx)
    return ppe_residual(system, system.gather(pressure.to(b.dtype)), system.gather(b))
