"""MPS particle operators as pure torch functions.

Every function takes positions, a radius graph and (where needed) values, and returns per-particle
results; nothing is stored between calls, and tensors stay on the device and in the dtype they came
in (float32 or float64, CPU or CUDA).

Graph convention (the whole project's): ``edge_index`` has shape (2, E), int64, with
``edge_index[0] = j`` the source (neighbour) and ``edge_index[1] = i`` the target (centre); no self
loops; every ordered pair within the radius that the caller wants summed. Sums run over the
neighbours of each target ``i``. A graph may hold edges into a subset of particles only (for example
only fluid particles receive edges): rows without incoming edges get 0.

Radii ``re`` are metres (callers pass a factor times ``l0``). ``dim`` is the spatial dimension ``d``
of the MPS model (3 by default; positions are always (N, 3), with z = 0 for 2-D scenes).

The MPS weight (Koshizuka & Oka 1996) is ``w(r) = re / r - 1`` for ``1e-8 < r < re`` and 0 otherwise.
"""

from __future__ import annotations

from types import ModuleType

import numpy as np
import torch
from torch import Tensor

from lagfluid.neighbors import pair_kernels
from lagfluid.neighbors.csr import sorted_rows
from lagfluid.neighbors.geometry import edge_vectors
from lagfluid.neighbors.pair_kernels import backend_for
from lagfluid.state import ParticleType

__all__ = [
    "corrected_pressure_gradient",
    "divergence",
    "edge_geometry",
    "free_surface",
    "gradient",
    "kernel",
    "laplacian",
    "laplacian_lambda",
    "laplacian_weights",
    "min_pressure_gradient",
    "number_density",
    "ppe_unknowns",
    "reference_density",
]

# Pairs closer than this (m) get weight 0: the authors' guard against coincident particles.
_R_MIN = 1e-8


def kernel(dist: Tensor, re: float) -> Tensor:
    """MPS weight function.

    ``w(r) = re / r - 1`` for ``1e-8 < r < re``, else 0. The weight is 1 at ``r = re / 2`` and
    decays continuously to 0 at ``re``.

    Args:
        dist: pair distances ``r_ij``, shape (E,), metres.
        re: kernel radius, metres.

    Returns:
        Weights ``w_ij``, shape (E,), same dtype and device as ``dist``. Differentiable w.r.t. ``dist``
        (no NaN gradients at the excluded pairs).
    """
    return backend_for("mps_kernel", dist)(dist, re)


def _kernel_torch(dist: Tensor, re: float) -> Tensor:
    """:func:`kernel` in torch operations (any device, differentiable)."""
    valid = (dist > _R_MIN) & (dist < re)
    if not (dist.requires_grad and torch.is_grad_enabled()):
        # The same numbers in fewer passes (the solver's hot path): ``re / t`` on a tensor is evaluated as
        # ``t.reciprocal() * re``, and masked entries are set to 0 afterwards instead of substituted before.
        return dist.reciprocal().mul_(re).sub_(1.0).masked_fill_(~valid, 0.0)
    # Substitute a harmless distance where the weight is masked out so that neither the value nor its
    # gradient sees re / 0.
    safe = torch.where(valid, dist, torch.full_like(dist, re))
    return torch.where(valid, re / safe - 1.0, torch.zeros_like(dist))


Geometry = tuple[Tensor, Tensor]
"""``(rel (E, 3), dist (E,))`` of a graph, as :func:`edge_geometry` returns them."""


def edge_geometry(pos: Tensor, edge_index: Tensor, geometry: Geometry | None = None) -> Geometry:
    """Relative positions and distances of the edges.

    Every operator takes an optional ``geometry`` keyword: a caller that already holds ``rel`` and ``dist``
    of its graph (the solver does, from its neighbour list) passes them in, and the operator skips the
    gather of ``pos`` over all edges (see ``benchmarks/results/operators.md``).

    Args:
        pos: positions, shape (N, 3).
        edge_index: (2, E) int64, ``[j, i]`` = [source, target].
        geometry: precomputed ``(rel, dist)`` of exactly these edges; returned as is when given.

    Returns:
        ``rel = x_j - x_i``, shape (E, 3), and ``dist = |x_j - x_i|``, shape (E,).
    """
    if geometry is not None:
        return geometry
    # The neighbour search's own formula, so a distance is the same number wherever it is computed.
    return edge_vectors(pos, edge_index)


