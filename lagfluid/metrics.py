"""Accuracy and physics metrics of particle fields, with the same definitions for every simulator.

Field metrics of one frame (README "Metrics"), evaluated on the fluid particles that are *not* on the free
surface (``n_i >= beta n0``), because at the surface a deficient number density is geometry, not
compression:

* density error: ``mean_i |n_i / n0 - 1|`` with ``n_i`` the MPS number density at ``re_density`` (2.1 l0)
  and ``n0`` the ideal-lattice value;
* velocity divergence: ``mean_i |div(v)_i|`` in 1/s, the MPS divergence at ``re_gradient``.

Comparisons of a prediction with a reference (paper section 4 "Metrics", LagrangeBench):

* :func:`chamfer_distance`: asymmetric Chamfer distance, paper eq. 29 (no correspondence needed);
* :func:`position_mse`: mean squared position error per coordinate, LagrangeBench's ``mse`` (particles keep
  their index, so particle ``i`` of one rollout is particle ``i`` of the other);
* :func:`kinetic_energy` and :func:`relative_error`: relative error of the total fluid kinetic energy;
* :func:`normalized_mae`: normalised mean absolute error, paper eqs. 30 and 32;
* :func:`ppe_relative_residual`: relative residual of a pressure field in the discretised pressure Poisson
  equation, paper eq. 31, assembled exactly as the MPS solver's pressure stage assembles it.

Over a run, "mean" is the mean of the per-frame values and "max" their maximum (:func:`summarize`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from lagfluid.errors import LagfluidError
from lagfluid.neighbor_list import VerletNeighborList
from lagfluid.neighbors import edge_vectors, radius_graph
from lagfluid.physics import operators as ops
from lagfluid.physics.mps import CollisionRule, ExactAdvection, ExactPressure
from lagfluid.physics.ppe import PPESystem, assemble_ppe, ppe_residual, ppe_source
from lagfluid.physics.stages import (
    MPSConstants,
    SolverSettings,
    SplitStepSimulator,
    StageTimer,
    StepContext,
    initial_constants,
    lattice_constants,
)
from lagfluid.state import ParticleState, ParticleType

ArrayLike = np.ndarray | Tensor


class MetricInputError(LagfluidError, ValueError):
    """Arrays given to a metric have the wrong shape, are empty or do not correspond."""


def _as_f64(values: ArrayLike, name: str) -> np.ndarray:
    """A float64 numpy copy of a tensor or array (metrics are accumulated in double precision)."""
    if isinstance(values, Tensor):
        values = values.detach().cpu().numpy()
    out = np.asarray(values, dtype=np.float64)
    if not np.isfinite(out).all():
        raise MetricInputError(f"{name} contains NaN or Inf ({int((~np.isfinite(out)).sum())} entries)")
    return out


def _points(values: ArrayLike, name: str) -> np.ndarray:
    out = _as_f64(values, name)
    if out.ndim != 2 or out.shape[0] == 0:
        raise MetricInputError(f"{name} must be a non-empty (N, D) array of points, got shape {out.shape}")
    return out


def _corresponding(pred: ArrayLike, ref: ArrayLike, what: str) -> tuple[np.ndarray, np.ndarray]:
    a, b = _points(pred, f"predicted {what}"), _points(ref, f"reference {what}")
    if a.shape != b.shape:
        raise MetricInputError(
            f"predicted and reference {what} must correspond particle by particle (same shape), "
            f"got {a.shape} and {b.shape}"
        )
    return a, b


# ------------------------------------------------------------------------------------------- field metrics
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

    ``density_error = mean_i |n_i / n0 - 1|`` and ``velocity_divergence = mean_i |div(v)_i|`` (1/s) over
    the interior fluid particles ``i`` (fluid with ``n_i >= surface_beta * n0``), where
    ``n_i = sum_j w(r_ij)`` with ``w = re/r - 1`` at ``re_density`` and
    ``div(v)_i = d/n0 sum_j (v_j - v_i).(x_j - x_i) / r_ij^2 w(r_ij)`` at ``re_gradient``. Both are 0 (with
    ``interior_particles = 0``) when no fluid particle is interior.

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


def summarize(values: Iterable[float], finite_only: bool = False) -> dict[str, float]:
    """``{"mean": mean_t v_t, "max": max_t v_t}`` of per-frame values ``v_t`` (NaN when there are none).

    Args:
        values: one value per frame.
        finite_only: leave out NaN/inf frames (a metric undefined at some frames, e.g. a one-step metric at
            frame 0); otherwise a NaN frame makes the mean NaN.
    """
    vals = [float(v) for v in values]
    if finite_only:
        vals = [v for v in vals if math.isfinite(v)]
    if not vals:
        return {"mean": float("nan"), "max": float("nan")}
    t = torch.tensor(vals, dtype=torch.float64)
    return {"mean": float(t.mean()), "max": float(t.max())}


# ------------------------------------------------------------------------------------------- comparisons
def chamfer_distance(pred: ArrayLike, ref: ArrayLike) -> float:
    """Asymmetric Chamfer distance from ``pred`` to ``ref``, paper eq. 29.

    ``L(X, Y) = 1/|X| sum_{x in X} min_{y in Y} ||x - y||_2`` with ``X = pred``, ``Y = ref``: the mean over
    the predicted particles of the distance to the nearest reference particle, in the units of the input
    (the paper reports millimetres). Needs no particle correspondence; not symmetric.

    Args:
        pred: (N, D) predicted positions X.
        ref: (M, D) reference positions Y.

    Raises:
        MetricInputError: an empty or non-finite set, or different dimensions D.
    """
    x, y = _points(pred, "predicted positions"), _points(ref, "reference positions")
    if x.shape[1] != y.shape[1]:
        raise MetricInputError(f"point sets differ in dimension: {x.shape} and {y.shape}")
    return float(cKDTree(y).query(x, k=1)[0].mean())


def position_mse(pred: ArrayLike, ref: ArrayLike) -> float:
    """Mean squared position error per coordinate (LagrangeBench's ``mse``), m^2.

    ``MSE = 1/(N D) sum_i sum_k (x_ik - y_ik)^2`` for corresponding particles ``i`` (same index in both
    rollouts) and coordinates ``k``; the mean squared distance ``1/N sum_i ||x_i - y_i||^2`` is ``D`` times
    it.

    Args:
        pred: (N, D) predicted positions.
        ref: (N, D) reference positions of the same particles.
    """
    a, b = _corresponding(pred, ref, "positions")
    return float(np.mean((a - b) ** 2))


def mse_horizons(
    steps: Sequence[int], values: Sequence[float], horizons: Iterable[int]
) -> dict[str, dict[str, float]]:
    """Position MSE at fixed rollout horizons, where the run has them.

    Returns ``{"at_step": {h: MSE(h)}, "mean_to_step": {h: mean of MSE(s) over stored steps 0 < s <= h}}`` for
    every horizon ``h`` that is a stored step (LagrangeBench's ``mse{h}`` is the second, over every step).

    Args:
        steps: (T,) step index of each stored frame, increasing.
        values: (T,) per-frame MSE.
        horizons: steps of interest, e.g. 1, 10, 50, 100.
    """
    if len(steps) != len(values):
        raise MetricInputError(f"steps and values differ in length: {len(steps)} and {len(values)}")
    at = dict(zip((int(s) for s in steps), (float(v) for v in values), strict=True))
    out: dict[str, dict[str, float]] = {"at_step": {}, "mean_to_step": {}}
    for h in horizons:
        h = int(h)
        if h < 1:
            raise MetricInputError(f"horizons must be steps >= 1, got {h}")
        if h not in at:
            continue
        out["at_step"][str(h)] = at[h]
        out["mean_to_step"][str(h)] = float(np.mean([v for s, v in at.items() if 0 < s <= h]))
    return out


def kinetic_energy(vel: ArrayLike, particle_mass: float) -> float:
    """Total kinetic energy ``E = 1/2 m sum_i ||v_i||^2`` of the fluid particles, J.

    Args:
        vel: (N, D) fluid velocities, m/s.
        particle_mass: mass m of one particle, kg (``rho l0^dim`` for a lattice of spacing l0).
    """
    v = _as_f64(vel, "velocities")
    if v.ndim != 2:
        raise MetricInputError(f"velocities must be an (N, D) array, got shape {v.shape}")
    if not (math.isfinite(particle_mass) and particle_mass > 0):
        raise MetricInputError(f"particle_mass must be finite and > 0, got {particle_mass!r}")
    return float(0.5 * particle_mass * np.sum(v * v))


def relative_error(pred: float, ref: float) -> float:
    """``|pred - ref| / |ref|``; 0 when both are 0 and inf when only ``ref`` is (the ratio is undefined).

    Used per frame for the kinetic energy: ``e_KE(t) = |E_pred(t) - E_ref(t)| / E_ref(t)``.
    """
    if ref == 0:
        return 0.0 if pred == 0 else math.inf
    return abs(pred - ref) / abs(ref)


def normalized_mae(pred: ArrayLike, target: ArrayLike) -> float:
    """Normalised mean absolute error of a prediction, paper eq. 30 (scalars) and eq. 32 (vectors).

    * scalars, (N,): ``L = 1/N sum_i |y^_i - y_i| / |y_i|`` (eq. 30);
    * vectors, (N, D): ``L = 1/N sum_i ||y^_i - y_i||_2 / ||y_i||_2`` (eq. 32, e.g. the advection net's
      acceleration ``u_dot`` per particle).

    Entries whose target is exactly zero are left out of the mean (their ratio is undefined); NaN when no
    entry is left. A fraction, not a percentage.

    Args:
        pred: (N,) or (N, D) prediction ``y^``.
        target: same shape, ground truth ``y``.
    """
    a, b = _as_f64(pred, "prediction"), _as_f64(target, "target")
    if a.shape != b.shape or a.ndim not in (1, 2) or a.shape[0] == 0:
        raise MetricInputError(
            "prediction and target must have the same non-empty (N,) or (N, D) shape, "
            f"got {a.shape} and {b.shape}"
        )
    if a.ndim == 1:
        err, scale = np.abs(a - b), np.abs(b)
    else:
        err, scale = np.linalg.norm(a - b, axis=1), np.linalg.norm(b, axis=1)
    keep = scale > 0
    if not keep.any():
        return float("nan")
    return float(np.mean(err[keep] / scale[keep]))


# ------------------------------------------------------------------------------------------- PPE residual
def mps_constants(state: ParticleState, settings: SolverSettings) -> MPSConstants:
    """``n0``, ``n0_lap``, ``lambda`` as the MPS solver takes them (``settings.n0_from``) for this scene."""
    if settings.n0_from == "lattice":
        return lattice_constants(state.params.l0, settings, state.params.dim)
    return initial_constants(state, settings)


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


def mps_neighbor_list(state: ParticleState, settings: SolverSettings) -> VerletNeighborList:
    """A Verlet list with the MPS solver's cutoff, skin, backend and wall hops (so the same wall targets)."""
    mps = SplitStepSimulator("mps", settings, ExactAdvection(), CollisionRule(), ExactPressure())
    l0 = state.params.l0
    cutoff = mps.cutoff(state.params) * l0
    skin = settings.neighbor_skin_fraction * cutoff
    return VerletNeighborList(cutoff, skin, settings.neighbor_backend, settings.wall_hops)


def exact_ppe(ctx: StepContext) -> tuple[PPESystem, Tensor]:
    """The MPS pressure Poisson system ``A p = b`` at ``ctx.state``, as the exact pressure stage builds it.

    Mirrors :class:`lagfluid.physics.mps.ExactPressure`: free surface ``n_i < beta n0`` (Dirichlet ``p = 0``),
    unknowns the non-free-surface fluid and wall particles (walls within the solver's wall hops), source
    ``b_i = -gamma_div div(v)_i / dt + gamma_n (n_i - n0) / (dt^2 n0)``, matrix the Laplacian model at
    ``re_laplacian`` (:func:`lagfluid.physics.ppe.assemble_ppe`).

    Args:
        ctx: context at the pressure stage's input ``(x**, v**)`` (see :func:`exact_context`).

    Returns:
        The assembled system and the source ``b`` (N,) of every particle.
    """
    s, c, params = ctx.settings, ctx.constants, ctx.params
    pos, vel, ptype = ctx.state.pos, ctx.state.vel, ctx.state.ptype
    n_all = pos.shape[0]
    g_lap = ctx.graph(pos, s.re_laplacian)
    g_n = ctx.graph(pos, s.re_density)
    g_div = ctx.graph(pos, s.re_gradient)
    n = ops.number_density(
        pos, g_n.edge_index, ctx.radius(s.re_density), num_nodes=n_all, geometry=g_n.geometry
    )
    surface = n < s.surface_beta * c.n0
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
    system = assemble_ppe(
        g_lap.edge_index,
        coef,
        (ptype != ParticleType.DUMMY) & ~surface,
        params.density,
        dirichlet_mask=surface & (ptype != ParticleType.DUMMY),
    )
    return system, b


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
    """
    n_all = ctx.state.pos.shape[0]
    if not isinstance(pressure, Tensor) or pressure.shape != (n_all,):
        raise MetricInputError(
            f"pressure must be an ({n_all},) tensor, one value per particle, "
            f"got {getattr(pressure, 'shape', None)}"
        )
    system, b = exact_ppe(ctx)
    return ppe_residual(system, system.gather(pressure.to(b.dtype)), system.gather(b))
