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
* :func:`kinetic_energy` and :func:`kinetic_energy_error`: the error of the total fluid kinetic energy
  relative to the reference's peak kinetic energy over the run;
* :func:`normalized_mae`: normalised mean absolute error, paper eqs. 30 and 32.

The PPE residual of a pressure field (paper eq. 31) is scored in the exact MPS system: it is a one-step
reference of that solver and lives with it (:func:`lagfluid.physics.reference.ppe_relative_residual`).

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

from lagfluid.errors import MetricInputError
from lagfluid.neighbors import edge_vectors, radius_graph
from lagfluid.physics import operators as ops
from lagfluid.state import ParticleType

__all__ = [
    "FieldMetrics",
    "MetricInputError",
    "chamfer_distance",
    "field_metrics",
    "kinetic_energy",
    "kinetic_energy_error",
    "mse_horizons",
    "normalized_mae",
    "position_mse",
    "summarize",
]

ArrayLike = np.ndarray | Tensor


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
    interior = fluid & ~ops.free_surface(n, n0, surface_beta)
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


def kinetic_energy_error(pred: Sequence[float], ref: Sequence[float]) -> list[float]:
    """Kinetic-energy error relative to the reference peak, ``|E_pred(t) - E_ref(t)| / max_s E_ref(s)``.

    A fraction. The scale is the largest kinetic energy the reference reaches over the frames given, not
    ``E_ref(t)`` itself: a dam break starts at rest, so a per-frame ratio divides by almost zero near
    ``t = 0`` (598 % at step 1 for a few millijoules). When the reference never moves (peak 0), a frame is 0
    where the prediction is at rest too and inf where it is not (no scale to compare with).

    Args:
        pred: (T,) predicted kinetic energy per frame, J.
        ref: (T,) reference kinetic energy at the same frames, J.
    """
    a, b = _as_f64(pred, "predicted kinetic energy"), _as_f64(ref, "reference kinetic energy")
    if a.shape != b.shape or a.ndim != 1:
        raise MetricInputError(
            f"kinetic energies must be two (T,) series of one length, got shapes {a.shape} and {b.shape}"
        )
    err = np.abs(a - b)
    peak = float(b.max()) if b.size else 0.0
    if peak > 0:
        return (err / peak).tolist()
    return [0.0 if e == 0 else math.inf for e in err.tolist()]


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