def _num_nodes(pos: Tensor, num_nodes: int | None) -> int:
    return int(pos.shape[0]) if num_nodes is None else int(num_nodes)


def _scatter_sum(msg: Tensor, index: Tensor, num_nodes: int) -> Tensor:
    """Sum edge messages (E, ...) into their targets: (num_nodes, ...), zero where no edge arrives."""
    out = msg.new_zeros((num_nodes, *msg.shape[1:]))
    return out.index_add(0, index, msg)


def _gradient_terms(pos: Tensor, edge_index: Tensor, re: float, geometry: Geometry | None = None) -> Tensor:
    """Per-edge vectors ``(x_j - x_i) / r_ij^2 * w_ij``, shape (E, 3)."""
    rel, dist = edge_geometry(pos, edge_index, geometry)
    w = kernel(dist, re)
    # w is 0 wherever dist <= 1e-8, so the clamp only keeps 0 / 0 out of the product.
    return rel * (w / dist.clamp_min(_R_MIN).square()).unsqueeze(-1)


def number_density(
    pos: Tensor,
    edge_index: Tensor,
    re: float,
    num_nodes: int | None = None,
    *,
    geometry: Geometry | None = None,
) -> Tensor:
    """MPS particle number density.

    ``n_i = sum_{j != i} w(r_ij)``.

    Args:
        pos: positions, shape (N, 3).
        edge_index: (2, E) int64, ``[j, i]``.
        re: kernel radius, metres.
        num_nodes: number of output rows (default ``N``).
        geometry: optional precomputed ``(rel, dist)`` of these edges (see :func:`edge_geometry`).

    Returns:
        Number densities, shape (N,). Rows without incoming edges are 0.
    """
    _, dist = edge_geometry(pos, edge_index, geometry)
    density = backend_for("number_density", dist)
    return density(edge_index, dist, re, _num_nodes(pos, num_nodes), pos.shape[0])


def _number_density_torch(
    edge_index: Tensor, dist: Tensor, re: float, num_nodes: int, num_sources: int
) -> Tensor:
    """:func:`number_density` from the edge distances (E,) in torch operations: (num_nodes,)."""
    return _scatter_sum(kernel(dist, re), edge_index[1], num_nodes)


def _masked_argmax(n: Tensor, mask: Tensor | None) -> Tensor:
    """Index (0-dim int64) of the largest ``n`` among the masked rows (first one on ties)."""
    if mask is None:
        if n.numel() == 0:
            raise ValueError("cannot take a reference density over zero particles")
        return torch.argmax(n)
    mask = torch.as_tensor(mask, device=n.device)
    if mask.dtype != torch.bool or mask.shape != n.shape:
        raise ValueError(
            f"mask must be a bool tensor of shape {tuple(n.shape)}, got {mask.dtype} {tuple(mask.shape)}"
        )
    if not bool(mask.any()):
        raise ValueError("mask selects no particle: cannot take a reference density")
    return torch.argmax(torch.where(mask, n, torch.full_like(n, -torch.inf)))


def free_surface(n: Tensor, n0: float, beta: float) -> Tensor:
    """The MPS free-surface rule: ``n_i < beta n0``.

    A particle whose number density falls below ``beta n0`` has neighbours missing on one side: it is on the
    free surface (Dirichlet ``p = 0`` in the PPE), and its density deficit is geometry, not compression (the
    field metrics leave it out). Written once here for the solver, the learned pressure stage and the
    metrics.

    Args:
        n: number densities, shape (N,), at the density radius ``re_density``.
        n0: reference number density at that radius.
        beta: threshold, in (0, 1] (the authors: 0.97).

    Returns:
        Bool (N,), True on the free surface.

    Raises:
        ValueError: when ``beta`` is outside (0, 1].
    """
    if not 0 < beta <= 1:
        raise ValueError(f"the free-surface threshold beta must be in (0, 1], got {beta!r}")
    return n < beta * n0


def ppe_unknowns(ptype: Tensor, surface: Tensor) -> Tensor:
    """The pressure unknowns: fluid and wall particles off the free surface.

    Free-surface particles are Dirichlet ``p = 0``; dummy particles carry no pressure (they only complete
    the walls' number density). The exact PPE solves for these particles, the learned pressure stage
    predicts for them.

    Args:
        ptype: (N,) particle types (:class:`~lagfluid.state.ParticleType`).
        surface: (N,) bool, the free surface (:func:`free_surface`).

    Returns:
        Bool (N,), True for an unknown.
    """
    if ptype.shape != surface.shape:
        raise ValueError(
            f"ptype and surface must have the same shape, got {tuple(ptype.shape)} and {tuple(surface.shape)}"
        )
    return (ptype != ParticleType.DUMMY) & ~surface


def reference_density(n: Tensor, mask: Tensor | None = None) -> Tensor:
    """Reference number density ``n0 = max_{i in mask} n_i``.

    The authors' ``n0``: the maximum number density over the fluid particles of the initial frame
    (an interior particle of the initial lattice, when there is one).

    Args:
        n: number densities, shape (N,).
        mask: bool (N,), the particles to take the maximum over (``None``: all).

    Returns:
        0-dim tensor (dtype and device of ``n``; call ``float()`` for a Python number).

    Raises:
        ValueError: when the mask selects no particle.
    """
    return n[_masked_argmax(n, mask)]


def laplacian_lambda(
    pos: Tensor,
    edge_index: Tensor,
    re: float,
    mask: Tensor | None = None,
    num_nodes: int | None = None,
    *,
    geometry: Geometry | None = None,
) -> tuple[Tensor, Tensor]:
    """Number density and ``lambda`` of the Laplacian model, at the densest masked particle.

    For every particle ``n_i = sum_j w_ij`` and ``lambda_i = sum_j r_ij^2 w_ij / sum_j w_ij`` (radius
    ``re``). The particle ``k`` with the largest ``n_i`` among the masked ones (the first such on ties)
    gives ``n0_lap = n_k`` and ``lambda = lambda_k``, so both constants describe one full neighbourhood
    (on a lattice, truncated neighbourhoods have smaller ``n_i`` and smaller ``lambda_i``: the missing
    neighbours are the far ones). On an interior simple-cubic lattice site with ``re = 3.1 l0``:
    ``n0_lap = 54.3212`` and ``lambda = 3.2434 l0^2``.

    Args:
        pos: positions, shape (N, 3).
        edge_index: (2, E) int64, ``[j, i]``, at least every pair within ``re`` into the masked rows.
        re: Laplacian kernel radius, metres.
        mask: bool (N,), candidate particles (``None``: all), typically the initial fluid.
        num_nodes: number of particles (default ``N``).
        geometry: optional precomputed ``(rel, dist)`` of these edges (see :func:`edge_geometry`).

    Returns:
        ``(n0_lap, lam)``: two 0-dim tensors (dtype and device of ``pos``); ``lam`` is in m^2.

    Raises:
        ValueError: when the mask selects no particle or the densest one has no neighbour.
    """
    _, dist = edge_geometry(pos, edge_index, geometry)
    w = kernel(dist, re)
    size = _num_nodes(pos, num_nodes)
    n = _scatter_sum(w, edge_index[1], size)
    r2w = _scatter_sum(dist.square() * w, edge_index[1], size)
    k = _masked_argmax(n, mask)
    n0_lap = n[k]
    if not bool(n0_lap > 0):
        raise ValueError("the densest masked particle has no neighbour within re: lambda is undefined")
    return n0_lap, r2w[k] / n0_lap


def gradient(
    pos: Tensor,
    edge_index: Tensor,
    values: Tensor,
    re: float,
    n0: float | Tensor,
    dim: int = 3,
    num_nodes: int | None = None,
    *,
    geometry: Geometry | None = None,
) -> Tensor:
    """MPS gradient of a scalar field.

    ``grad phi_i = d / n0 * sum_j (phi_j - phi_i) (x_j - x_i) / r_ij^2 * w_ij``.
    Exact for linear fields at particles with a full, symmetric lattice neighbourhood.

    Args:
        pos: positions, shape (N, 3).
        edge_index: (2, E) int64, ``[j, i]``.
        values: field ``phi``, shape (N,).
        re: kernel radius, metres.
        n0: reference number density at radius ``re``.
        dim: spatial dimension ``d``.
        num_nodes: number of output rows (default ``N``).
        geometry: optional precomputed ``(rel, dist)`` of these edges (see :func:`edge_geometry`).

    Returns:
        Gradient, shape (N, 3). Rows without incoming edges are 0.
    """
    src, dst = edge_index[0], edge_index[1]
    terms = _gradient_terms(pos, edge_index, re, geometry) * (
        values.index_select(0, src) - values.index_select(0, dst)
    ).unsqueeze(-1)
    return _scatter_sum(terms, dst, _num_nodes(pos, num_nodes)) * (dim / n0)


def min_pressure_gradient(
    pos: Tensor,
    edge_index: Tensor,
    pressure: Tensor,
    re: float,
    n0: float | Tensor,
    dim: int = 3,
    include_self: bool = True,
    num_nodes: int | None = None,
    *,
    geometry: Geometry | None = None,
    sources: Tensor | None = None,
) -> Tensor:
    """Stabilised MPS pressure gradient with the neighbourhood minimum pressure (Koshizuka & Oka).

    ``grad p_i = d / n0 * sum_j (p_j - p_min,i) (x_j - x_i) / r_ij^2 * w_ij`` with
    ``p_min,i = min(p_i, min_j p_j)`` (``include_self=True``, the authors' code) or ``min_j p_j``.

    With ``include_self`` every term is non-negative, so ``-grad p`` pushes a particle away from its
    neighbours (repulsive pairs: the scheme's stability). The result is invariant to adding a constant
    to ``p``. For a linear field ``a.x + b`` at a particle with a full, point-symmetric neighbourhood
    it equals ``a`` exactly (the extra ``(p_i - p_min,i)`` term multiplies
    ``sum_j (x_j - x_i) / r_ij^2 w_ij = 0``); at particles with a one-sided neighbourhood (free
    surface, walls) it differs from :func:`gradient`: for ``p = c z`` at the centre of a lattice's top
    face (radius 2.1 l0) it gives ``grad_z = -0.4896 c`` where :func:`gradient` gives ``+0.5 c``.
    Only the neighbours present in ``edge_index`` enter the minimum: leave out particles without pressure
    (dummy walls) with ``sources``.

    Args:
        pos: positions, shape (N, 3).
        edge_index: (2, E) int64, ``[j, i]``.
        pressure: pressure, shape (N,).
        re: kernel radius, metres.
        n0: reference number density at radius ``re``.
        dim: spatial dimension ``d``.
        include_self: include ``p_i`` in the neighbourhood minimum.
        num_nodes: number of output rows (default ``N``).
        geometry: optional precomputed ``(rel, dist)`` of these edges (see :func:`edge_geometry`).
        sources: optional (N,) bool, the particles that may be neighbours: edges from the others are left
            out, as if absent from ``edge_index``.

    Returns:
        Gradient, shape (N, 3). Rows without incoming edges are 0.
    """
    gradient = backend_for("min_pressure_gradient", pos, pressure, *(geometry or ()))
    return gradient(
        pos, edge_index, pressure, re, n0, dim, include_self, _num_nodes(pos, num_nodes), geometry, sources
    )


def _min_gradient_torch(
    pos: Tensor,
    edge_index: Tensor,
    pressure: Tensor,
    re: float,
    n0: float | Tensor,
    dim: int,
    include_self: bool,
    size: int,
    geometry: Geometry | None,
    sources: Tensor | None,
) -> Tensor:
    """:func:`min_pressure_gradient` in torch operations (any device, differentiable): (size, 3)."""
    if sources is not None:
        edge_index, geometry = _from_sources(edge_index, geometry, sources)
    src, dst = edge_index[0], edge_index[1]
    # Rows that receive no edge keep p_i; with include_self=False the others take min_j p_j only.
    p_min = pressure.scatter_reduce(
        0, dst, pressure.index_select(0, src), reduce="amin", include_self=include_self
    )
    terms = _gradient_terms(pos, edge_index, re, geometry) * (
        pressure.index_select(0, src) - p_min.index_select(0, dst)
    ).unsqueeze(-1)
    return _scatter_sum(terms, dst, size) * (dim / n0)


def _adjugate(m: Tensor) -> tuple[Tensor, Tensor]:
    """Adjugate (B, d, d) and determinant (B,) of a batch of 2 x 2 or 3 x 3 matrices (B, d, d)."""
    if m.shape[-1] == 2:
        a, b, c, e = m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1]
        adj = torch.stack([torch.stack([e, -b], -1), torch.stack([-c, a], -1)], -2)
        return adj, a * e - b * c
    rows = (m[:, 1].cross(m[:, 2], dim=-1), m[:, 2].cross(m[:, 0], dim=-1), m[:, 0].cross(m[:, 1], dim=-1))
    adj = torch.stack(rows, dim=-1)  # columns are the cross products of the rows: adj(m) = cof(m)^T
    return adj, (m[:, 0] * rows[0]).sum(dim=-1)


def corrected_pressure_gradient(
    pos: Tensor,
    edge_index: Tensor,
    pressure: Tensor,
    re: float,
    n0: float | Tensor,
    dim: int = 3,
    num_nodes: int | None = None,
    *,
    geometry: Geometry | None = None,
    min_determinant: float = 0.1,
) -> Tensor:
    """Pressure gradient exact for linear fields, stabilised only by what a linear field does not explain.

    The minimum-pressure gradient (:func:`min_pressure_gradient`) adds ``(p_i - p_min,i) s_i`` with
    ``s_i = d / n0 * sum_j (x_j - x_i) / r_ij^2 * w_ij`` to the plain gradient: a repulsion proportional to
    the pressure drop across the neighbourhood. Under hydrostatic load (``p_i - p_min,i`` ~ 2 rho g l0 at
    radius 2.1 l0) this repulsion makes the simple-cubic lattice shear-unstable: a column of particles
    displaced by ``delta`` along gravity gets an extra force of ~6.3 m/s^2 per l0 * delta *in the
    direction of the displacement* at g = 9.81 (``tests/test_operators.py``), which grows with an e-folding
    time of ~0.1 s at l0 = 0.05 m: the "resting" column's spurious motion. This variant:

    * ``G_i = M_i^-1 d / n0 * sum_j (p_j - p_i) (x_j - x_i) / r_ij^2 * w_ij`` with the corrective matrix
      ``M_i = d / n0 * sum_j (x_j - x_i) (x_j - x_i)^T / r_ij^2 * w_ij`` (Khayyer & Gotoh 2011): exact for
      any linear field at any particle with a non-degenerate neighbourhood (``det M_i >= min_determinant``;
      ``M = I`` in a full lattice, ~0.5 at a flat free surface);
    * neighbour pressures about that linear fit, ``q_j = p_j - G_i . (x_j - x_i)``, and
      ``p_ref,i = max(p_min,i, min(p_i, min_j q_j))``;
    * ``grad p_i = G_i + (p_i - p_ref,i) s_i``;
    * where ``det M_i < min_determinant`` (a splash, a thin sheet: too few directions to fit a plane), the
      authors' gradient :func:`min_pressure_gradient` unchanged.

    For a linear field every ``q_j = p_i``, so the repulsion vanishes and the gradient is exact; a pressure
    peak at ``i`` (two particles pressed together) still pushes them apart, by at most what the authors'
    minimum-pressure gradient would (``p_ref,i >= p_min,i``). With ``p = 0`` everywhere the result is 0 (free
    fall stays exact). Invariant to adding a constant to ``p``.

    Args:
        pos: positions, shape (N, 3).
        edge_index: (2, E) int64, ``[j, i]``; only its neighbours enter (drop dummy walls beforehand).
        pressure: pressure, shape (N,).
        re: kernel radius, metres.
        n0: reference number density at radius ``re``.
        dim: spatial dimension ``d`` (2: the correction acts in the x-y plane).
        num_nodes: number of output rows (default ``N``).
        geometry: optional precomputed ``(rel, dist)`` of these edges (see :func:`edge_geometry`).
        min_determinant: smallest ``det M_i`` (dimensionless, 1 in a full lattice) that is inverted.

    Returns:
        Gradient, shape (N, 3). Rows without incoming edges are 0.
    """
    src, dst = edge_index[0], edge_index[1]
    size = _num_nodes(pos, num_nodes)
    rel, dist = edge_geometry(pos, edge_index, geometry)
    terms = _gradient_terms(pos, edge_index, re, (rel, dist)) * (dim / n0)  # (E, 3)
    p_src, p_dst = pressure.index_select(0, src), pressure.index_select(0, dst)
    plain = _scatter_sum(terms * (p_src - p_dst).unsqueeze(-1), dst, size)  # (size, 3)
    moments = _scatter_sum(
        terms[:, :dim].unsqueeze(2) * rel[:, :dim].unsqueeze(1), dst, size
    )  # (size, dim, dim)
    adjugate, det = _adjugate(moments)
    invertible = det >= min_determinant
    # Explicit inverse of the small matrices: cheaper than batched det + solve, and not this operator's cost
    # (its extra passes over the edges are; see benchmarks/results/operators.md).
    solved = (adjugate @ plain[:, :dim].unsqueeze(-1)).squeeze(-1) / torch.where(
        invertible, det, 1.0
    ).unsqueeze(-1)
    linear = plain.clone()
    linear[:, :dim] = torch.where(invertible.unsqueeze(-1), solved, plain[:, :dim])
    p_i = pressure[:size]
    p_min = p_i.scatter_reduce(0, dst, p_src, reduce="amin", include_self=True)
    about_fit = p_src - (linear.index_select(0, dst) * rel).sum(dim=1)
    p_fit_min = p_i.scatter_reduce(0, dst, about_fit, reduce="amin", include_self=True)
    # Degenerate neighbourhoods (a splash, a thin sheet) keep the authors' gradient: plain + minimum.
    p_ref = torch.where(invertible, torch.maximum(p_min, p_fit_min), p_min)
    return linear + (p_i - p_ref).unsqueeze(-1) * _scatter_sum(terms, dst, size)


def divergence(
    pos: Tensor,
    edge_index: Tensor,
    vel: Tensor,
    re: float,
    n0: float | Tensor,
    dim: int = 3,
    num_nodes: int | None = None,
    *,
    geometry: Geometry | None = None,
) -> Tensor:
    """MPS divergence of a vector field.

    ``div v_i = d / n0 * sum_j (v_j - v_i) . (x_j - x_i) / r_ij^2 * w_ij``.
    Exact (``trace(M)``) for linear fields ``M x + c`` at particles with a full lattice neighbourhood.
    (The authors' GPU kernel multiplies the z-velocity difference by the y-offset; that defect is not
    reproduced.)

    Args:
        pos: positions, shape (N, 3).
        edge_index: (2, E) int64, ``[j, i]``.
        vel: vector field, shape (N, 3).
        re: kernel radius, metres.
        n0: reference number density at radius ``re``.
        dim: spatial dimension ``d``.
        num_nodes: number of output rows (default ``N``).
        geometry: optional precomputed ``(rel, dist)`` of these edges (see :func:`edge_geometry`).

    Returns:
        Divergence, shape (N,). Rows without incoming edges are 0.
    """
    src, dst = edge_index[0], edge_index[1]
    terms = (
        _gradient_terms(pos, edge_index, re, geometry) * (vel.index_select(0, src) - vel.index_select(0, dst))
    ).sum(dim=-1)
    return _scatter_sum(terms, dst, _num_nodes(pos, num_nodes)) * (dim / n0)


def laplacian_weights(
    dist: Tensor, re: float, n0_lap: float | Tensor, lam: float | Tensor, dim: int = 3
) -> Tensor:
    """Per-edge coefficients of the MPS Laplacian model.

    ``c_ij = 2d / (lambda n0_lap) * w(r_ij)``, so that ``lap phi_i = sum_j c_ij (phi_j - phi_i)``.
    The pressure Poisson matrix is assembled from the same coefficients, so the Laplacian model lives in
    one place.

    Args:
        dist: pair distances, shape (E,), metres.
        re: Laplacian kernel radius, metres.
        n0_lap: reference number density at radius ``re``.
        lam: ``lambda`` of the Laplacian model, m^2 (see :func:`laplacian_lambda`).
        dim: spatial dimension ``d``.

    Returns:
        Coefficients, shape (E,), in 1/m^2.
    """
    return kernel(dist, re) * (2.0 * dim / (lam * n0_lap))


def laplacian(
    pos: Tensor,
    edge_index: Tensor,
    values: Tensor,
    re: float,
    n0_lap: float | Tensor,
    lam: float | Tensor,
    dim: int = 3,
    num_nodes: int | None = None,
    *,
    geometry: Geometry | None = None,
) -> Tensor:
    """MPS Laplacian model.

    ``lap phi_i = 2d / (lambda n0_lap) * sum_j (phi_j - phi_i) w_ij``.
    Exact for quadratic fields at particles with a full lattice neighbourhood (with the lattice's
    ``n0_lap`` and ``lambda``).

    Args:
        pos: positions, shape (N, 3).
        edge_index: (2, E) int64, ``[j, i]``.
        values: field, shape (N,) or (N, C) (column-wise, e.g. a velocity).
        re: Laplacian kernel radius, metres.
        n0_lap: reference number density at radius ``re``.
        lam: ``lambda`` of the Laplacian model, m^2.
        dim: spatial dimension ``d``.
        num_nodes: number of output rows (default ``N``).
        geometry: optional precomputed ``(rel, dist)`` of these edges (see :func:`edge_geometry`).

    Returns:
        Laplacian, same trailing shape as ``values``: (N,) or (N, C). Rows without incoming edges are 0.
    """
    _, dist = edge_geometry(pos, edge_index, geometry)
    body = backend_for("laplacian", values, dist)
    return body(edge_index, dist, values, re, n0_lap, lam, dim, _num_nodes(pos, num_nodes))


def _laplacian_torch(
    edge_index: Tensor,
    dist: Tensor,
    values: Tensor,
    re: float,
    n0_lap: float | Tensor,
    lam: float | Tensor,
    dim: int,
    num_nodes: int,
) -> Tensor:
    """:func:`laplacian` from the edge distances (E,) in torch operations (any device, differentiable)."""
    src, dst = edge_index[0], edge_index[1]
    coef = laplacian_weights(dist, re, n0_lap, lam, dim)
    diff = values.index_select(0, src) - values.index_select(0, dst)
    terms = diff * coef.view(-1, *([1] * (diff.dim() - 1)))
    return _scatter_sum(terms, dst, num_nodes)


# ------------------------------------------------------------------------------------------ CPU fast paths
def _operator_kernels() -> ModuleType:
    """The Numba kernels of the operators (a compiled body runs only where they load)."""
    return pair_kernels.load(_NUMBA)


def _from_sources(
    edge_index: Tensor, geometry: Geometry | None, sources: Tensor
) -> tuple[Tensor, Geometry | None]:
    """The edges (and their geometry) whose source has ``sources[j]`` True."""
    keep = torch.nonzero(sources.index_select(0, edge_index[0])).flatten()
    picked = (
        None if geometry is None else (geometry[0].index_select(0, keep), geometry[1].index_select(0, keep))
    )
    return edge_index.index_select(1, keep), picked


def _min_gradient_compiled(
    pos: Tensor,
    edge_index: Tensor,
    pressure: Tensor,
    re: float,
    n0: float | Tensor,
    dim: int,
    include_self: bool,
    size: int,
    geometry: Geometry | None,
    sources: Tensor | None,
) -> Tensor:
    """:func:`min_pressure_gradient` in one compiled pass per target row.

    As :func:`_laplacian_compiled`: edges sorted by target, a Python ``n0``, ``pressure`` in the positions'
    dtype (the torch body takes the rest). The torch body's numbers to the bit without its (E, 3)
    temporaries, the scatter of the minimum and the selection of the edges from ``sources`` (a pass over
    every edge of the step's largest graph; ``benchmarks/results/fgn_speed.md``).
    """
    args = (pos, edge_index, pressure, re, n0, dim, include_self, size, geometry, sources)
    if isinstance(n0, Tensor) or pressure.dtype != pos.dtype or size > pressure.shape[0]:
        return _min_gradient_torch(*args)
    rows = sorted_rows(edge_index, pressure.shape[0], size)
    if rows is None:
        return _min_gradient_torch(*args)
    _, src, row_ptr = rows
    rel, dist = edge_geometry(pos, edge_index, geometry)
    p = pressure.detach().contiguous().numpy()
    mask = sources.contiguous().numpy() if sources is not None else np.ones(1, dtype=np.bool_)
    out = np.empty((size, rel.shape[1]), dtype=p.dtype)
    t = p.dtype.type  # torch rounds Python scalars to the tensor's dtype
    r, d = rel.detach().contiguous().numpy(), dist.detach().contiguous().numpy()
    _operator_kernels().min_gradient_rows(
        src, r, d, p, mask, sources is not None, row_ptr, t(re), t(_R_MIN), t(dim / n0), include_self, out
    )
    return torch.from_numpy(out)


_COMPILED_KERNEL_MIN = 4096  # below this many pairs the call costs more than the passes it saves


def _kernel_compiled(dist: Tensor, re: float) -> Tensor:
    """:func:`kernel` in one compiled pass (its ~6 elementwise passes fused), the torch body's numbers.

    A few pairs (or a ``dist`` of another shape than (E,)) go to the torch body.
    """
    if dist.dim() != 1 or dist.numel() <= _COMPILED_KERNEL_MIN:
        return _kernel_torch(dist, re)
    d = dist.detach().contiguous().numpy()
    out = np.empty_like(d)
    pair_kernels.set_threads()
    _operator_kernels().kernel_weights(d, d.dtype.type(re), d.dtype.type(_R_MIN), out)
    return torch.from_numpy(out)


def _number_density_compiled(
    edge_index: Tensor, dist: Tensor, re: float, num_nodes: int, num_sources: int
) -> Tensor:
    """:func:`number_density` in one compiled pass per target row.

    As :func:`_laplacian_compiled`: edges sorted by target (the torch body takes others); the torch body's
    numbers to the bit without the kernel's ~6 elementwise passes over the edges and the scatter.
    """
    rows = sorted_rows(edge_index, num_sources, num_nodes)
    if rows is None:
        return _number_density_torch(edge_index, dist, re, num_nodes, num_sources)
    d = dist.detach().contiguous().numpy()
    out = np.empty(num_nodes, dtype=d.dtype)
    t = d.dtype.type
    _operator_kernels().density_rows(d, rows[2], t(re), t(_R_MIN), out)
    return torch.from_numpy(out)


def _laplacian_compiled(
    edge_index: Tensor,
    dist: Tensor,
    values: Tensor,
    re: float,
    n0_lap: float | Tensor,
    lam: float | Tensor,
    dim: int,
    num_nodes: int,
) -> Tensor:
    """:func:`laplacian` in one compiled pass per target row.

    Takes edges sorted by target (the neighbour list's graphs), (N,) or (N, C) ``values`` in the dtype of
    ``dist`` with ``num_nodes`` no larger than N, and Python ``n0_lap`` and ``lam``; the torch body takes
    the rest. The same numbers as the torch operations (weights, differences, products and the per-row
    sum in edge order), without the (E, C) gathers and the scatter (several times faster: see
    ``benchmarks/results/operators.md``).
    """
    scale = 2.0 * dim / (lam * n0_lap)
    takes = not isinstance(scale, Tensor) and values.dim() in (1, 2) and values.dtype == dist.dtype
    rows = (
        sorted_rows(edge_index, values.shape[0], num_nodes)
        if takes and num_nodes <= values.shape[0]
        else None
    )
    if rows is None:
        return _laplacian_torch(edge_index, dist, values, re, n0_lap, lam, dim, num_nodes)
    _, src, row_ptr = rows
    vals = values.detach().contiguous().numpy()
    vals2 = vals.reshape(vals.shape[0], -1)
    out = np.empty((num_nodes, vals2.shape[1]), dtype=vals.dtype)
    d = dist.detach().contiguous().numpy()
    t = d.dtype.type  # torch rounds Python scalars to the tensor's dtype
    _operator_kernels().laplacian_rows(src, d, vals2, row_ptr, t(re), t(_R_MIN), t(float(scale)), out)
    return torch.from_numpy(out.reshape((num_nodes, *values.shape[1:])))


_NUMBA = "lagfluid.physics._operators_numba"
pair_kernels.register("mps_kernel", compiled=_kernel_compiled, torch=_kernel_torch, module=_NUMBA)
pair_kernels.register(
    "number_density", compiled=_number_density_compiled, torch=_number_density_torch, module=_NUMBA
)
pair_kernels.register(
    "min_pressure_gradient", compiled=_min_gradient_compiled, torch=_min_gradient_torch, module=_NUMBA
)
pair_kernels.register("laplacian", compiled=_laplacian_compiled, torch=_laplacian_torch, module=_NUMBA)
